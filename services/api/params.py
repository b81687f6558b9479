"""Parsing and validation of HTTP query parameters, done before any work.

Every rejection is an `ApiError` that names the parameter, turned into a JSON 4xx reply by the
app. Limits are checked on the numbers alone, before a grid or array is built.
"""

from __future__ import annotations

import math
import re
from collections.abc import Callable

import numpy as np

from gmm_core import Grid
from gmm_core.occupancy import MAX_VARIANCE, MIN_VARIANCE
from protocol import ProtocolError, check_id
from protocol.messages import MAX_QUERY_POINTS

MIN_RESOLUTION = 0.005  # metres
MAX_RESOLUTION = 10.0
MAX_CELLS = 16_000_000  # per occupancy request
MAX_POINTS = MAX_QUERY_POINTS  # per point request (HTTP and Zenoh)
MAX_COORDINATE = 1e9  # metres from the world origin, for points

# The text formats, stated once: the parsers below accept exactly these (float() alone would also
# take "1_0" or non-ASCII digits), and the OpenAPI schema publishes them as patterns. Blanks are
# spelled [ \t] because \s means different things in Python and in the schema's ECMA regexes.
NUMBER = r"[-+]?(?:[0-9]+(?:\.[0-9]*)?|\.[0-9]+)(?:[eE][-+]?[0-9]+)?"
_B = r"[ \t]*"
NUMBERS_PATTERN = rf"^{_B}{NUMBER}{_B}(?:,{_B}{NUMBER}{_B})*$"
BBOX_PATTERN = rf"^{_B}{NUMBER}{_B}(?:,{_B}{NUMBER}{_B}){{3}}(?:(?:,{_B}{NUMBER}{_B}){{2}})?$"
ID_PATTERN = r"^[A-Za-z0-9_-]{1,64}$"
ROBOTS_PATTERN = rf"^{_B}[A-Za-z0-9_-]{{1,64}}{_B}(?:,{_B}[A-Za-z0-9_-]{{1,64}}{_B})*$"  # no empty name
_NUMBER = re.compile(rf"{_B}{NUMBER}{_B}")
_NON_FINITE = re.compile(rf"{_B}[-+]?(?:nan|inf|infinity){_B}", re.IGNORECASE)  # parsed, to say "finite"
_ROBOTS = re.compile(ROBOTS_PATTERN)


class ApiError(Exception):
    """A bad request: `field` is the parameter at fault; `status` the HTTP code (4xx)."""

    def __init__(self, field: str, message: str, status: int = 422):
        super().__init__(f"{field}: {message}")
        self.field = field
        self.message = message
        self.status = status


def numbers(text: str, field: str) -> np.ndarray:
    """Comma-separated finite numbers."""
    parts = text.split(",")
    if not all(_NUMBER.fullmatch(p) or _NON_FINITE.fullmatch(p) for p in parts):
        raise ApiError(field, f"must be comma-separated numbers, got {text!r:.80}")
    values = np.array([float(p) for p in parts], dtype=np.float64)
    if not np.isfinite(values).all():
        raise ApiError(field, "every number must be finite (no NaN or infinity)")
    return values


def resolution(value: float) -> float:
    if not (math.isfinite(value) and MIN_RESOLUTION <= value <= MAX_RESOLUTION):
        raise ApiError("resolution", f"must be between {MIN_RESOLUTION} and {MAX_RESOLUTION} m, got {value}")
    return float(value)


def variance(value: float) -> float:
    """sigma^2 of Eq. 12's dead band: a Bernoulli variance p (1 - p), so at most 0.25."""
    if not (math.isfinite(value) and MIN_VARIANCE <= value <= MAX_VARIANCE):
        raise ApiError("variance", f"sigma^2 of Eq. 12 must be between {MIN_VARIANCE} and {MAX_VARIANCE}, got {value}")
    return float(value)


