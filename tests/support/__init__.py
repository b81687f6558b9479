"""Shared test fixtures and helpers, reached through tests/conftest.py: paths, ports, the process
harness, HTTP helpers and seeded generators. Test modules import from here, never from each other."""
