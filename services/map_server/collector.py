"""The interpreter's cyclic garbage collector in a server that holds a shift's map.

CPython collects its oldest generation each time that generation grew by a quarter, and such a
collection walks every tracked object with the interpreter lock held: every thread stops. A map
server holds tens of Python objects per node (its samples, samplers, poses and keys), so in the
20-robot office run a full collection came every 5-7 s, stopped the server for 0.06 s at first
and 0.39 s after 40 s of driving, a spike of every tile request's latency each time, and the
pauses grow with the map over a shift (docs/RELIABILITY.md, "Fourteenth session").

`freeze_survivors` moves every object that survived a full collection into the permanent
generation (gc.freeze), so the next one walks only what came since. The cost: a reference cycle
that was alive at a freeze is never collected once it dies, where reference counting cannot free
it. This server's cycles die young: in that run the young generations collected 5,572 objects
and the full collections 654 more.
"""

from __future__ import annotations

import gc
from collections.abc import Callable


def _freeze_after_full_collection(phase: str, info: dict) -> None:
    if phase == "stop" and info["generation"] == 2:
        gc.freeze()


def freeze_survivors() -> Callable[[], None]:
    """Freeze what is alive now and what survives each later full collection; returns the undo
    (the frozen objects go back to the oldest generation)."""
    gc.freeze()
    gc.callbacks.append(_freeze_after_full_collection)

    def undo() -> None:
        if _freeze_after_full_collection in gc.callbacks:
            gc.callbacks.remove(_freeze_after_full_collection)
        gc.unfreeze()

    return undo
