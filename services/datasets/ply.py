"""PLY (Stanford polygon format) sequences: a directory of numbered `NNNNNN.ply` or `.ply.gz` files.

Reads `format ascii 1.0`, `binary_little_endian 1.0` and `binary_big_endian 1.0`. Only the
`vertex` element's x y z are kept, of any numeric type; its other properties (list properties
too) and every other element (faces, edges, ...) before or after it are skipped. Points with a
non-finite coordinate are dropped. Points are in the sensor frame. PLY files carry no time:
`index` and `stamp` are the file number NNNNNN. Poses as for PCD: from a poses file
(poses.read_poses, KITTI or TUM layout), else the identity.
"""

from __future__ import annotations

import re
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numba
import numpy as np

from .common import DatasetError, RangeScan, parse_rows, read_bytes
from .point_files import point_files, read_numbered_clouds

PLY_FILE = re.compile(r"(\d+)\.ply(\.gz)?")
_TYPES = {"char": "i1", "uchar": "u1", "short": "i2", "ushort": "u2", "int": "i4", "uint": "u4", "float": "f4"}
_TYPES |= {"double": "f8", "int8": "i1", "uint8": "u1", "int16": "i2", "uint16": "u2", "int32": "i4"}
_TYPES |= {"uint32": "u4", "float32": "f4", "float64": "f8"}
_BYTE_ORDER = {"ascii": "=", "binary_little_endian": "<", "binary_big_endian": ">"}


@dataclass(frozen=True)
class _Property:
    name: str
    value: np.dtype  # the scalar's type, or a list's item type (in the file's byte order)
    list_count: np.dtype | None = None  # a list property's count type; None for a scalar


@dataclass
class _Element:
    name: str
    count: int
    properties: list[_Property] = field(default_factory=list)

    @property
    def has_lists(self) -> bool:
        return any(p.list_count is not None for p in self.properties)


def _property(words: list[str], order: str, where: str) -> _Property:
    """`property TYPE NAME` or `property list COUNT_TYPE ITEM_TYPE NAME`."""
    is_list = words[1:2] == ["list"]
    types = words[2:4] if is_list else words[1:2]
    if len(words) != (5 if is_list else 3) or not all(t in _TYPES for t in types):
        raise DatasetError(f"{where}: bad property line {' '.join(words)!r}")
    dtypes = [np.dtype(order + _TYPES[t]) for t in types]
    return _Property(words[-1], dtypes[-1], dtypes[0] if len(dtypes) == 2 else None)


def _read_header(raw: bytes, name: str) -> tuple[str, list[_Element], int, int]:
    """(format, elements, byte offset of the body, number of header lines)."""
    fmt, elements, pos, lineno = None, [], 0, 0
    while True:
        end = raw.find(b"\n", pos)
        if end < 0:
            raise DatasetError(f"{name}: header has no end_header line")
        lineno += 1
        line = raw[pos:end].decode("latin-1").strip()
        pos = end + 1
        words, where = line.split(), f"{name}:{lineno}"
        if lineno == 1 and line != "ply":
            raise DatasetError(f"{where}: not a PLY file (first line {line[:40]!r}, expected 'ply')")
        if lineno == 1 or not words or words[0] in ("comment", "obj_info"):
            continue
        if words[0] == "end_header":
            break
        if words[0] == "format" and len(words) == 3 and words[1] in _BYTE_ORDER:
            fmt = words[1]
        elif words[0] == "element" and len(words) == 3 and words[2].isdigit():
            elements.append(_Element(words[1], int(words[2])))
        elif words[0] == "property" and elements and fmt is not None:
            elements[-1].properties.append(_property(words, _BYTE_ORDER[fmt], where))
        else:
            raise DatasetError(f"{where}: bad header line {line[:80]!r}")
    if fmt is None:
        raise DatasetError(f"{name}: header has no format line")
    return fmt, elements, pos, lineno


@numba.njit(cache=True)
def _walk_records(data, start, count, sizes, count_sizes, big_endian, want, offsets):  # pragma: no cover - numba
    """Walk `count` records with list properties from byte `start`; returns the end offset, or -1
    when the data ends first. Property k is a scalar of sizes[k] bytes when count_sizes[k] == 0,
    else a list: an unsigned count of count_sizes[k] bytes, then that many items of sizes[k] bytes.
    offsets[i, j] gets the byte offset of property want[j] (a scalar) in record i."""
    pos = start
    n = len(data)
    for i in range(count):
        for k in range(len(sizes)):
            for j in range(len(want)):
                if want[j] == k:
                    offsets[i, j] = pos
            c = count_sizes[k]
            if c == 0:
                pos += sizes[k]
                continue
            if pos + c > n:
                return -1
            m = 0
            for b in range(c):
                m = m * 256 + data[pos + (b if big_endian else c - 1 - b)]
            pos += c + m * sizes[k]  # a negative signed count reads as huge: "ends first" below
        if pos > n:
            return -1
    return pos


