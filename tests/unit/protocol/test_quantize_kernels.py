"""The numba kernels of encoding "q" (protocol/bitstream.py, protocol/quantize.py) against the plain
numpy reference (tests/support/quantize_reference.py): the same bytes, codes and float bits."""

from __future__ import annotations

import numpy as np
import pytest

from gmm_core.mixture import Mixture
from protocol import ProtocolError
from protocol import quantize as qz
from protocol.bitstream import pack_records, unpack_records
from support import quantize_reference as reference
from support.fuzz import random_rotations

pytestmark = pytest.mark.filterwarnings("error")

FLOAT32_MAX = float(np.finfo(np.float32).max)


def assert_same_bits(got: Mixture, want: Mixture) -> None:
    for name in ("weights", "means", "covariances"):
        a, b = getattr(got, name), getattr(want, name)
        assert a.shape == b.shape and a.dtype == b.dtype == np.float64, name
        assert a.tobytes() == b.tobytes(), (name, np.flatnonzero(a.view(np.uint64) != b.view(np.uint64))[:5])
    assert got.support == want.support


def valid_stream(rng: np.random.Generator, count: int, dim: int) -> bytes:
    """Random bits, i.e. random and corrupt codes, with the padding bits zero."""
    stream = bytearray(rng.bytes(qz.stream_bytes(count, dim)))
    used = count * qz.record_bits(dim) % 8
    if used:
        stream[-1] &= (1 << used) - 1
    return bytes(stream)


def random_bounds(rng: np.random.Generator, dim: int) -> np.ndarray:
    kind = rng.integers(4)
    if kind == 0:  # a flat box: every mean on one point
        lo = hi = rng.uniform(-100, 100, dim)
    elif kind == 1:  # the widest box float32 holds
        lo, hi = np.full(dim, -FLOAT32_MAX), np.full(dim, FLOAT32_MAX)
    else:
        lo = rng.uniform(-100, 100, dim)
        hi = lo + rng.uniform(0, 10.0 ** rng.uniform(-3, 3), dim)
    return np.concatenate([lo, hi]).astype(np.float32)


def reference_decode(bounds, stream, count, dim, support):
    mixture = reference.dequantize(bounds, stream, count, dim, "occupied")
    return Mixture(mixture.weights, mixture.means, mixture.covariances, support)


@pytest.mark.parametrize("dim", [2, 3])
def test_decode_of_random_streams_matches_the_reference_bit_for_bit(dim):
    rng = np.random.default_rng(dim)
    for count in [0, 1, 2, 3, 7, 8, 9, 127, 128, 129, 4096, *rng.integers(10, 400, 40)]:  # np.sum's blocks of 8, 128
        stream, bounds = valid_stream(rng, count, dim), random_bounds(rng, dim)
        got = qz.dequantize(bounds, stream, count, dim, "occupied", 5)
        assert_same_bits(got, reference_decode(bounds, stream, count, dim, 5))
        as_array = qz.dequantize(bounds, np.frombuffer(stream, np.uint8), count, dim, "occupied", 5)
        assert_same_bits(as_array, got)


@pytest.mark.parametrize("dim", [2, 3])
def test_decode_of_every_rotation_scale_and_weight_code_matches_the_reference(dim):
    """Each code of each field at least once, beside random others: every look-up the kernel makes."""
    rng = np.random.default_rng(10 + dim)
    widths = qz.FIELD_WIDTHS[dim]
    count = 2 ** int(widths.max())
    codes = rng.integers(0, 2**widths, size=(count, len(widths)))
    for field, width in enumerate(widths):
        codes[:, field] = rng.permutation(count) % 2**width
    stream = reference.pack_records(list(codes.T), list(widths))
    bounds = random_bounds(rng, dim)
    assert_same_bits(
        qz.dequantize(bounds, stream, count, dim, "free", 0), reference_decode(bounds, stream, count, dim, 0)
    )


def random_mixture(rng: np.random.Generator, count: int, dim: int) -> Mixture:
    """Scan-like and awkward: stds over the coded range and past it, isotropic and axis-aligned ones."""
    means = rng.uniform(-30, 30, (count, dim)) * 10.0 ** rng.uniform(-3, 0)
    log_std = rng.uniform(np.log(1e-5), np.log(3e2), (count, dim))
    log_std[: count // 4] = log_std[: count // 4, :1]
    rotations = random_rotations(rng, count, dim)
    rotations[count // 4 : count // 2] = np.eye(dim)
    covs = np.einsum("kij,kj,klj->kil", rotations, np.exp(2 * log_std), rotations)
    weights = rng.exponential(size=count) * (rng.random(count) > 0.1) + 1e-9
    return Mixture(weights / weights.sum(), means, covs, 7)


@pytest.mark.parametrize("dim", [2, 3])
def test_encode_then_decode_of_random_mixtures_matches_the_reference(dim):
    rng = np.random.default_rng(20 + dim)
    for count in [1, 2, 5, *rng.integers(10, 300, 20)]:
        bounds, stream = qz.quantize(random_mixture(rng, count, dim))
        assert_same_bits(
            qz.dequantize(bounds, stream, count, dim, "occupied", 7), reference_decode(bounds, stream, count, dim, 7)
        )


def random_widths(rng: np.random.Generator) -> np.ndarray:
    return rng.integers(1, 20, rng.integers(1, 12))


def test_pack_matches_the_reference_on_random_codes():
    rng = np.random.default_rng(30)
    for _ in range(200):
        widths = random_widths(rng)
        codes = rng.integers(0, 2**widths, size=(int(rng.integers(0, 50)), len(widths)))
        assert pack_records(codes, widths) == reference.pack_records(list(codes.T), list(widths))


def test_unpack_matches_the_reference_on_random_streams():
    rng = np.random.default_rng(31)
    for _ in range(200):
        widths = random_widths(rng)
        count = int(rng.integers(0, 50))
        stream = bytearray(rng.bytes((count * int(widths.sum()) + 7) // 8))
        if rng.random() < 0.8 and count * widths.sum() % 8:  # else the padding bits are likely not zero
            stream[-1] &= (1 << int(count * widths.sum() % 8)) - 1
        try:
            want = np.stack(reference.unpack_records(bytes(stream), count, list(widths), "c"), axis=1)
        except ProtocolError as error:
            with pytest.raises(ProtocolError) as caught:
                unpack_records(bytes(stream), count, widths, "c")
            assert (caught.value.field, caught.value.message) == (error.field, error.message)
            continue
        got = unpack_records(bytes(stream), count, widths, "c")
        assert got.dtype == np.int64 and np.array_equal(got, want.reshape(count, len(widths)))


@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("count", [0, 1, 5])
def test_bad_streams_raise_what_the_reference_raises(dim, count):
    bounds = np.array([0.0] * dim + [1.0] * dim, dtype=np.float32)
    good = valid_stream(np.random.default_rng(count), count, dim)
    streams = [good + b"\0", good + b"\x01"] + ([good[:-1]] if good else [])
    if count * qz.record_bits(dim) % 8:
        streams.append(good[:-1] + bytes([good[-1] | 0x80]))  # a padding bit set
    for stream in streams:
        with pytest.raises(ProtocolError) as want:
            reference.dequantize(bounds, stream, count, dim, "free")
        with pytest.raises(ProtocolError) as got:
            qz.dequantize(bounds, stream, count, dim, "free")
        assert (got.value.field, got.value.message) == (want.value.field, want.value.message)
        assert got.value.field == "free.components"
