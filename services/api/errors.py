"""The HTTP API's error replies: their bodies and status codes as OpenAPI shows them (app.py adds them
to its routes), and the JSON replies its exception handlers answer with."""

from __future__ import annotations

from fastapi import FastAPI
from fastapi.responses import JSONResponse
from pydantic import BaseModel
from starlette.routing import Match

from services.map_server.tracers import TracersSaturated, TracingStopped

from .limits import MAX_BODY


class ErrorBody(BaseModel):
    """Every error reply: what is wrong, and the parameter at fault (null when none is)."""

    detail: str
    field: str | None


class BusyBody(ErrorBody):
    """A request shed under load: why (`reason`), and when to ask again (also the Retry-After header)."""

    reason: str
    retry_after: int


ERRORS = {
    status: {"model": ErrorBody, "description": text}
    for status, text in (
        (400, "The body is not valid JSON"),
        (404, "No such robot or path"),
        (413, f"Request body over {MAX_BODY:,} bytes"),
        (422, "A parameter is missing, malformed or over a limit; `field` names it"),
    )
}
STOPPING = {
    503: {
        "model": BusyBody,
        "description": "The server is stopping (`reason` server_stopping): the request's trace was cut off; "
        "ask again after Retry-After seconds",
    }
}
AUTH_ERRORS = {
    status: {"model": ErrorBody, "description": text}
    for status, text in (
        (401, "No bearer token, or not one of the server's (WWW-Authenticate: Bearer)"),
        (403, "The token may not read a robot the request names (`field` names the parameter)"),
    )
}


def allowed_methods(app: FastAPI, scope) -> set[str]:
    """Every method that some route serves at the request's path."""
    return {
        m
        for route in app.router.routes
        if route.matches(scope)[0] is not Match.NONE
        for m in getattr(route, "methods", None) or ()
    }


def error(status: int, field: str | None, message: str, headers=None) -> JSONResponse:
    return JSONResponse(
        {"detail": f"{field}: {message}" if field else message, "field": field}, status_code=status, headers=headers
    )


def busy(refusal: TracersSaturated | TracingStopped) -> JSONResponse:
    """503 with BusyBody: the tracers would not take the request's trace, or were closed under it."""
    body = {"detail": str(refusal), "field": None, "reason": refusal.reason, "retry_after": refusal.retry_after}
    return JSONResponse(body, status_code=503, headers={"Retry-After": str(refusal.retry_after)})
