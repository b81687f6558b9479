"""gmmap processes: agent, map server, HTTP API, simulator, CLI."""
