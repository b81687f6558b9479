"""Who may read the map over HTTP: bearer tokens, checked before any route runs.

With a token file (`--http-tokens`), every request needs `Authorization: Bearer TOKEN` of one of
its clients, except for what holds no map: the viewer's page, /healthz (for probes that carry no
token), and the API's description (/docs, /openapi.json, Swagger UI's files). Unknown paths are
refused like the rest, so nothing about the API is learnt without a token either.

A client limited to some robots reads only their map: a request that names no robots is answered
for its robots alone (tiles, points, the extent, /v1/robots), one that names another robot is
refused with 403, and /metrics (which counts by robot) needs a client of the whole fleet.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

from fastapi import Request, Security
from fastapi.responses import JSONResponse
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer

from services.map_server.tokens import TokenFile

from .params import ApiError

OPEN_PATHS = frozenset({"/", "/healthz", "/docs", "/openapi.json"})
OPEN_PREFIX = "/static/swagger-ui/"
ACCESS = "gmmap.access"  # the ASGI scope key under which the middleware leaves a request's Access
REALM = 'Bearer realm="gmmap"'


@dataclass(frozen=True)
class Access:
    """What one request may read: `robots` None is every robot."""

    client: str | None  # the token file's name for the client; None on a server without tokens
    robots: frozenset[str] | None = None

    def select(self, selected: Sequence[str] | None, field: str = "robots") -> tuple[str, ...] | None:
        """The robots a request reads: those it names (403 if one is not this client's), else all it may."""
        if self.robots is None:
            return None if selected is None else tuple(selected)
        if selected is None:
            return tuple(sorted(self.robots))
        denied = sorted(set(selected) - self.robots)
        if denied:
            raise ApiError(field, f"this token may not read robot {', '.join(denied)}", status=403)
        return tuple(selected)

    def require_fleet(self, what: str) -> None:
        if self.robots is not None:
            raise ApiError("robots", f"{what} needs a token of the whole fleet, not one limited to robots", status=403)


EVERYONE = Access(None)


def _bearer(scope) -> str | None:
    """The token of the first Authorization header, when it is a Bearer one."""
    for name, value in scope["headers"]:
        if name == b"authorization":
            scheme, _, token = value.decode("latin-1").partition(" ")
            return (token.strip() or None) if scheme.lower() == "bearer" else None
    return None


class BearerAuth:
    """ASGI middleware: 401 with the API's JSON error body for a request without a valid token;
    `refused` (a Prometheus counter labelled by reason) counts each."""

    def __init__(self, app, tokens: TokenFile, refused):
        self.app = app
        self.tokens = tokens
        self.refused = refused

    async def __call__(self, scope, receive, send):
        if scope["type"] != "http" or scope["path"] in OPEN_PATHS or scope["path"].startswith(OPEN_PREFIX):
            return await self.app(scope, receive, send)
        token = _bearer(scope)
        client = self.tokens.client(token) if token is not None else None
        if client is not None:
            scope[ACCESS] = Access(client.name, client.robots)
            return await self.app(scope, receive, send)
        if token is None:
            reason, message, challenge = "missing", "a bearer token is required (Authorization: Bearer TOKEN)", REALM
        else:
            reason, message, challenge = "invalid", "the bearer token is not valid", f'{REALM}, error="invalid_token"'
        self.refused.labels(reason).inc()
        reply = JSONResponse(
            {"detail": message, "field": None}, status_code=401, headers={"WWW-Authenticate": challenge}
        )
        await reply(scope, receive, send)


def access_dependency(tokens: TokenFile | None):
    """The FastAPI dependency that gives an endpoint its request's Access. With tokens it also declares
    the bearer scheme in the OpenAPI document (the middleware has checked the token already)."""
    if tokens is None:

        def everyone() -> Access:
            return EVERYONE

        return everyone
    scheme = HTTPBearer(auto_error=False, scheme_name="bearer", description="a token of the server's --http-tokens")

    def token_access(request: Request, _: HTTPAuthorizationCredentials | None = Security(scheme)) -> Access:
        return request.scope[ACCESS]

    return token_access
