"""What a service asks of its machine: cores, and freed memory handed back to the OS."""

import sys
import threading

import pytest

from services.host import cpu_cores, release_free_memory


def resident_mib() -> float:
    with open("/proc/self/statm") as statm:
        return int(statm.read().split()[1]) * 4096 / 2**20


def test_cpu_cores_is_positive():
    assert cpu_cores() >= 1


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
