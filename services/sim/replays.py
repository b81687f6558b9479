"""The beam replays of a run (byte_models.replay_robot), one per robot, in worker processes.

They need only the fleet and how many scans each robot published, not the server: `gmmap sim`
starts them as soon as the robots are done, so that they run while the server answers the final
snapshot and is restarted, and the map rebuilds (services.sim.rebuild) run beside them. The
workers run at a lower processor priority (WORKER_NICE) so that they take mostly what the server
leaves: the times measured meanwhile (the final snapshot within `wall_s`, `restart_s`) stay near
what they were without them.
"""

from __future__ import annotations

import multiprocessing
import os
import threading
from concurrent.futures import Future, ProcessPoolExecutor

import numpy as np

from gmm_core import Grid
from services.host import cpu_cores
from services.sim.byte_models import octomap_stride, replay_robot
from services.sim.fleet import SimulatedFleet, robot_name
from services.sim.processes import die_with_parent
from services.sim.record import RunRecord

# Niceness added to the workers': a nice-10 process weighs about a tenth of a nice-0 one in Linux's
# scheduler, so a server at full load loses under 10% to them, while they still outweigh other
# work at nice 19 on a shared machine by 7 to 1.
WORKER_NICE = 10
_WORKER: tuple[SimulatedFleet, Grid, int] | None = None  # a worker's fleet, graded grid, scans between closures


def _start_worker(fleet: SimulatedFleet, grid: Grid, update_every: int) -> None:
    global _WORKER
    die_with_parent()  # a killed `gmmap sim` leaves no replay behind
    os.nice(WORKER_NICE)
    _WORKER = (fleet, grid, update_every)


def _replay(index: int, scans: int, stride: int) -> tuple[dict[str, np.ndarray], np.ndarray]:
    assert _WORKER is not None, "a replay worker is started by _start_worker"
    fleet, grid, update_every = _WORKER
    return replay_robot(fleet, grid, update_every, index, scans, stride)


class BeamReplays:
    """Every robot's replay_robot of the scans it published (record.published), on as many
    worker processes as there are cores (and robots). The workers are started on a thread of
    their own: each is handed the fleet (its world's raster, 64 MB for the mine), which takes
    the starting thread about a second, not the caller's."""

    def __init__(self, record: RunRecord):
        spawn = multiprocessing.get_context("spawn")  # no fork of a process running Zenoh
        self._pool = ProcessPoolExecutor(
            min(cpu_cores(), record.fleet.robots),
            mp_context=spawn,
            initializer=_start_worker,
            initargs=(record.fleet, record.grid, record.update_every),
        )
        self._futures: dict[str, Future] = {}
        self._failed: BaseException | None = None  # why the workers could not be started
        self._starting = threading.Thread(target=self._submit, args=(dict(record.published), record.fleet.robots))
        self._starting.start()

    def _submit(self, published: dict[str, int], robots: int) -> None:
        stride = octomap_stride(sum(published.values()))
        try:
            for i in range(robots):
                name = robot_name(i)
                self._futures[name] = self._pool.submit(_replay, i, published.get(name, 0), stride)
        except BaseException as error:  # raised to the caller of results()
            self._failed = error

    def results(self, progress) -> tuple[dict[str, dict[str, np.ndarray]], dict[str, np.ndarray]]:
        """(per robot: bytes per scan by kind, first-seen counts per cell), when all are done;
        `progress(n)` as each robot's n scans are."""
        self._starting.join()
        if self._failed is not None:
            raise RuntimeError("gmmap sim: the beam replays could not be started") from self._failed
        per_scan, first_seen = {}, {}
        for name, future in self._futures.items():
            per_scan[name], first_seen[name] = future.result()
            progress(len(per_scan[name]["raw"]))
        self.close()
        return per_scan, first_seen

    def close(self) -> None:
        self._starting.join()
        self._pool.shutdown(cancel_futures=True)
