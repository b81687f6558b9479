"""The map an export writes: a probability grid read from a `gmmap replay --out` npz, or fetched
from a map server's HTTP API."""

from __future__ import annotations

import io
import json
import math
import time
import urllib.error
import zipfile
from dataclasses import dataclass
from pathlib import Path
from urllib.parse import quote

import numpy as np

from gmm_core import Grid
from services.api.params import MAX_CELLS
from services.http_client import HttpClient

MAX_EXPORT_CELLS = 8 * MAX_CELLS  # 512 MB of float32 probabilities in this process
REQUEST_TIMEOUT_S = 300.0  # one request of up to MAX_CELLS cells, traced by the server
BUSY_RETRIES = 10  # 503 answers (tracers saturated) waited out, each for its Retry-After


@dataclass(frozen=True)
class ExportMap:
    """Probabilities `prob` ([iy, ix] or [iz, iy, ix], float32) over `grid`."""

    grid: Grid
    prob: np.ndarray


def check_bbox(values: list[float], dim: int) -> tuple[np.ndarray, np.ndarray]:
    """(lo, hi) of `xmin,ymin,xmax,ymax` (2D) or `xmin,ymin,zmin,xmax,ymax,zmax` (3D) for a `dim`D map."""
    if len(values) != 2 * dim:
        spelled = "xmin,ymin,xmax,ymax" if dim == 2 else "xmin,ymin,zmin,xmax,ymax,zmax"
        raise ValueError(f"bbox: this map is {dim}D: give {2 * dim} numbers, {spelled}; got {len(values)}")
    box = np.asarray(values, dtype=np.float64)
    if not np.isfinite(box).all():
        raise ValueError("bbox: every number must be finite")
    lo, hi = box[:dim], box[dim:]
    if not (hi > lo).all():
        raise ValueError("bbox: every max must exceed its min")
    return lo, hi


def read_npz(path: str | Path) -> ExportMap:
    """The map of a `gmmap replay --out` file: `prob`, `origin` (min corner) and `resolution`."""
    try:
        data = np.load(path, allow_pickle=False)
    except (zipfile.BadZipFile, ValueError) as error:
        raise ValueError(f"--from: {path} is not an npz file ({error})") from None
    if not isinstance(data, np.lib.npyio.NpzFile):  # a lone .npy array
        raise ValueError(f"--from: {path} is not an npz file (one array, not prob, origin and resolution)")
    with data:
        fields = {name: data[name] for name in ("prob", "origin", "resolution") if name in data.files}
    missing = [name for name in ("prob", "origin", "resolution") if name not in fields]
    if missing:
        raise ValueError(f"--from: {path} lacks {', '.join(missing)} (write it with `gmmap replay --out`)")
    prob = fields["prob"]
    if prob.ndim not in (2, 3) or prob.dtype.kind != "f":
        raise ValueError(f"--from: {path}: prob must be a 2D or 3D float array, got {prob.dtype} {prob.shape}")
    if not (np.isfinite(prob).all() and (prob >= 0).all() and (prob <= 1).all()):
        raise ValueError(f"--from: {path}: prob must hold probabilities in [0, 1]")
    try:
        grid = Grid(fields["origin"], float(fields["resolution"]), tuple(reversed(prob.shape)))
    except (TypeError, ValueError) as error:
        raise ValueError(f"--from: {path}: {error}") from None
    return ExportMap(grid, prob.astype(np.float32, copy=False))


def crop(source: ExportMap, lo: np.ndarray, hi: np.ndarray) -> ExportMap:
    """The cells of `source` that reach into the box [lo, hi] (whole cells: no resampling)."""
    grid = source.grid
    first = np.floor((lo - grid.origin) / grid.resolution + 1e-9).astype(np.int64)
    stop = np.ceil((hi - grid.origin) / grid.resolution - 1e-9).astype(np.int64)
    first, stop = np.maximum(first, 0), np.minimum(stop, grid.shape)
    if (stop <= first).any():
        lo_text, hi_text = np.round(grid.origin, 6).tolist(), np.round(grid.upper, 6).tolist()
        raise ValueError(f"bbox: outside the map, which spans {lo_text} .. {hi_text}")
    window = tuple(slice(int(a), int(b)) for a, b in zip(reversed(first), reversed(stop)))
    return ExportMap(
        Grid(grid.origin + first * grid.resolution, grid.resolution, tuple(stop - first)), source.prob[window]
    )


