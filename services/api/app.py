"""The HTTP API of a map server and its web viewer (OpenAPI at /docs).

Endpoints that reconstruct occupancy or read the fleet map are plain `def` functions: FastAPI
runs them in its threadpool, so CPU-bound reconstruction (and waiting for the map's lock) never
blocks the event loop. Every bad parameter is answered with JSON and a 4xx code naming it.
With a token file, who may read what is checked first (auth.py).
"""

from __future__ import annotations

import io
import threading
import time
from enum import Enum
from pathlib import Path
from typing import Literal

import fastapi_offline
import numpy as np
from fastapi import Depends, FastAPI, Query, Request
from fastapi import Path as PathParam
from fastapi.exceptions import RequestValidationError
from fastapi.middleware.cors import CORSMiddleware
from fastapi.openapi.docs import get_swagger_ui_html
from fastapi.responses import HTMLResponse, JSONResponse, Response
from pydantic import BaseModel, ConfigDict, Field
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.staticfiles import StaticFiles

from gmm_core.occupancy import DEFAULT_VARIANCE
from protocol import MapReply, encode
from services.export.octomap_tree import NOT_3D, bt_bytes, ot_bytes, reach_problem
from services.export.pgm import pgm_bytes
from services.export.ply import ply_bytes
from services.map_server.tiles import MAX_STALE_S, PATIENCE_S
from services.map_server.tokens import TokenFile
from services.map_server.tracers import TracersSaturated, TracingStopped
from services.render import occupancy_png, probability_png, top_down_classes

from . import params
from .auth import Access, BearerAuth, access_dependency
from .encoded import EncodedTiles
from .errors import AUTH_ERRORS, ERRORS, STOPPING, BusyBody, allowed_methods, busy, error
from .limits import MAX_BODY, BodyLimit
from .params import ApiError
from .points import evaluate

VIEWER = Path(__file__).with_name("static") / "viewer.html"
# Swagger UI's files as the fastapi-offline package ships them (a Swagger UI that reads OpenAPI 3.1).
SWAGGER_FILES = Path(fastapi_offline.__file__).with_name("static")
SWAGGER_STATIC = "/static/swagger-ui"
GRID_HEADERS = ["X-Grid-Origin", "X-Grid-Resolution", "X-Grid-Shape"]
EXPOSED_HEADERS = GRID_HEADERS + [
    "X-Map-Age",
    "X-Map-Samples-Per-Cell",
    "Retry-After",
]  # to a viewer on another origin (CORS)
VIEWER_DEFAULT_VARIANCE = "__DEFAULT_VARIANCE__"  # in viewer.html, replaced by DEFAULT_VARIANCE when served


class Format(str, Enum):
    npy = "npy"
    png = "png"
    msgpack = "msgpack"
    pgm = "pgm"
    bt = "bt"
    ot = "ot"
    ply = "ply"


class Shade(str, Enum):
    """What a PNG shows: the Eq. 12 classes, or grey = 1 - p."""

    classes = "classes"
    probability = "probability"


MEDIA_TYPES = {
    Format.npy: "application/x-npy",
    Format.png: "image/png",
    Format.msgpack: "application/msgpack",
    Format.pgm: "image/x-portable-graymap",
    Format.bt: "application/octet-stream",
    Format.ot: "application/octet-stream",
    Format.ply: "application/octet-stream",
}
EXPORTS = {Format.pgm, Format.bt, Format.ot, Format.ply}  # classified by Eq. 12, as `gmmap export` writes them


# Schema constraints are published for clients and API fuzzers; the checks themselves are in
# `params`, so every rejection keeps one wording. Constraints between values (lo < hi, the cell
# and point limits, one dimension per request) cannot be said in OpenAPI and are only in `params`.
def _range(lo: float, hi: float) -> dict:
    return {"json_schema_extra": {"minimum": lo, "maximum": hi}}


Method = Literal["auto", "analytic", "mc"]  # of /v1/occupancy/points: services/api/points.py
ROBOTS_DESCRIPTION = "comma-separated robot ids; every robot when absent; 404 for one the fleet has had nothing from"
METHOD_DESCRIPTION = (
    "mc: Monte-Carlo grids; analytic: the expected evidence at each point's cell (Eq. 3-10), per "
    "point; auto: analytic where it is cheaper (few scattered points), else mc"
)


