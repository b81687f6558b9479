"""`gmmap export (--url http://HOST:PORT | --from MAP.npz) --format pgm|bt|ot|ply [--bbox ...]
[--resolution R] [--variance S2] --out PATH`."""

from __future__ import annotations

import math
from urllib.parse import urlsplit

import numpy as np

from gmm_core.occupancy import FREE, OCCUPIED, classify
from services.http_client import HttpClient, read_token, tls_context

from . import OCTOMAP_FORMATS, check_dimension, write_export
from .octomap_tree import lattice_offset
from .sources import ExportMap, check_bbox, check_resolution, crop, fetch, map_dimension, on_lattice, read_npz

DEFAULT_URL_RESOLUTION = 0.1  # m, for --url without --resolution (the ROS map's default in issue 14)


def client_for(url: str, token_file: str | None, ca_file: str | None) -> HttpClient:
    """An HttpClient of `url` (http://HOST:PORT or https://HOST:PORT), with the token and CA given."""
    parts = urlsplit(url)
    if parts.scheme not in ("http", "https") or not parts.netloc or parts.path not in ("", "/") or parts.query:
        raise ValueError(f"--url: must be http://HOST:PORT or https://HOST:PORT, got {url!r}")
    if ca_file:
        tls_context(ca_file)  # a bad CA file is said now, not at the first request
    return HttpClient(f"{parts.scheme}://{parts.netloc}", read_token(token_file) if token_file else None, ca_file)


def load_map(
    url: str | None,
    npz: str | None,
    fmt: str,
    bbox: list[float] | None,
    resolution: float | None,
    token_file: str | None = None,
    ca_file: str | None = None,
) -> ExportMap:
    """The map to export: fetched from a server at `resolution` (on OctoMap's lattice for bt and ot), or read
    from an npz, which is only cropped, never resampled."""
    if resolution is not None and not (math.isfinite(resolution) and resolution > 0):
        raise ValueError(f"resolution: must be a positive number of metres, got {resolution}")
    if url is not None:
        client = client_for(url, token_file, ca_file)
        dim, lo, hi = map_dimension(client)
        check_dimension(fmt, dim)
        if bbox is not None:
            lo, hi = check_bbox(bbox, dim)
        res = resolution if resolution is not None else DEFAULT_URL_RESOLUTION
        if fmt in OCTOMAP_FORMATS:
            lo, hi = on_lattice(lo, hi, res)
        return fetch(client, lo, hi, res)
    if npz is None:
        raise ValueError("give --url http://HOST:PORT or --from MAP.npz")
    source = read_npz(npz)
    check_resolution(resolution, source.grid.resolution)
    check_dimension(fmt, source.grid.dim)
    return crop(source, *check_bbox(bbox, source.grid.dim)) if bbox is not None else source


def summary(source: ExportMap, fmt: str, variance: float) -> str:
    grid = source.grid
    classes = classify(source.prob, variance)
    text = (
        f"{'x'.join(map(str, grid.shape))} cells at {grid.resolution!r} m from {np.round(grid.origin, 6).tolist()}: "
        f"{int((classes == OCCUPIED).sum()):,} occupied, {int((classes == FREE).sum()):,} free "
        f"(Eq. 12 at sigma^2 = {variance!r})"
    )
    if fmt in OCTOMAP_FORMATS and np.abs(offset := lattice_offset(grid)).max() > 1e-9 * grid.resolution:
        text += f"; cells moved by {np.round(offset, 6).tolist()} m onto OctoMap's voxels"
    if fmt == "pgm" and grid.dim == 3:
        text += "; the PGM shows it from above"
    return text


def run_export(
    url: str | None,
    npz: str | None,
    fmt: str,
    bbox: list[float] | None,
    resolution: float | None,
    variance: float,
    out: str,
    token_file: str | None = None,
    ca_file: str | None = None,
) -> int:
    source = load_map(url, npz, fmt, bbox, resolution, token_file, ca_file)
    paths = write_export(source, fmt, out, variance)
    print(f"wrote {' and '.join(map(str, paths))}: {summary(source, fmt, variance)}")
    return 0
