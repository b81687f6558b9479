"""The server's garbage-collector policy: survivors of a full collection are left out of the next."""

import gc
import weakref

from services.map_server.collector import freeze_survivors


class _Node:
    pass


def test_survivors_of_a_full_collection_are_frozen_and_new_cycles_still_collected():
    thaw = freeze_survivors()
    try:
        frozen = gc.get_freeze_count()
        assert frozen > 0  # what was alive at the start
        kept = [_Node() for _ in range(1000)]  # long-lived: survives the next full collection
        gc.collect()
        assert gc.get_freeze_count() >= frozen + len(kept)
        cycle = _Node()
        cycle.self = cycle  # garbage only the collector frees, made after the freeze
        dead = weakref.ref(cycle)
        del cycle
        gc.collect()
        assert dead() is None
    finally:
        thaw()
    assert gc.get_freeze_count() == 0 and all(c.__name__ != "_freeze_after_full_collection" for c in gc.callbacks)