class PointsBody(BaseModel):
    model_config = ConfigDict(strict=True)  # JSON numbers only: no true for 1.0, no "0.1" for 0.1

    points: list[list[float]] = Field(
        json_schema_extra={
            "minItems": 1,
            "maxItems": params.MAX_POINTS,
            "items": {"type": "array", "items": {"type": "number"}, "minItems": 2, "maxItems": 3},
        }
    )
    resolution: float = Field(**_range(params.MIN_RESOLUTION, params.MAX_RESOLUTION))
    robots: list[str] | None = Field(None, json_schema_extra={"minItems": 1, "items": {"pattern": params.ID_PATTERN}})
    method: Method = "auto"


def create_app(
    state,
    *,
    cors_origins: list[str] | None = None,
    default_variance: float = DEFAULT_VARIANCE,
    tokens: TokenFile | None = None,
) -> FastAPI:
    """The FastAPI app over one server's `state` (a ServerState: fleet, fleet_map, metrics).

    CORS is off unless `cors_origins` is given. `default_variance` is sigma^2 of Eq. 12 for PNGs that
    ask for none (the server's reconstruction.variance). With `tokens`, every request but those of
    auth.OPEN_PATHS needs a bearer token of that file, and reads only its client's robots.
    """
    default_variance = params.variance(default_variance)
    app = FastAPI(
        title="gmmap map server",
        version="1",
        description=(
            "Occupancy of a robot fleet's shared Gaussian-mixture map, at any region and resolution. "
            "Grids follow docs/ARCHITECTURE.md: origin is the min corner, arrays are indexed [iy, ix] or [iz, iy, ix], "
            "cell centre = origin + (index + 0.5) * resolution, 0.5 where nothing was observed."
        ),
        responses=ERRORS | AUTH_ERRORS if tokens is not None else ERRORS,
        docs_url=None,
        redoc_url=None,
    )  # /docs is served below from local files: no CDN on a robot's network
    app.add_middleware(BodyLimit, max_bytes=MAX_BODY)
    if tokens is not None:  # outside BodyLimit: a request without a token is refused before its body is read
        app.add_middleware(BearerAuth, tokens=tokens, refused=state.metrics.http_refused)
    if cors_origins:
        app.add_middleware(
            CORSMiddleware, allow_origins=cors_origins, allow_methods=["GET", "POST"], expose_headers=EXPOSED_HEADERS
        )
    fmap = state.fleet_map
    access = access_dependency(tokens)
    viewer_html = VIEWER.read_text(encoding="utf-8").replace(VIEWER_DEFAULT_VARIANCE, repr(default_variance))
    encoded = EncodedTiles()
    synced = {"hits": 0, "misses": 0, "updates": 0, "stale": 0, "thinned_updates": 0}
    sync_lock = threading.Lock()

    @app.exception_handler(ApiError)
    async def api_error(request: Request, exc: ApiError):
        if exc.status == 403:
            state.metrics.http_refused.labels("forbidden").inc()
        return error(exc.status, exc.field, exc.message)

    @app.exception_handler(RequestValidationError)
    async def validation_error(request: Request, exc: RequestValidationError):
        first = exc.errors()[0] if exc.errors() else {}
        if first.get("type") == "json_invalid":  # FastAPI's loc is ("body", the character where parsing stopped)
            where = f"{first['ctx']['error']} at character {first['loc'][-1]}"
            return error(400, None, f"the body is not valid JSON: {where}")
        if first.get("type") == "missing" and tuple(first.get("loc", ())) == ("body",):
            return error(422, None, "the body is empty: a JSON object is required, as the OpenAPI schema gives it")
        loc = [str(p) for p in first.get("loc", ()) if p not in ("query", "path", "body")]
        return error(422, ".".join(loc) or None, first.get("msg", "invalid request"))

    @app.exception_handler(StarletteHTTPException)
    async def http_error(request: Request, exc: StarletteHTTPException):
        headers = getattr(exc, "headers", None)
        if exc.status_code == 405:  # Starlette lists the first route's methods; GET and POST share a path
            headers = {"Allow": ", ".join(sorted(allowed_methods(app, request.scope)))}
        return error(exc.status_code, None, str(exc.detail), headers)

    @app.exception_handler(TracingStopped)
    async def stopping(request: Request, exc: TracingStopped):
        return busy(exc)  # a handled exception: no traceback in the log, unlike those of internal_error

    @app.exception_handler(Exception)
    async def internal_error(request: Request, exc: Exception):
        return error(500, None, f"internal error: {type(exc).__name__}")

    def selection(who: Access, names: str | list[str] | None) -> tuple[str, ...] | None:
        """The robots a request reads (params.robots, then Access.select: 403 before 404, so a limited
        token learns nothing of other robots); those it names must be some, and of the fleet."""
        selected = who.select(params.robots(names))
        if names is None:
            return selected  # a limited token's robots may not have sent anything yet
        return params.named_robots(selected, fmap.unknown_robots, state.fleet)

    def occupancy_of(grid, robots, max_age: float = MAX_STALE_S):
        try:
            return fmap.occupancy_answer(grid, robots, may_shed=True, max_age=max_age, patience=PATIENCE_S)
        except ValueError as e:  # the map's own checks (a dimension that changed meanwhile)
            raise ApiError("bbox", str(e)) from None

    def shed(saturated: TracersSaturated) -> JSONResponse:
        state.metrics.tile_answers.labels("shed").inc()
        return busy(saturated)

    # -- occupancy ------------------------------------------------------------------------
    @app.get(
        "/v1/occupancy",
        summary="Occupancy probabilities of a box at a resolution",
        responses={
            200: {
                "content": {m: {} for m in MEDIA_TYPES.values()},
                "description": "npy: float32 probabilities (ny, nx) or (nz, ny, nx); png: 8-bit grey "
                "image seen from above, north up (see `shade`); msgpack: a protocol "
                "MapReply of the probabilities; pgm: the ROS map_server image of the Eq. 12 classes (occupied 0, "
                "free 254, unknown 205; its YAML's origin is X-Grid-Origin); bt: an OctoMap binary tree of the "
                "occupied and free cells (3D maps; each cell in the OctoMap voxel holding its centre); ot: the "
                "same as a full OctoMap tree whose leaves hold the MAP log-odds log(p / (1 - p)); ply: the "
                "occupied cell centres with their probability. "
                "X-Map-Age: seconds the state served has been out of date "
                f"(0: up to date; at most max_age when a previous state is served: under load, or while "
                f"an update takes over {PATIENCE_S:g} s). X-Map-Samples-Per-Cell: the fewest Monte-Carlo samples "
                "per cell any scan of the state is counted with (fewer than the map's after updates while the "
                "tracers were busy, until they are refined)",
            },
            503: {
                "model": BusyBody,
                "description": "The tracers are saturated and the tile has no state recent enough to serve "
                "(`reason` tracers_saturated: nothing was queued), or the server is stopping (server_stopping); "
                "ask again after Retry-After seconds",
            },
        },
    )
    def occupancy(
        bbox: str = Query(
            ...,
            description="xmin,ymin,xmax,ymax (2D) or xmin,ymin,zmin,xmax,ymax,zmax (3D), metres",
            json_schema_extra={"pattern": params.BBOX_PATTERN},
        ),
        resolution: float = Query(
            ...,
            description=f"cell size in metres, {params.MIN_RESOLUTION} to "
            f"{params.MAX_RESOLUTION}; at most {params.MAX_CELLS:,} cells",
            **_range(params.MIN_RESOLUTION, params.MAX_RESOLUTION),
        ),
        format: Format = Query(Format.npy, description="npy, png, msgpack, pgm, bt (3D), ot (3D) or ply"),
        robots: str | None = Query(
            None,
            description=ROBOTS_DESCRIPTION,
            json_schema_extra={"pattern": params.ROBOTS_PATTERN},
        ),
        shade: Shade = Query(
            Shade.classes,
            description=(
                "png only. classes: the classification of Eq. 12 (free white, occupied black, unknown grey); 3D maps "
                "classify each voxel, then a column is occupied if any voxel is, free if none is and some is free, "
                "else unknown (a voxel in the dead band counts as unseen). probability: grey = 1 - p; a 3D column "
                "shows its most occupied voxel if one is above 0.5, else its freest"
            ),
        ),
        variance: float = Query(
            default_variance,
            description=(
                f"png with shade=classes, pgm, bt, ot and ply: sigma^2 of Eq. 12, "
                f"{params.MIN_VARIANCE} to {params.MAX_VARIANCE} "
                f"(the variance p (1 - p) of a cell's Bernoulli occupancy). A cell is free for "
                f"p <= (1 - sqrt(1 - 4 sigma^2)) / 2, occupied for p >= (1 + sqrt(1 - 4 sigma^2)) / 2, unknown between "
                f"and at 0.5 (nothing seen); a smaller sigma^2 widens that dead band. Default: the server's (the "
                f"project's {DEFAULT_VARIANCE}, thresholds 0.3 and 0.7, unless set)"
            ),
            **_range(params.MIN_VARIANCE, params.MAX_VARIANCE),
        ),
        max_age: float = Query(
            MAX_STALE_S,
            description=f"the oldest state to serve: seconds it has been out of date, 0 to {MAX_STALE_S:g}; 0 "
            "waits for every change stored before the request (and may be shed under load)",
            **_range(0.0, MAX_STALE_S),
        ),
        who: Access = Depends(access),
    ) -> Response:
        start = time.perf_counter()
        if not 0.0 <= max_age <= MAX_STALE_S:
            raise ApiError("max_age", f"must lie in [0, {MAX_STALE_S:g}] seconds, got {max_age}")
        res = params.resolution(resolution)
        lo, hi = params.bbox(bbox)
        params.check_dimension(len(lo), fmap.dim, "bbox")
        grid = params.grid(lo, hi, res)
        if format in (Format.bt, Format.ot):
            if grid.dim != 3:
                raise ApiError("format", NOT_3D.format(fmt=format.value, dim=grid.dim))
            if problem := reach_problem(grid):
                raise ApiError("bbox", problem)
        selected = selection(who, robots)  # the reply's key below: per client's robots
        sigma2 = params.variance(variance)
        if format is Format.png:
            picture = (shade, sigma2 if shade is Shade.classes else None)
        else:  # the exports classify by Eq. 12 too
            picture = (format, sigma2) if format in EXPORTS else None
        try:
            answer = occupancy_of(grid, selected, max_age)
        except TracersSaturated as saturated:
            return shed(saturated)
        prob = answer.prob
        reply = (
            format,
            picture,
            tuple(grid.origin),
            grid.resolution,
            grid.shape,
            None if selected is None else tuple(selected),
        )
        body = encoded.get(reply, prob)
        if body is None:
            if format is Format.npy:
                buffer = io.BytesIO()
                np.save(buffer, np.asarray(prob, dtype=np.float32))
                body = buffer.getvalue()
            elif format is Format.png:
                body = occupancy_png(prob, sigma2) if shade is Shade.classes else probability_png(prob)
            elif format is Format.pgm:
                body = pgm_bytes(top_down_classes(prob, sigma2))
            elif format is Format.bt:
                body = bt_bytes(prob, grid, sigma2)
            elif format is Format.ot:
                body = ot_bytes(prob, grid, sigma2)
            elif format is Format.ply:
                body = ply_bytes(prob, grid, sigma2)
            else:
                body = encode(MapReply(state.fleet, grid.origin, grid.resolution, prob))
            encoded.put(reply, prob, body)
        state.metrics.query_seconds.observe(time.perf_counter() - start)
        headers = {
            "X-Grid-Origin": ",".join(repr(float(v)) for v in grid.origin),
            "X-Grid-Resolution": repr(grid.resolution),
            "X-Grid-Shape": ",".join(str(n) for n in grid.array_shape),
            "X-Map-Age": f"{answer.age:.6f}",
            "X-Map-Samples-Per-Cell": f"{answer.samples_per_cell:g}",
        }
        state.metrics.tile_answers.labels(answer.kind).inc()
        state.metrics.tile_age.observe(answer.age)
        return Response(body, media_type=MEDIA_TYPES[format], headers=headers)

    def points_reply(pts: np.ndarray, res: float, selected, field: str, method: str) -> dict:
        start = time.perf_counter()
        try:
            prob, method = evaluate(fmap, pts, res, selected, method)
        except ValueError as e:
            raise ApiError(field, str(e)) from None
        state.metrics.query_seconds.observe(time.perf_counter() - start)
        return {"resolution": res, "points": pts.tolist(), "probabilities": prob.tolist(), "method": method}

    @app.get(
        "/v1/occupancy/points", summary="Occupancy of the cell of size R centred on each point", responses=STOPPING
    )
    def occupancy_points(
        xy: str | None = Query(
            None, description="x1,y1,x2,y2,... (2D maps)", json_schema_extra={"pattern": params.NUMBERS_PATTERN}
        ),
        xyz: str | None = Query(
            None, description="x1,y1,z1,... (3D maps)", json_schema_extra={"pattern": params.NUMBERS_PATTERN}
        ),
        resolution: float = Query(
            ..., description="cell size in metres", **_range(params.MIN_RESOLUTION, params.MAX_RESOLUTION)
        ),
        robots: str | None = Query(
            None,
            description=ROBOTS_DESCRIPTION,
            json_schema_extra={"pattern": params.ROBOTS_PATTERN},
        ),
        method: Method = Query("auto", description=METHOD_DESCRIPTION),
        who: Access = Depends(access),
    ) -> dict:
        if (xy is None) == (xyz is None):
            raise ApiError("xy", "give exactly one of xy (2D) or xyz (3D)")
        field, text, d = ("xy", xy, 2) if xy is not None else ("xyz", xyz, 3)
        res = params.resolution(resolution)
        if text.count(",") >= params.MAX_POINTS * d:  # before parsing
            raise ApiError(field, f"at most {params.MAX_POINTS:,} points per request")
        params.check_dimension(d, fmap.dim, field)
        pts = params.points(params.numbers(text, field), d, field)
        return points_reply(pts, res, selection(who, robots), field, method)

    @app.post(
        "/v1/occupancy/points", summary="Occupancy at points given in a JSON body (for long lists)", responses=STOPPING
    )
    def occupancy_points_post(body: PointsBody, who: Access = Depends(access)) -> dict:
        res = params.resolution(body.resolution)
        d = len(body.points[0]) if body.points else 0
        if d not in (2, 3) or any(len(p) != d for p in body.points):
            raise ApiError("points", "must be a non-empty list of [x, y] or [x, y, z]")
        params.check_dimension(d, fmap.dim, "points")
        pts = params.points(body.points, d, "points")
        return points_reply(pts, res, selection(who, body.robots), "points", body.method)

    # -- robots and the map -----------------------------------------------------------------
    @app.get("/v1/robots", summary="Every robot of the fleet")
    def robots_list(who: Access = Depends(access)) -> list[dict]:
        return [r for r in fmap.robots() if who.robots is None or r["robot"] in who.robots]

    @app.get("/v1/robots/{robot}/trajectory", summary="World positions of a robot's nodes, in node order")
    def trajectory(
        robot: str = PathParam(..., json_schema_extra={"pattern": params.ID_PATTERN}), who: Access = Depends(access)
    ) -> list[list[float]]:
        name = params.robot(robot)
        who.select((name,), "robot")  # 403 before 404: a limited token learns nothing of other robots
        if fmap.unknown_robots((name,)):
            raise ApiError("robot", f"no robot {name!r} in fleet {state.fleet!r}", status=404)
        return fmap.trajectory(name).tolist()

    @app.get("/v1/map/extent", summary="World box reached by every node, or null for an empty map")
    def extent(who: Access = Depends(access)) -> dict | None:
        box = fmap.extent(who.robots)
        if box is None:
            return None
        return {"dim": len(box[0]), "lo": box[0].tolist(), "hi": box[1].tolist()}

    # -- operations ---------------------------------------------------------------------------
    @app.get("/healthz", summary="Liveness")
    async def healthz() -> dict:
        return {"status": "ok", "fleet": state.fleet}

    @app.get("/metrics", summary="Prometheus metrics", response_class=Response)
    def metrics(who: Access = Depends(access)) -> Response:
        who.require_fleet("/metrics")  # it counts bytes by robot
        stats = fmap.cache_stats()
        state.metrics.tracer_queue.set(stats["trace_queued"])
        with sync_lock:  # the map counts; the Prometheus counters follow by the difference
            for key, counter in (
                ("hits", state.metrics.cache_hits),
                ("misses", state.metrics.cache_misses),
                ("updates", state.metrics.cache_updates),
                ("stale", state.metrics.cache_stale),
                ("thinned_updates", state.metrics.cache_thinned),
            ):
                if stats[key] > synced[key]:
                    counter.inc(stats[key] - synced[key])
                    synced[key] = stats[key]
        return Response(state.metrics.render(), media_type="text/plain; version=0.0.4; charset=utf-8")

    @app.get("/", response_class=HTMLResponse, include_in_schema=False)
    async def viewer() -> HTMLResponse:
        return HTMLResponse(viewer_html)

    app.mount(SWAGGER_STATIC, StaticFiles(directory=SWAGGER_FILES), name="swagger-ui")

    @app.get("/docs", response_class=HTMLResponse, include_in_schema=False)
    async def docs() -> HTMLResponse:
        return get_swagger_ui_html(
            openapi_url=app.openapi_url,
            title=f"{app.title} - API",
            swagger_js_url=f"{SWAGGER_STATIC}/swagger-ui-bundle.js",
            swagger_css_url=f"{SWAGGER_STATIC}/swagger-ui.css",
            swagger_favicon_url=f"{SWAGGER_STATIC}/favicon.png",
        )

    return app
