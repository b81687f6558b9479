"""Records of fixed-width unsigned fields, least significant bit first, one continuous stream
zero-padded to a whole byte (encoding "q", docs/PROTOCOL.md); numba kernels, checked bit for bit
against the numpy reference in tests/support/quantize_reference.py."""

from __future__ import annotations

import numpy as np
from numba import njit

from protocol.errors import ProtocolError


def pack_records(codes: np.ndarray, widths: np.ndarray) -> bytes:
    """(K, fields) non-negative integer codes -> the stream; each code keeps its low `width` bits."""
    return _write_codes(np.ascontiguousarray(codes, dtype=np.int64), widths).tobytes()


def unpack_records(data: bytes | np.ndarray, n_records: int, widths: np.ndarray, field: str) -> np.ndarray:
    """The stream -> (n_records, fields) int64 codes; ProtocolError(field) for a wrong length or
    padding bits that are not zero (a stream is canonical)."""
    stream = as_stream(data)
    codes, status = read_codes(stream, n_records, widths)
    check_status(status, stream, n_records, widths, field)
    return codes


def as_stream(data: bytes | np.ndarray) -> np.ndarray:
    return np.frombuffer(data, dtype=np.uint8) if isinstance(data, (bytes, bytearray, memoryview)) else data


READ, WRONG_LENGTH, PADDING_SET = 0, 1, 2  # what read_codes found


def check_status(status: int, stream: np.ndarray, n_records: int, widths: np.ndarray, field: str) -> None:
    if status == WRONG_LENGTH:
        expected = (n_records * int(widths.sum()) + 7) // 8
        raise ProtocolError(field, f"expected {expected} bytes for {n_records} components, got {len(stream)}")
    if status == PADDING_SET:
        raise ProtocolError(field, "padding bits after the last component must be zero")


@njit(cache=True)
def _write_codes(codes, widths):
    n_records, n_fields = codes.shape
    out = np.zeros((n_records * widths.sum() + 7) // 8, dtype=np.uint8)
    held, n_held, at = 0, 0, 0  # bits not yet written, lowest first
    for k in range(n_records):
        for f in range(n_fields):
            held |= (codes[k, f] & ((1 << widths[f]) - 1)) << n_held
            n_held += widths[f]
            while n_held >= 8:
                out[at] = held & 0xFF
                held >>= 8
                n_held -= 8
                at += 1
    if n_held:
        out[at] = held
    return out


@njit(cache=True)
def read_codes(stream, n_records, widths):
    """-> ((n_records, fields) codes, READ | WRONG_LENGTH | PADDING_SET); numba callers check the status."""
    codes = np.empty((n_records, len(widths)), dtype=np.int64)
    if len(stream) != (n_records * widths.sum() + 7) // 8:
        return codes, WRONG_LENGTH
    held, n_held, at = 0, 0, 0  # bits read but not yet used, lowest first
    for k in range(n_records):
        for f in range(len(widths)):
            while n_held < widths[f]:
                held |= np.int64(stream[at]) << n_held
                n_held += 8
                at += 1
            codes[k, f] = held & ((1 << widths[f]) - 1)
            held >>= widths[f]
            n_held -= widths[f]
    return codes, READ if held == 0 else PADDING_SET  # held: the pad up to a whole byte
