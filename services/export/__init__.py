"""`gmmap export`: a map as files other tools read, written from a probability grid.

pgm (+ yaml): ROS map_server / Nav2 (pgm.py); bt and ot: OctoMap's binary tree (classes) and full
tree (the MAP log-odds) of a 3D map (octomap_tree.py); ply: occupied cell centres with their
probability (ply.py). Every format classifies by Eq. 12 at one sigma^2 (`variance`). The same
writers serve `format=pgm|bt|ot|ply` on the HTTP API.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

from services.render import top_down_classes

from .octomap_tree import NOT_3D, bt_bytes, ot_bytes
from .pgm import map_yaml, pgm_bytes
from .ply import ply_bytes

if TYPE_CHECKING:  # sources imports the HTTP API's limits, and the API imports these writers
    from .sources import ExportMap

FORMATS = ("pgm", "bt", "ot", "ply")  # the pgm, bt and ply, and ot: OctoMap with log-odds
OCTOMAP_FORMATS = ("bt", "ot")  # 3D only, on OctoMap's voxels


def check_dimension(fmt: str, dim: int) -> None:
    """A ValueError naming the format when it cannot hold a `dim`D map (bt and ot: 3D only)."""
    if fmt not in FORMATS:
        raise ValueError(f"format: must be one of {', '.join(FORMATS)}, got {fmt!r}")
    if fmt in OCTOMAP_FORMATS and dim != 3:
        raise ValueError("format: " + NOT_3D.format(fmt=fmt, dim=dim))


def output_paths(fmt: str, out: str | Path) -> list[Path]:
    """The files an export to `out` writes: PATH.pgm and PATH.yaml, PATH.bt, PATH.ot, PATH.ply (the suffix
    is added unless `out` has it; `out` may end in .pgm or .yaml for the pair)."""
    out = Path(out)
    if fmt == "pgm":
        base = out.with_suffix("") if out.suffix in (".pgm", ".yaml") else out
        return [base.with_name(base.name + ".pgm"), base.with_name(base.name + ".yaml")]
    return [out if out.suffix == f".{fmt}" else out.with_name(out.name + f".{fmt}")]


def write_export(source: ExportMap, fmt: str, out: str | Path, variance: float) -> list[Path]:
    """Write `source` as `fmt` to the files of `output_paths`; returns them."""
    check_dimension(fmt, source.grid.dim)
    paths = output_paths(fmt, out)
    if fmt == "pgm":
        image = pgm_bytes(top_down_classes(source.prob, variance))
        contents = [image, map_yaml(paths[0].name, source.grid, variance).encode()]
    elif fmt == "bt":
        contents = [bt_bytes(source.prob, source.grid, variance)]
    elif fmt == "ot":
        contents = [ot_bytes(source.prob, source.grid, variance)]
    else:
        contents = [ply_bytes(source.prob, source.grid, variance)]
    for path, content in zip(paths, contents):
        path.write_bytes(content)
    return paths
