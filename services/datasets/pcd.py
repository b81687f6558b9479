"""PCD (Point Cloud Library) sequences: a directory of numbered `NNNNNN.pcd` or `.pcd.gz` files.

Reads `DATA ascii`, `binary` and `binary_compressed` (LZF), any extra fields (only x y z are
kept), organised or not; points with a non-finite coordinate are dropped. Points are in the
sensor frame. PCD files carry no time: `index` and `stamp` are the file number NNNNNN.
Without a poses file every scan's pose is the identity; with one (see poses.read_poses: KITTI
layout, line k is the pose of scan file number k; or TUM layout) the scans get its poses.
"""

from __future__ import annotations

import re
from collections.abc import Iterator
from pathlib import Path

import numba
import numpy as np

from .common import DatasetError, RangeScan, parse_rows, read_bytes
from .point_files import point_files, read_numbered_clouds

PCD_FILE = re.compile(r"(\d+)\.pcd(\.gz)?")
_TYPES = {("F", 4): "<f4", ("F", 8): "<f8", ("I", 1): "i1", ("I", 2): "<i2", ("I", 4): "<i4", ("I", 8): "<i8"}
_TYPES |= {("U", 1): "u1", ("U", 2): "<u2", ("U", 4): "<u4", ("U", 8): "<u8"}


@numba.njit(cache=True)
def _lzf_decompress_into(src: np.ndarray, dst: np.ndarray) -> int:  # pragma: no cover - numba
    """liblzf's decompressor; returns bytes written, or -1 on a corrupt stream."""
    i = 0
    o = 0
    n, m = len(src), len(dst)
    while i < n:
        ctrl = src[i]
        i += 1
        if ctrl < 32:  # literal run of ctrl + 1 bytes
            length = ctrl + 1
            if i + length > n or o + length > m:
                return -1
            dst[o : o + length] = src[i : i + length]
            i += length
            o += length
        else:  # back reference
            length = ctrl >> 5
            if length == 7:
                if i >= n:
                    return -1
                length += src[i]
                i += 1
            if i >= n:
                return -1
            ref = o - ((ctrl & 0x1F) << 8) - 1 - src[i]
            i += 1
            length += 2
            if ref < 0 or o + length > m:
                return -1
            for k in range(length):  # may overlap: byte by byte
                dst[o + k] = dst[ref + k]
            o += length
    return o


def lzf_decompress(data: bytes, size: int) -> bytes:
    """LZF-decompress `data` to exactly `size` bytes; ValueError when the stream is corrupt."""
    dst = np.empty(size, dtype=np.uint8)
    got = _lzf_decompress_into(np.frombuffer(data, dtype=np.uint8), dst)
    if got != size:
        raise ValueError(f"corrupt LZF stream (decoded {got} of {size} bytes)")
    return dst.tobytes()


def read_pcd_points(path: Path) -> np.ndarray:
    """The (n, 3) float64 x y z of one PCD file, non-finite points dropped."""
    raw = read_bytes(path)
    header: dict[str, list[str]] = {}
    pos = 0
    lineno = 0
    while True:
        end = raw.find(b"\n", pos)
        if end < 0:
            raise DatasetError(f"{path.name}: header has no DATA line")
        lineno += 1
        line = raw[pos:end].decode("latin-1").strip()
        pos = end + 1
        if not line or line.startswith("#"):
            continue
        key, *values = line.split()
        header[key.upper()] = values
        if key.upper() == "DATA":
            break
    try:
        fields = header["FIELDS"]
        sizes = [int(s) for s in header["SIZE"]]
        types = header["TYPE"]
        counts = [int(c) for c in header.get("COUNT", ["1"] * len(fields))]
        width, height = int(header["WIDTH"][0]), int(header.get("HEIGHT", ["1"])[0])
        npoints = int(header.get("POINTS", [str(width * height)])[0])
        encoding = header["DATA"][0].lower()
    except (KeyError, ValueError, IndexError) as e:
        raise DatasetError(f"{path.name}: bad or missing header entry {e}") from None
    if not (len(fields) == len(sizes) == len(types) == len(counts)):
        raise DatasetError(f"{path.name}: FIELDS, SIZE, TYPE and COUNT differ in length")
    if not {"x", "y", "z"} <= set(fields):
        raise DatasetError(f"{path.name}: no x y z fields (has {fields})")
    try:
        dts = [np.dtype(_TYPES[(t.upper(), s)]) for t, s in zip(types, sizes)]
    except KeyError:
        raise DatasetError(f"{path.name}: unsupported TYPE/SIZE {types}/{sizes}") from None
    names = [f if f != "_" else f"_pad{k}" for k, f in enumerate(fields)]
    dtype = np.dtype([(n, d, (c,)) if c > 1 else (n, d) for n, d, c in zip(names, dts, counts)])
    body = raw[pos:]
    if encoding == "ascii":
        text = body.decode("latin-1")
        ncols = sum(counts)
        table = parse_rows(text, path.name, ncols, lineno + 1) if text.strip() else np.empty((0, ncols))
        offsets = np.cumsum([0] + counts)
        cols = [table[:, offsets[fields.index(a)]] for a in "xyz"]
        points = np.column_stack(cols)
    elif encoding == "binary":
        if len(body) < npoints * dtype.itemsize:
            raise DatasetError(f"{path.name}: truncated: {len(body)} bytes for {npoints} points")
        rec = np.frombuffer(body, dtype=dtype, count=npoints)
        points = np.column_stack([rec[a].astype(np.float64) for a in "xyz"])
    elif encoding == "binary_compressed":
        if len(body) < 8:
            raise DatasetError(f"{path.name}: truncated binary_compressed header")
        csize, usize = np.frombuffer(body[:8], dtype="<u4")
        try:
            data = lzf_decompress(body[8 : 8 + int(csize)], int(usize))
        except ValueError as e:
            raise DatasetError(f"{path.name}: {e}") from None
        # column-major: each field's values for all points, one field after another
        points = np.empty((npoints, 3))
        off = 0
        for n, d, c in zip(names, dts, counts):
            nbytes = d.itemsize * c * npoints
            if off + nbytes > len(data):
                raise DatasetError(f"{path.name}: decompressed data too short for {npoints} points")
            if n in ("x", "y", "z"):
                points[:, "xyz".index(n)] = np.frombuffer(data, dtype=d, count=npoints, offset=off)
            off += nbytes
    else:
        raise DatasetError(f"{path.name}: unknown DATA encoding {encoding!r}")
    return np.ascontiguousarray(points[np.isfinite(points).all(axis=1)])


def count_pcd(path: str | Path) -> int:
    return len(point_files(Path(path), PCD_FILE, "pcd"))


def read_pcd(path: str | Path, *, poses: str | Path | None = None, min_range: float = 0.0) -> Iterator[RangeScan]:
    """The scans of a directory of numbered .pcd(.gz) files (or one file), in number order."""
    return read_numbered_clouds(path, PCD_FILE, "pcd", read_pcd_points, poses, min_range)
