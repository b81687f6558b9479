"""The HTTP API and web viewer of a map server: `create_app(state)` gives the FastAPI app."""

from .app import create_app

__all__ = ["create_app"]
