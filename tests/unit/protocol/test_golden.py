"""Golden vectors (tests/golden, written by tests/golden/make_vectors.py): each file's bytes decode
to the values of its JSON, the encoder writes those bytes again, and regenerating changes nothing."""

from __future__ import annotations

import json
import math

import msgpack
import pytest
from golden.make_vectors import REFUSED, VECTORS, write_vectors

from protocol import ProtocolError, ScanMessage, decode, encode
from support.golden import FOLDER, decoded_values, record_codes, to_json, wire_map


def load(folder, name: str) -> tuple[bytes, dict]:
    return (folder / f"{name}.msgpack").read_bytes(), json.loads((folder / f"{name}.json").read_text("utf-8"))


def assert_values(got, want, approx: bool, path: str = "") -> None:
    """Equal, floats bit for bit unless `approx` (values computed in float64 by the decoder, which
    another libm may round differently in the last bits)."""
    assert type(got) is type(want) or {type(got), type(want)} <= {int, float}, path
    if isinstance(want, dict):
        assert list(got) == list(want), path
        for key in want:
            assert_values(got[key], want[key], approx, f"{path}.{key}")
    elif isinstance(want, list):
        assert len(got) == len(want), path
        for index, (a, b) in enumerate(zip(got, want)):
            assert_values(a, b, approx, f"{path}[{index}]")
    elif isinstance(want, float) and approx:
        assert math.isclose(got, want, rel_tol=1e-12, abs_tol=1e-15), (path, got, want)
    else:
        assert got == want, (path, got, want)


def test_the_folder_holds_exactly_the_vectors():
    names = {path.name for path in FOLDER.iterdir() if path.suffix in (".msgpack", ".json")}
    assert names == {f"{name}{suffix}" for name in VECTORS for suffix in (".msgpack", ".json")}
    refused = {path.name for path in (FOLDER / "refused").iterdir()}
    assert refused == {f"{name}{suffix}" for name in REFUSED for suffix in (".msgpack", ".json")}


@pytest.mark.parametrize("name", sorted(VECTORS))
def test_vector_decodes_to_its_json(name):
    data, want = load(FOLDER, name)
    assert len(data) == want["bytes"]
    raw = msgpack.unpackb(data, raw=False)
    assert_values(wire_map(raw), want["wire"], approx=False)  # keys in order, every bin byte for byte
    message = decode(data, max_bytes=len(data))
    quantised = isinstance(message, ScanMessage) and want["encoding"] == "q"
    got = decoded_values(message)
    poses = {key: got.pop(key) for key in ("pose", "poses", "anchor") if key in got}  # from a matrix: approx
    assert_values(poses, {key: want["decoded"][key] for key in poses}, approx=True)
    assert_values(got, {key: value for key, value in want["decoded"].items() if key not in poses}, quantised)
    if quantised:
        codes = {part: record_codes(raw[key], message.dim) for part, key in (("occupied", "O"), ("free", "F"))}
        assert codes == want["codes"]


@pytest.mark.parametrize("name", sorted(VECTORS))
def test_encoder_writes_the_vector_from_its_inputs_and_from_its_decoded_message(name):
    data, want = load(FOLDER, name)
    vector = VECTORS[name]
    again = encode(decode(data, max_bytes=len(data)), vector.encoding)
    if vector.older is not None:  # an older version's bytes: read, and written in the current version
        assert vector.older() == data and not want["fixed_point"]
        assert again == encode(vector.build(), vector.encoding)
        return
    assert encode(vector.build(), vector.encoding) == data
    assert (again == data) is vector.fixed_point is want["fixed_point"]
    if not vector.fixed_point:  # other codes of the same mixture, within a quantisation step
        assert len(again) == len(data) and decode(again).model.n_components == decode(data).model.n_components


@pytest.mark.parametrize("name", sorted(REFUSED))
def test_refused_vector_names_its_field(name):
    data, want = load(FOLDER / "refused", name)
    with pytest.raises(ProtocolError) as caught:
        decode(data)
    assert caught.value.field == want["field"] == REFUSED[name].field


def test_regenerating_changes_nothing(tmp_path):
    written = write_vectors(tmp_path)
    assert len(written) == 2 * (len(VECTORS) + len(REFUSED))
    for path in written:
        assert path.read_bytes() == (FOLDER / path.relative_to(tmp_path)).read_bytes(), path.name


def test_json_layout_is_stable():
    assert to_json({"a": [1, 2.5], "b": [[1], {"c": None}], "d": "é"}) == (
        '{\n  "a": [1, 2.5],\n  "b": [\n    [1],\n    {\n      "c": null\n    }\n  ],\n  "d": "é"\n}'
    )
