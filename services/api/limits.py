"""Caps on requests, enforced before the app reads them.

The only endpoint with a body is POST /v1/occupancy/points; without a cap, FastAPI would read and
parse a body of any size before the point limit could say no. A declared Content-Length over
the cap is answered at once; a chunked body is counted as it arrives and refused when it passes
the cap. Both replies are 413 with the API's JSON error body.

A request head (request line with its query string, and headers) is capped by uvicorn's h11
parser, set to MAX_REQUEST_HEAD by the server; over it, or not HTTP at all, the request never
reaches the app: `JsonErrorH11` gives uvicorn's 400 for it the API's JSON error body too.
"""

from __future__ import annotations

import json

import h11
from starlette.exceptions import HTTPException
from uvicorn.protocols.http.h11_impl import H11Protocol

MAX_BODY = 1 << 20  # bytes; 10,000 points in JSON take about 0.5 MB
MAX_REQUEST_HEAD = 1 << 20  # bytes: holds the longest GET the API accepts (10,000 points)


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


class JsonErrorH11(H11Protocol):
    """uvicorn's h11 protocol (`uvicorn.Config(http=...)`), its 400 for a request h11 cannot parse
    in the API's JSON error body rather than plain text."""

    def send_400_response(self, msg: str) -> None:
        why = f"{msg} (not HTTP, or a request head over {MAX_REQUEST_HEAD:,} bytes)"
        body = json.dumps({"detail": why, "field": None}).encode()
        headers = [
            (b"content-type", b"application/json"),
            (b"content-length", str(len(body)).encode()),
            (b"connection", b"close"),
        ]
        for event in (h11.Response(status_code=400, headers=headers), h11.Data(data=body), h11.EndOfMessage()):
            self.transport.write(self.conn.send(event))
        self.transport.close()
