"""Reading one msgpack map field by field, each check raising ProtocolError(field).

Wire maps come from an untrusted decoder: values can have any msgpack type, so every read
states the type it wants. bool is rejected where an int is wanted (in Python it is one).
"""

from __future__ import annotations

import builtins
import math

import numpy as np

from protocol.errors import ProtocolError
from protocol.keys import MAX_NODE


class Fields:
    """A wire map whose errors are reported as `<prefix>.<name>`."""

    def __init__(self, raw, prefix: str = ""):
        if not isinstance(raw, dict):
            raise ProtocolError(prefix or "message", f"must be a msgpack map, got {type(raw).__name__}")
        self.raw = raw
        self.prefix = prefix

    def name(self, name: str) -> str:
        return f"{self.prefix}.{name}" if self.prefix else name

    def get(self, key: str, name: str):
        if key not in self.raw:
            raise ProtocolError(self.name(name), f"missing (key {key!r})")
        return self.raw[key]

    def int(self, key: str, name: str, lo: int = 0, hi: int = MAX_NODE) -> int:
        value = self.get(key, name)
        if type(value) is not int or not lo <= value <= hi:
            raise ProtocolError(self.name(name), f"must be an integer in [{lo}, {hi}], got {value!r:.80}")
        return value

    def float(self, key: str, name: str) -> float:
        value = self.get(key, name)
        if type(value) not in (int, float) or not math.isfinite(value):
            raise ProtocolError(self.name(name), f"must be a finite number, got {value!r:.80}")
        return float(value)

    def array(self, key: str, name: str, dtype: str, count: builtins.int | None = None, nullable: bool = False):
        """A bin of little-endian numbers; floats must be finite. None for nil if nullable."""
        value = self.get(key, name)
        if value is None and nullable:
            return None
        if type(value) is not bytes:
            raise ProtocolError(self.name(name), f"must be bin (raw bytes), got {type(value).__name__}")
        itemsize = np.dtype(dtype).itemsize
        if len(value) % itemsize or (count is not None and len(value) != count * itemsize):
            wanted = f"{count} x {itemsize}" if count is not None else f"a multiple of {itemsize}"
            raise ProtocolError(self.name(name), f"must hold {wanted} bytes, got {len(value)}")
        array = np.frombuffer(value, dtype=dtype)
        if array.dtype.kind == "f" and not np.isfinite(array).all():
            raise ProtocolError(self.name(name), "must be finite (no NaN or inf)")
        return array
