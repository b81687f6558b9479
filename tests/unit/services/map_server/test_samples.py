"""The sample cache: a node made ready to sample once serves every resolution with the samples
gmm_core.sampling.scan_samples draws from the decoded model, within its byte bound, whether the
node holds its bytes or the store does."""

import numpy as np
import pytest

from gmm_core import fit_scan
from gmm_core.analytic.components import NodeComponents
from gmm_core.sampling import ScanSamples, scan_samples, scan_seed
from protocol import ScanMessage, decode, encode
from services.map_server import samples
from services.map_server.nodes import NodeKey, NodeStore, ScanEntry
from services.map_server.samples import SampleCache
from services.map_server.store import Store

RESOLUTIONS = (0.05, 0.1, 0.2)


@pytest.fixture(scope="module")
def messages(intel_scans):
    """Scan messages as a server receives them: decoded from their wire bytes (the model quantised)."""
    return [
        decode(encode(ScanMessage("f", "r", s.index, s.stamp, fit_scan(s.hits, s.no_return), s.pose)))
        for s in intel_scans[:12]
    ]


def held_nodes(messages, hold_models=True):
    store = NodeStore(lambda lo, hi: None, hold_models=hold_models)
    store.add_many([ScanEntry.of(m, 0, encode(m)) for m in messages])
    return [store.robots["r"].nodes[m.node] for m in messages]


def assert_same(a: ScanSamples, b: ScanSamples) -> None:
    for x, y in ((a.occupied, b.occupied), (a.free, b.free)):
        for field in ("means", "chol", "counts", "offsets", "weights"):
            assert np.array_equal(getattr(x, field), getattr(y, field)), field
        assert x.key == y.key
    assert np.array_equal(a.origin, b.origin)


def test_every_resolution_draws_what_scan_samples_draws_from_the_decoded_model(messages):
    cache = SampleCache(samples_per_cell=4.0)
    for node, message in zip(held_nodes(messages), messages):
        for resolution in RESOLUTIONS:
            expected = scan_samples(message.model, resolution, scan_seed("r", message.node), 4.0)
            assert_same(cache.samples(node, resolution), expected)
        # the means and Cholesky factors are shared by the resolutions, not copied per resolution
        drawn = [cache.samples(node, r).occupied for r in RESOLUTIONS]
        assert all(d.means is drawn[0].means and d.chol is drawn[0].chol for d in drawn)


def test_nodes_that_hold_nothing_are_read_from_the_store(messages, tmp_path):
    store = Store(tmp_path)
    store.put_scans([(m, encode(m)) for m in messages])
    nodes = held_nodes(messages, hold_models=False)
    assert all(n.raw is None and n.held_model is None for n in nodes)
    cache = SampleCache(4.0, store.scan_reader("f"))
    for node, message in zip(nodes, messages):
        assert_same(cache.samples(node, 0.1), scan_samples(message.model, 0.1, node.seed, 4.0))
    with pytest.raises(LookupError, match="no store"):
        SampleCache(4.0).samples(nodes[0], 0.1)
    with pytest.raises(LookupError, match="not in the store"):
        store.scan_reader("other fleet")(NodeKey("r", messages[0].node))
    store.close()


def test_a_node_primed_at_ingest_is_sampled_without_reading_the_store(messages):
    """Ingest decoded the model to check it: primed with it, the cache never reads the node's bytes,
    and draws what it would have drawn from them (FleetMap.add_entries with models)."""

    def unread(key):
        raise AssertionError(f"read {key} from the store")

    cache = SampleCache(4.0, unread)
    nodes = held_nodes(messages, hold_models=False)
    for node, message in zip(nodes, messages):
        cache.prime(node.key, node.seed, message.model)
    for node, message in zip(nodes, messages):
        for resolution in RESOLUTIONS:
            assert_same(cache.samples(node, resolution), scan_samples(message.model, resolution, node.seed, 4.0))


def test_the_cache_holds_at_most_its_bytes_and_evicts_the_least_recent(messages, monkeypatch):
    cache = SampleCache(4.0)
    nodes = held_nodes(messages)
    cache.samples(nodes[0], 0.1)
    one = cache.bytes_held
    monkeypatch.setattr(samples, "SAMPLE_CACHE_BYTES", 3 * one)
    for node in nodes:
        cache.samples(node, 0.1)
        assert cache.bytes_held <= 3 * one * 1.5  # nodes differ a little in components
    assert nodes[-1].key in cache._entries and nodes[0].key not in cache._entries
    # an evicted node made again draws the same samples
    assert_same(cache.samples(nodes[0], 0.1), scan_samples(messages[0].model, 0.1, nodes[0].seed, 4.0))


def test_a_nodes_components_are_decomposed_once_and_counted_with_its_samples(messages, monkeypatch):
    """Point queries' analytic evidence (services/api/points.py): a node's components in its frame,
    NodeComponents.of its decoded model, made once, in the same entry and byte bound as its samples."""
    cache = SampleCache(4.0)
    nodes = held_nodes(messages)
    first = cache.components(nodes[0])
    expected = NodeComponents.of(messages[0].model)
    for field in ("means", "evals", "evecs", "counts", "max_range", "origin"):
        assert np.array_equal(getattr(first, field), getattr(expected, field)), field
    assert cache.components(nodes[0]) is first and cache.bytes_held == first.nbytes
    cache.samples(nodes[0], 0.1)  # the same entry: its samples join the components
    assert len(cache._entries) == 1 and cache.bytes_held == cache._entries[nodes[0].key].nbytes > first.nbytes
    monkeypatch.setattr(samples, "SAMPLE_CACHE_BYTES", 3 * first.nbytes)
    for node in nodes:
        cache.components(node)
    assert cache.bytes_held <= 3 * first.nbytes * 1.5 and nodes[0].key not in cache._entries