def bbox(text: str) -> tuple[np.ndarray, np.ndarray]:
    """`xmin,ymin,xmax,ymax` or `xmin,ymin,zmin,xmax,ymax,zmax` -> (lo, hi)."""
    values = numbers(text, "bbox")
    if len(values) not in (4, 6):
        raise ApiError("bbox", f"must have 4 numbers (2D: xmin,ymin,xmax,ymax) or 6 (3D), got {len(values)}")
    d = len(values) // 2
    lo, hi = values[:d], values[d:]
    if not (hi > lo).all():
        raise ApiError("bbox", "every max must exceed its min (xmin < xmax, ymin < ymax[, zmin < zmax])")
    return lo, hi


def check_dimension(d: int, map_dim: int | None, field: str) -> None:
    if map_dim is not None and d != map_dim:
        raise ApiError(field, f"this map is {map_dim}D, the request is {d}D")


def grid(lo: np.ndarray, hi: np.ndarray, res: float) -> Grid:
    """The grid of docs/ARCHITECTURE.md over [lo, hi]; 422 above MAX_CELLS, counted before anything is built."""
    spans = [(h - l) / res for l, h in zip(lo.tolist(), hi.tolist())]  # Python floats: inf, no warning
    cells = math.prod(max(math.ceil(n - 1e-9), 1) for n in spans) if all(map(math.isfinite, spans)) else math.inf
    if cells > MAX_CELLS:
        raise ApiError(
            "bbox",
            f"{float(min(cells, 1e300)):.4g} cells requested; at most {MAX_CELLS:,} cells per request "
            "(use a coarser resolution or a smaller box)",
        )
    return Grid.from_bbox(lo, hi, res)


def robots(selection: str | list[str] | None) -> tuple[str, ...] | None:
    """None (every robot), or ids as a comma-separated string (none of them empty) or a list; an
    empty list selects none."""
    if selection is None:
        return None
    if isinstance(selection, str) and not _ROBOTS.fullmatch(selection):
        raise ApiError("robots", f"must be comma-separated ids matching [A-Za-z0-9_-]{{1,64}}, got {selection!r:.80}")
    names = [n.strip() for n in selection.split(",")] if isinstance(selection, str) else selection
    try:
        return tuple(sorted({check_id(n, "robots") for n in names}))
    except ProtocolError as e:
        raise ApiError("robots", e.message) from None


def named_robots(
    selected: tuple[str, ...], unknown_of: Callable[[tuple[str, ...]], list[str]], fleet: str
) -> tuple[str, ...]:
    """Robots a request names: some, each one the fleet has had a scan or a pose graph from
    (`unknown_of` lists the others): a name mistyped is refused (404), not answered with a blank map."""
    if not selected:
        raise ApiError("robots", "name at least one robot, or leave robots out to read every robot")
    if unknown := unknown_of(selected):
        raise ApiError("robots", f"no robot {', '.join(unknown)} in fleet {fleet!r}", status=404)
    return selected


def robot(name: str) -> str:
    try:
        return check_id(name, "robot")
    except ProtocolError as e:
        raise ApiError("robot", e.message) from None


def points(values, d: int, field: str) -> np.ndarray:
    """(n, d) finite points from a flat sequence; at most MAX_POINTS."""
    values = np.asarray(values, dtype=np.float64).ravel()
    if len(values) == 0 or len(values) % d:
        raise ApiError(field, f"must hold {d} numbers per point, got {len(values)} numbers")
    if len(values) // d > MAX_POINTS:
        raise ApiError(field, f"{len(values) // d} points requested; at most {MAX_POINTS:,} per request")
    if not np.isfinite(values).all():
        raise ApiError(field, "every number must be finite (no NaN or infinity)")
    if np.abs(values).max() > MAX_COORDINATE:
        raise ApiError(field, f"coordinates must lie within ±{MAX_COORDINATE:g} m")
    return values.reshape(-1, d)