def on_lattice(lo: np.ndarray, hi: np.ndarray, resolution: float) -> tuple[np.ndarray, np.ndarray]:
    """[lo, hi] grown to whole multiples of `resolution` from the world origin (OctoMap's voxels)."""
    return np.floor(lo / resolution + 1e-9) * resolution, np.ceil(hi / resolution - 1e-9) * resolution


def _get(client: HttpClient, path: str):
    """Body and headers of GET `path`; a 503 (tracers saturated) waited out; other errors a ValueError
    with the server's own words."""
    for _ in range(BUSY_RETRIES + 1):
        try:
            return client.fetch(path, REQUEST_TIMEOUT_S)
        except urllib.error.HTTPError as error:
            body = error.read()
            retry_after = error.headers.get("Retry-After")
            if error.code == 503 and retry_after is not None:
                time.sleep(float(retry_after))
                continue
            try:
                detail = json.loads(body)["detail"]
            except (ValueError, KeyError, TypeError):
                detail = body[:200].decode("utf-8", "replace")
            raise ValueError(f"--url: {client.base}{path.split('?')[0]} answered {error.code}: {detail}") from None
        except urllib.error.URLError as error:
            raise ValueError(f"--url: cannot reach {client.base}: {error.reason}") from None
    raise ValueError(f"--url: {client.base} stayed busy (503) through {BUSY_RETRIES} retries; try again later")


def map_dimension(client: HttpClient) -> tuple[int, np.ndarray, np.ndarray]:
    """The dimension and box (lo, hi) of the server's map; a ValueError when it is empty."""
    extent = json.loads(_get(client, "/v1/map/extent")[0])
    if extent is None:
        raise ValueError(f"--url: the map at {client.base} is empty: nothing to export")
    return int(extent["dim"]), np.asarray(extent["lo"], float), np.asarray(extent["hi"], float)


def fetch(
    client: HttpClient, lo: np.ndarray, hi: np.ndarray, resolution: float, max_cells: int = MAX_CELLS
) -> ExportMap:
    """The server's probabilities over Grid.from_bbox(lo, hi, resolution), fetched as npy in slabs
    along the slowest array axis (z in 3D, y in 2D) of at most `max_cells` cells each (the API's limit)."""
    grid = Grid.from_bbox(lo, hi, resolution)
    if grid.n_cells > MAX_EXPORT_CELLS:
        raise ValueError(
            f"bbox: {grid.n_cells:,} cells at {resolution} m; an export holds at most {MAX_EXPORT_CELLS:,} "
            "(give a smaller --bbox or a coarser --resolution)"
        )
    axis = grid.dim - 1  # x, y[, z]: the last is the slowest in array order
    per_layer = grid.n_cells // grid.shape[axis]
    if per_layer > max_cells:
        raise ValueError(f"bbox: one layer holds {per_layer:,} cells, over the server's {max_cells:,} per request")
    step = max_cells // per_layer
    slabs = []
    for start in range(0, grid.shape[axis], step):
        stop = min(start + step, grid.shape[axis])
        slab_lo, slab_hi = grid.origin.copy(), grid.origin + np.asarray(grid.shape) * resolution
        slab_lo[axis] = grid.origin[axis] + start * resolution
        slab_hi[axis] = grid.origin[axis] + stop * resolution
        box = ",".join(repr(float(v)) for v in (*slab_lo, *slab_hi))
        body, headers = _get(client, f"/v1/occupancy?bbox={quote(box)}&resolution={resolution!r}&format=npy&max_age=0")
        prob = np.load(io.BytesIO(body), allow_pickle=False)
        expected = (stop - start, *grid.array_shape[1:])
        if prob.shape != expected:
            raise ValueError(f"--url: asked for {expected} cells at {box}, the server sent {prob.shape}")
        slabs.append(prob)
    return ExportMap(grid, np.concatenate(slabs, axis=0) if len(slabs) > 1 else slabs[0])


def check_resolution(asked: float | None, have: float) -> None:
    """--from cannot resample: a --resolution other than the file's is refused."""
    if asked is not None and not math.isclose(asked, have, rel_tol=1e-9):
        raise ValueError(
            f"resolution: the npz holds a {have!r} m grid and --from does not resample; "
            f"export from a server (--url) to get {asked!r} m"
        )