def _binary_xyz(
    raw: bytes, pos: int, big_endian: bool, elements: list[_Element], vertex: _Element, xyz: list[int], name: str
):
    """The vertex x y z columns of a binary body starting at byte `pos`."""
    data = np.frombuffer(raw, dtype=np.uint8)
    cols = []
    for el in elements:
        if not el.has_lists:  # fixed-size records: one structured dtype
            dtype = np.dtype([(f"p{k}", p.value) for k, p in enumerate(el.properties)])
            end = pos + el.count * dtype.itemsize
            if el is vertex and end <= len(raw):
                rec = np.frombuffer(raw, dtype=dtype, count=el.count, offset=pos)
                cols = [rec[f"p{k}"] for k in xyz]
        else:
            sizes = np.array([p.value.itemsize for p in el.properties], dtype=np.int64)
            count_sizes = np.array([p.list_count.itemsize if p.list_count else 0 for p in el.properties], np.int64)
            want = np.array(xyz if el is vertex else [], dtype=np.int64)
            offsets = np.zeros((el.count, len(want)), dtype=np.int64)
            end = _walk_records(data, pos, el.count, sizes, count_sizes, big_endian, want, offsets)
            if el is vertex and end >= 0:  # gather each coordinate's bytes at its per-record offset
                for j, k in enumerate(xyz):
                    size = el.properties[k].value.itemsize
                    cols.append(data[offsets[:, j, None] + np.arange(size)].view(el.properties[k].value)[:, 0])
        if end < 0 or end > len(raw):
            raise DatasetError(f"{name}: truncated: {len(raw) - pos} bytes left for {el.count} {el.name} elements")
        pos = end
    return cols


def _ascii_xyz(text: str, first_line: int, elements: list[_Element], vertex: _Element, xyz: list[int], name: str):
    """The vertex x y z columns of an ascii body (one element a line) whose first line is `first_line`."""
    lines = text.split("\n")
    filled = [i for i, ln in enumerate(lines) if ln.strip()]  # blank lines hold no element
    cursor, cols = 0, []
    for el in elements:
        mine = filled[cursor : cursor + el.count]
        if len(mine) < el.count:
            raise DatasetError(f"{name}: truncated: {len(mine)} lines for {el.count} {el.name} elements")
        cursor += el.count
        if el is not vertex or not mine:
            continue
        if el.has_lists:
            table = np.array([_ascii_record(lines[i], el, xyz, f"{name}:{first_line + i}") for i in mine])
            cols = list(table.T)
        else:
            table = parse_rows("\n".join(lines[mine[0] : mine[-1] + 1]), name, len(el.properties), first_line + mine[0])
            cols = [table[:, k] for k in xyz]
    # the file's own type: float32 values printed in decimal come back as the float32 written
    return [c.astype(vertex.properties[k].value) for c, k in zip(cols, xyz)]


def _ascii_record(line: str, el: _Element, xyz: list[int], where: str) -> list[float]:
    """The x y z of one ascii vertex line whose properties include lists."""
    words, pos, values = line.split(), 0, {}
    try:
        for k, p in enumerate(el.properties):
            if p.list_count is None:
                values[k] = float(words[pos])
                pos += 1
            else:
                pos += 1 + int(words[pos])
        if pos != len(words):
            raise IndexError
    except (IndexError, ValueError):
        raise DatasetError(f"{where}: does not match the vertex properties: {line.strip()[:80]!r}") from None
    return [values[k] for k in xyz]


def read_ply_points(path: Path) -> np.ndarray:
    """The (n, 3) float64 vertex x y z of one PLY file, non-finite points dropped."""
    raw = read_bytes(path)
    fmt, elements, pos, header_lines = _read_header(raw, path.name)
    vertex = next((el for el in elements if el.name == "vertex"), None)
    if vertex is None:
        raise DatasetError(f"{path.name}: no vertex element (has {[el.name for el in elements]})")
    names = [p.name if p.list_count is None else None for p in vertex.properties]
    if not {"x", "y", "z"} <= set(names):
        raise DatasetError(
            f"{path.name}: vertex element has no x y z properties (has {[p.name for p in vertex.properties]})"
        )
    xyz = [names.index(a) for a in "xyz"]
    if fmt == "ascii":
        cols = _ascii_xyz(raw[pos:].decode("latin-1"), header_lines + 1, elements, vertex, xyz, path.name)
    else:
        cols = _binary_xyz(raw, pos, fmt == "binary_big_endian", elements, vertex, xyz, path.name)
    points = np.column_stack(cols).astype(np.float64) if vertex.count else np.empty((0, 3))
    return np.ascontiguousarray(points[np.isfinite(points).all(axis=1)])


def count_ply(path: str | Path) -> int:
    return len(point_files(Path(path), PLY_FILE, "ply"))


def read_ply(path: str | Path, *, poses: str | Path | None = None, min_range: float = 0.0) -> Iterator[RangeScan]:
    """The scans of a directory of numbered .ply(.gz) files (or one file), in number order."""
    return read_numbered_clouds(path, PLY_FILE, "ply", read_ply_points, poses, min_range)
