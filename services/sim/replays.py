"""The beam replays of a run (byte_models.replay_robot), one per robot, in worker processes.

They need only the fleet and how many scans each robot published, not the server. `gmmap sim`
starts the workers as soon as the robots are done, so that they are handed the fleet and ready
while the server answers the final snapshot and is restarted; they replay only once grading
begins (`begin`), when nothing measured runs any more: the final snapshot (within `wall_s`) and
`restart_s` are measured as without them, and the replays get the cores at the harness's own
priority, beside the map rebuilds (services.sim.rebuild) on the harness's threads.
"""

from __future__ import annotations

import multiprocessing
import threading
from concurrent.futures import Future, ProcessPoolExecutor

import numpy as np

from gmm_core import Grid
from services.host import cpu_cores, die_with_parent
from services.sim.byte_models import octomap_stride, replay_robot
from services.sim.fleet import SimulatedFleet, robot_name
from services.sim.record import RunRecord

# A worker's fleet, graded grid and scans between closures; the events `begin` and `cancelled`.
_WORKER: tuple | None = None


def _start_worker(fleet: SimulatedFleet, grid: Grid, update_every: int, begin, cancelled) -> None:
    global _WORKER
    die_with_parent(multiprocessing.parent_process().pid)  # a killed `gmmap sim` leaves no replay behind
    _WORKER = (fleet, grid, update_every, begin, cancelled)


def _replay(index: int, scans: int, stride: int) -> tuple[dict[str, np.ndarray], np.ndarray] | None:
    assert _WORKER is not None, "a replay worker is started by _start_worker"
    fleet, grid, update_every, begin, cancelled = _WORKER
    begin.wait()
    if cancelled.is_set():  # closed before grading began
        return None
    return replay_robot(fleet, grid, update_every, index, scans, stride)


class BeamReplays:
    """Every robot's replay_robot of the scans it published (record.published), on as many
    worker processes as there are cores (and robots), from `begin` on. The workers are started
    on a thread of their own: each is handed the fleet (its world's raster, 64 MB for the mine),
    which takes that thread about a second, not the caller's. The thread lives until `close`: a
    worker dies with the thread that started it (die_with_parent's PR_SET_PDEATHSIG follows the
    thread)."""

    def __init__(self, record: RunRecord):
        spawn = multiprocessing.get_context("spawn")  # no fork of a process running Zenoh
        self._begin, self._cancelled = spawn.Event(), spawn.Event()
        self._pool = ProcessPoolExecutor(
            min(cpu_cores(), record.fleet.robots),
            mp_context=spawn,
            initializer=_start_worker,
            initargs=(record.fleet, record.grid, record.update_every, self._begin, self._cancelled),
        )
        self._futures: dict[str, Future] = {}
        self._failed: BaseException | None = None  # why the workers could not be started
        self._submitted, self._closing = threading.Event(), threading.Event()
        self._starting = threading.Thread(
            target=self._start, args=(dict(record.published), record.fleet.robots, record.grid.dim)
        )
        self._starting.start()

    def _start(self, published: dict[str, int], robots: int, dim: int) -> None:
        stride = octomap_stride(sum(published.values()), dim)
        try:
            for i in range(robots):
                name = robot_name(i)
                self._futures[name] = self._pool.submit(_replay, i, published.get(name, 0), stride)
        except BaseException as error:  # raised to the caller of results()
            self._failed = error
        finally:
            self._submitted.set()
        self._closing.wait()

    def begin(self) -> None:
        """Let the workers replay."""
        self._begin.set()

    def results(self, progress) -> tuple[dict[str, dict[str, np.ndarray]], dict[str, np.ndarray]]:
        """(per robot: bytes per scan by kind, first-seen counts per cell), when all are done;
        `progress(n)` as each robot's n scans are."""
        self.begin()
        self._submitted.wait()
        if self._failed is not None:
            raise RuntimeError("gmmap sim: the beam replays could not be started") from self._failed
        per_scan, first_seen = {}, {}
        for name, future in self._futures.items():
            per_scan[name], first_seen[name] = future.result()
            progress(len(per_scan[name]["raw"]))
        self._pool.shutdown()
        self.close()
        return per_scan, first_seen

    def close(self) -> None:
        """Ends the workers: at once where they are still replaying (they die with their thread),
        and those waiting for `begin` without replaying."""
        if not self._begin.is_set():
            self._cancelled.set()
            self._begin.set()
        self._closing.set()
        self._starting.join()
        self._pool.shutdown(cancel_futures=True)
