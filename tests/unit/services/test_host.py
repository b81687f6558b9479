"""What a service asks of its machine: cores, freed memory handed back, how busy and how fast it was."""

import sys
import threading
import time

import pytest

from services.host import cpu_cores, cpu_shares, cpu_ticks, loop_rate, release_free_memory


def resident_mib() -> float:
    with open("/proc/self/statm") as statm:
        return int(statm.read().split()[1]) * 4096 / 2**20


def test_cpu_cores_is_positive():
    assert cpu_cores() >= 1


def test_loop_rate_counts_iterations_for_about_the_time_asked():
    start = time.perf_counter()
    rate = loop_rate(0.05)
    took = time.perf_counter() - start
    # At least one chunk of 10,000 iterations ran, and no more than one chunk past the end.
    assert 0.05 <= took < 1.0
    assert 0.01 / took <= rate < 1e4


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's malloc_trim and /proc")
def test_freed_memory_goes_back_to_the_os_on_release():
    """190 MiB in 48 KiB pieces (under glibc's mmap threshold) freed by another thread stay resident
    in its arena until released (the last piece kept, so they are not at the heap's top)."""
    kept = []

    def churn():
        pieces = [bytearray(48 * 1024) for _ in range(4000)]
        kept.append(pieces[-1])

    thread = threading.Thread(target=churn)
    thread.start()
    thread.join()
    freed = resident_mib()
    assert release_free_memory()
    assert resident_mib() < freed - 100


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="/proc/stat")
def test_cpu_shares_split_the_time_between_two_readings():
    """Busy, idle and stolen fractions of the machine's CPU time sum to one; a burst of work on this
    thread shows as busy time."""
    before = cpu_ticks()
    deadline = time.monotonic() + 0.3
    while time.monotonic() < deadline:
        pass
    shares = cpu_shares(before, cpu_ticks())
    assert shares is not None and set(shares) == {"busy", "idle", "steal"}
    assert abs(sum(shares.values()) - 1) < 0.01 and shares["busy"] > 0


def test_cpu_shares_of_missing_or_equal_readings_are_none():
    assert cpu_shares(None, (1, 2, 3)) is None and cpu_shares((1, 2, 3), None) is None
    assert cpu_shares((1, 2, 3), (1, 2, 3)) is None
    assert cpu_shares((0, 0, 0), (5, 3, 2)) == {"busy": 0.5, "idle": 0.3, "steal": 0.2}
