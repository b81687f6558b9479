"""A cap on request bodies, enforced before the app reads them.

The only endpoint with a body is POST /v1/occupancy/points; without a cap, FastAPI would read and
parse a body of any size before the point limit could say no. A declared Content-Length over
the cap is answered at once; a chunked body is counted as it arrives and refused when it passes
the cap. Both replies are 413 with the API's JSON error body.
"""

from __future__ import annotations

import json

from starlette.exceptions import HTTPException

MAX_BODY = 1 << 20  # bytes; 10,000 points in JSON take about 0.5 MB


def _too_large(limit: int) -> HTTPException:
    return HTTPException(413, f"request body exceeds {limit:,} bytes")


class BodyLimit:
    """ASGI middleware: 413 for bodies over `max_bytes`."""

    def __init__(self, app, max_bytes: int = MAX_BODY):
        self.app = app
        self.max_bytes = max_bytes

    async def __call__(self, scope, receive, send):
        if scope["type"] != "http":
            return await self.app(scope, receive, send)
        declared = dict(scope["headers"]).get(b"content-length")
        if declared is not None and declared.isdigit() and int(declared) > self.max_bytes:
            return await self._reply(send)
        received = 0

        async def counted():
            nonlocal received
            message = await receive()
            if message["type"] == "http.request":
                received += len(message.get("body", b""))
                if received > self.max_bytes:
                    # Raised inside the endpoint's body read: the app's handler turns it into JSON.
                    raise _too_large(self.max_bytes)
            return message

        await self.app(scope, counted, send)

    async def _reply(self, send) -> None:
        error = _too_large(self.max_bytes)
        body = json.dumps({"detail": error.detail, "field": None}).encode()
        # Connection: close, since the unread body would otherwise be taken for the next request.
        await send(
            {
                "type": "http.response.start",
                "status": 413,
                "headers": [
                    (b"content-type", b"application/json"),
                    (b"content-length", str(len(body)).encode()),
                    (b"connection", b"close"),
                ],
            }
        )
        await send({"type": "http.response.body", "body": body})
