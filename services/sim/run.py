"""`gmmap sim`: a simulated fleet over real Zenoh, measured while it runs.

One map server and the robots run as processes on 127.0.0.1 (scouting off): each robot is a
full agent (Zenoh session, outbox), several to a process (services.sim.robots). Each
agent reaches the server through a CountingRelay (its link, bytes counted both ways); a Zenoh
client on the server (the WireTap) notes every scan, pose-graph update and Ack as it passes;
the whole map is fetched over HTTP every few seconds, and N HTTP clients fetch tiles (over TLS and
with a bearer token when the server's settings and --http-token/--http-ca say so). When
every agent is done (all its scans acknowledged) the server answers a final snapshot, is stopped
and restarted (meanwhile the workers that will replay the robots' beams get ready:
services.sim.replays); then the record is graded (services.sim.grading) and, with --report,
written out (services.sim.render).
"""

from __future__ import annotations

import dataclasses
import io
import json
import math
import multiprocessing
import random
import resource
import sqlite3
import sys
import tempfile
import threading
import time
import urllib.error
from collections import Counter
from concurrent.futures import ThreadPoolExecutor
from http.client import HTTPException
from pathlib import Path

import numpy as np

from gmm_core import Grid
from services.config import GmmapConfig
from services.host import child_pids, cpu_cores, cpu_shares, cpu_ticks, die_with_parent, loop_rate
from services.http_client import Connection, HttpClient
from services.sim import plots
from services.sim.fleet import SimSource, SimulatedFleet, correction_interval, robot_name
from services.sim.grading import grade
from services.sim.processes import Processes, free_port, http_security_args
from services.sim.record import RunRecord, Snapshot, blocks, evaluation_grid
from services.sim.relay import CountingRelay
from services.sim.render import summary, write_report
from services.sim.replays import BeamReplays
from services.sim.tap import WireTap

TILE = 256  # cells per tile side, as the viewer asks
# Cells a graded snapshot asks for per request. A box draws every component whose rays reach it, so a
# ray is drawn and set up once per box it crosses: over the mine's graded box, boxes of 500,000 cells
# drew 2.8x the samples of one box and 1.5x the processor time of these (within 10 % of one box).
SNAPSHOT_CELLS = 4_000_000
ACK_TIMEOUT_S = 120.0  # the agents' --timeout: how long one waits for Acks after its last scan
SHED_WAIT_S = 5.0  # the longest Retry-After a tile client honours
SNAPSHOTS = 12  # graded instants of a run, about


def fetch_occupancy(client: HttpClient, grid: Grid) -> np.ndarray:
    """GET /v1/occupancy as npy, box by box, as many at a time as the server has cores (each box is
    traced by one tracer thread); a box shed (503) is asked again after its Retry-After."""
    out = np.empty(grid.array_shape, dtype=np.float32)

    def fetch(box: Grid, place: tuple[slice, ...]) -> None:
        bbox = ",".join(repr(float(v)) for v in (*box.origin, *box.upper))
        path = f"/v1/occupancy?bbox={bbox}&resolution={box.resolution}&format=npy&max_age=0"  # graded: every change
        while True:
            try:
                out[place] = np.load(io.BytesIO(client.get(path, timeout=300)))
                return
            except urllib.error.HTTPError as error:
                if error.code != 503:  # shed while the tracers are saturated: the grader asks again
                    raise
                time.sleep(float(error.headers.get("Retry-After", 1)))

    with ThreadPoolExecutor(cpu_cores()) as pool:
        for future in [pool.submit(fetch, box, place) for box, place in blocks(grid, SNAPSHOT_CELLS)]:
            future.result()
    return out


def tile_urls(grid: Grid) -> list[str]:
    """The viewer's tiles over the graded box: TILE cells a side, at 1, 2 and 4 times the base resolution."""
    base_res = 0.05 if grid.dim == 2 else 0.1  # a 3D tile spans the box's height as well
    urls = []
    for res in (base_res, 2 * base_res, 4 * base_res):
        size = TILE * res
        for ix in range(int(grid.origin[0] // size), int(math.ceil(grid.upper[0] / size))):
            for iy in range(int(grid.origin[1] // size), int(math.ceil(grid.upper[1] / size))):
                lo, hi = [ix * size, iy * size], [(ix + 1) * size, (iy + 1) * size]
                if grid.dim == 3:
                    lo, hi = lo + [grid.origin[2]], hi + [grid.upper[2]]
                urls.append(f"/v1/occupancy?bbox={','.join(f'{v:.4f}' for v in lo + hi)}&resolution={res}&format=png")
    return urls


def fetch_tiles(http: HttpClient, urls: list[str], clients: int, asking, stop, results) -> None:
    """`clients` threads fetching random tiles (paths of `urls`) until `stop` is set, as a viewer
    does: each on a connection it keeps; a shed request (503) waits its Retry-After (at most
    SHED_WAIT_S) before the next. Sets `asking` once they started; puts
    ((asked, latency, X-Map-Age) of the answered requests, failures by kind) on `results`."""
    die_with_parent(multiprocessing.parent_process().pid)
    latencies, errors, lock = [], Counter(), threading.Lock()

    def client(seed: int) -> None:
        rng, connection = random.Random(seed), Connection(http, timeout=60)
        while not stop.is_set():
            asked, start = time.time(), time.perf_counter()
            try:
                _, headers = connection.fetch(rng.choice(urls))
                with lock:
                    latencies.append((asked, time.perf_counter() - start, float(headers.get("X-Map-Age", "nan"))))
            except urllib.error.HTTPError as error:
                with lock:
                    errors[f"HTTP {error.code}"] += 1
                if error.code == 503:
                    stop.wait(min(SHED_WAIT_S, float(error.headers.get("Retry-After", 1))))
            except (OSError, HTTPException) as error:
                kind = f"HTTP {error.code}" if isinstance(error, urllib.error.HTTPError) else repr(error)[:120]
                with lock:
                    errors[kind] += 1
        connection.close()

    threads = [threading.Thread(target=client, args=(i,)) for i in range(clients)]
    for thread in threads:
        thread.start()
    asking.set()
    for thread in threads:
        thread.join()
    results.put((latencies, dict(errors)))


class TileClients:
    """HTTP clients in a process of their own, so that their threads do not hold up the relays' and the tap's."""

    def __init__(self, http: HttpClient, urls: list[str], clients: int, timeout: float = 120.0):
        """Returns once the clients are asking (a spawned interpreter takes seconds to import them:
        a short run's robots were done before the first request on a loaded machine)."""
        spawn = multiprocessing.get_context("spawn")  # no fork of a process running Zenoh
        asking, self._stop, self._results = spawn.Event(), spawn.Event(), spawn.Queue()
        args = (http, urls, clients, asking, self._stop, self._results)
        self._process = spawn.Process(target=fetch_tiles, args=args, daemon=True)
        self._process.start()
        deadline = time.monotonic() + timeout
        while not asking.wait(0.5):
            if not self._process.is_alive() or time.monotonic() > deadline:
                self._process.kill()
                raise RuntimeError(
                    f"the tile clients' process did not start asking (exit code {self._process.exitcode})"
                )

    def stop(self) -> tuple[list[tuple[float, float, float]], dict[str, int]]:
        """((epoch s asked, latency s, X-Map-Age s) of the answered requests, failures by kind)."""
        self._stop.set()
        answer = self._results.get(timeout=120)
        self._process.join()
        return answer


def resident_bytes(pid: int) -> int:
    """Resident memory of a process and of its children (a server's tracer processes), Linux; 0 where
    /proc does not say."""
    return _vm_rss(pid) + sum(_vm_rss(child) for child in child_pids(pid))


def _vm_rss(pid: int) -> int:
    try:
        with open(f"/proc/{pid}/status") as status:
            return next(int(line.split()[1]) * 1024 for line in status if line.startswith("VmRSS:"))
    except (OSError, StopIteration):
        return 0


def robot_groups(robots: int) -> list[list[int]]:
    """Robot indices per agent process (services.sim.robots): as many processes as cores, at most."""
    processes = min(robots, cpu_cores())
    return [list(range(g, robots, processes)) for g in range(processes)]


def published_scans(outbox: Path) -> int:
    """Scans the agent sent: acknowledged ones plus any still waiting in its outbox."""
    db = sqlite3.connect(f"file:{outbox}?mode=ro", uri=True, timeout=10)
    try:
        return db.execute(
            "SELECT (SELECT COUNT(*) FROM acked WHERE kind = 'scan') + "
            "(SELECT COUNT(*) FROM outbox WHERE kind = 'scan')"
        ).fetchone()[0]
    finally:
        db.close()


def stored_scans(data_dir: Path, fleet: str) -> dict[tuple[str, int], bytes]:
    db = sqlite3.connect(f"file:{data_dir / 'gmmap.db'}?mode=ro", uri=True, timeout=10)
    try:
        rows = db.execute("SELECT robot, node, raw FROM scans WHERE fleet = ?", (fleet,))
        return {(robot, node): raw for robot, node, raw in rows}
    finally:
        db.close()


def restart_time(start_server, http: HttpClient, nodes: int, timeout: float = 600.0) -> float | None:
    """Seconds from starting the server again on its data directory until it serves all `nodes`
    (None: not within `timeout`)."""
    started = time.monotonic()
    start_server()
    while time.monotonic() - started < timeout:
        try:
            if sum(r["nodes"] for r in json.loads(http.get("/v1/robots", timeout=5))) >= nodes:
                return time.monotonic() - started
        except OSError:
            pass  # not listening yet
        time.sleep(0.1)
    return None


def wait_prepared(procs: Processes, start: Path, groups: list[str]) -> None:
    """Until every robot process has written start/ready-NAME (Agent.prepare: its whole run fitted)."""
    print(f"gmmap sim: the robots prepare their run ({len(groups)} processes) ...", file=sys.stderr, flush=True)
    while not all((start / f"ready-{g}").exists() for g in groups):
        ended = [g for g in groups if procs.reap(g) is not None]
        if ended:
            raise RuntimeError(f"gmmap sim: robots {ended[0]} exited while preparing:\n{procs.log_tail(ended[0])}")
        time.sleep(0.1)


def run_fleet(config: GmmapConfig, workdir: Path) -> tuple[RunRecord, BeamReplays]:
    """Run the fleet once; server, agents, relays and the tap are gone when this returns, and the
    workers of its beam replays, started when the robots were done, wait for grading to begin."""
    from tqdm import tqdm

    o = config.sim
    settings = workdir / "gmmap.toml"  # the robots' fit and the server's reconstruction, as resolved here
    settings.write_text(config.to_toml())

    fleet = SimulatedFleet(o.world, o.robots, o.scans, o.rate, o.seed)
    grid = evaluation_grid(fleet)
    names = [robot_name(i) for i in range(o.robots)]
    procs = Processes(workdir)
    relays: dict[str, CountingRelay] = {}
    tap = clients = replays = None
    usage = resource.getrusage(resource.RUSAGE_SELF)
    cpu_before = usage.ru_utime + usage.ru_stime
    try:
        zport, hport = free_port(), free_port()
        server = dataclasses.replace(config.server, http=f"127.0.0.1:{hport}")
        http = HttpClient.for_server(server, o.http_token, o.http_ca)

        def start_server(name: str = "server") -> None:
            data, security = workdir / "data", http_security_args(server)
            procs.server(zport, server.http, data, o.fleet, "--config", str(settings), *security, name=name)

        start_server()
        tap = WireTap(o.fleet, zport)
        record = RunRecord(config, fleet, grid, correction_interval(o.rate), time.time())
        # On one host Zenoh would hand messages over 3 kB to the server through shared memory,
        # around the link; a robot's radio link has no such shortcut.
        no_shm = workdir / "agent-zenoh.json5"
        no_shm.write_text("{transport: {shared_memory: {enabled: false}}}")
        for name in names:
            relays[name] = CountingRelay(zport)
        groups = robot_groups(o.robots)
        start = workdir / "start"  # the robots prepare their run, then wait for start/go
        start.mkdir()
        for g, members in enumerate(groups):
            procs.robots(
                f"robots-{g}",
                [(i, relays[names[i]].port) for i in members],
                SimSource(o.world, 0, o.robots, o.seed),
                o.rate,
                o.scans,
                o.fleet,
                "--time-scale",
                f"{o.time_scale:g}",
                "--start",
                str(start),
                "--name",
                f"robots-{g}",
                "--zenoh-config",
                str(no_shm),
                "--config",
                str(settings),
            )
        group_of = {names[i]: f"robots-{g}" for g, members in enumerate(groups) for i in members}
        wait_prepared(procs, start, sorted(set(group_of.values())))
        loop_rate_before = loop_rate()  # the robots wait for "go", no client asks yet: the host's own speed
        if o.http_clients:
            clients = TileClients(http, tile_urls(grid), o.http_clients)

        snapshots_dir = workdir / "snapshots"
        snapshots_dir.mkdir()
        (start / "go").touch()
        record.started = time.time()
        host_before = cpu_ticks()

        def snapshot() -> float:
            """Fetch and keep the whole graded map; the seconds it took."""
            t, stored = time.time(), tap.stored_per_robot()
            path = snapshots_dir / f"{len(record.snapshots):03d}.npy"
            np.save(path, fetch_occupancy(http, grid))
            record.snapshots.append(Snapshot(t, stored, path))
            return time.time() - t

        # A bounded number of graded instants however long the mission, each >= 3x the last fetch apart
        # (grading takes <= 1/4 of the server), taken on a thread of their own: a snapshot waiting for
        # busy tracers does not hold up the harness' sampling.
        every = max(2.0, o.wall_duration / SNAPSHOTS)
        deadline = time.monotonic() + o.wall_duration + ACK_TIMEOUT_S + 60
        driving = threading.Event()

        def snapshots_while_driving() -> None:
            wait = every
            while not driving.wait(wait):
                if tap.counts()[1]:
                    wait = max(every, 3 * snapshot())

        snapshotter = threading.Thread(target=snapshots_while_driving, name="gmmap-snapshots", daemon=True)
        snapshotter.start()
        total = o.robots * o.scans
        with (
            tqdm(total=total, desc="published", unit="scan", file=sys.stderr) as published,
            tqdm(total=total, desc="stored", unit="scan", file=sys.stderr) as stored,
        ):
            while any(procs.reap(g) is None for g in set(group_of.values())) and time.monotonic() < deadline:
                published.n, stored.n = tap.counts()
                record.server_rss.append((time.time(), resident_bytes(procs.running["server"].pid)))
                published.refresh()
                stored.refresh()
                time.sleep(0.2)
            published.n, stored.n = tap.counts()
        record.host_cpu = {
            **(cpu_shares(host_before, cpu_ticks()) or {}),
            "loop_rate_before": round(loop_rate_before, 2),
        }
        # The tile clients ask while the robots drive: stopped before waiting for a snapshot under way,
        # which otherwise stretched their window, by as long as that snapshot took, over the burst of
        # the robots' final corrections in some runs and not in others (docs/RELIABILITY.md).
        if clients is not None:
            record.tile_latencies, record.tile_errors = clients.stop()
            clients = None
        driving.set()
        snapshotter.join()
        for g in sorted(set(group_of.values())):
            code = procs.stop(g, timeout=5)  # only one past the deadline is still running
            if code != 0:
                print(f"gmmap sim: the robots of {g} exited {code}:\n{procs.log_tail(g)}", file=sys.stderr)
        record.agent_exit = {name: procs.running[g].returncode for name, g in group_of.items()}
        record.published = {name: published_scans(workdir / f"outbox-{name}.db") for name in names}
        replays = BeamReplays(record)  # its workers get ready while the server answers the final snapshot
        snapshot()  # the final map: an agent exits once its last pose-graph update is applied and acknowledged
        robots = json.loads(http.get("/v1/robots", timeout=30))
        record.components = {r["robot"]: r["components"] for r in robots}
        procs.stop("server")
        record.wall_s = time.time() - record.started
        record.restart_s = restart_time(lambda: start_server("restarted"), http, sum(r["nodes"] for r in robots))
        procs.stop("restarted")
        record.events = list(tap.events)
        record.link_bytes = {name: (relay.up, relay.down) for name, relay in relays.items()}
        record.stored = stored_scans(workdir / "data", o.fleet)
        usage = resource.getrusage(resource.RUSAGE_SELF)
        record.cpu_s = {
            "server": procs.cpu_s["server"],
            "agents": sum(procs.cpu_s[g] for g in set(group_of.values())),
            "harness": usage.ru_utime + usage.ru_stime - cpu_before,
        }
        return record, replays
    except BaseException:
        if replays is not None:
            replays.close()
        raise
    finally:
        if clients is not None:
            clients.stop()
        if tap is not None:
            tap.close()
        for relay in relays.values():
            relay.close()
        procs.close()


def run_sim(config: GmmapConfig) -> int:
    """One simulated fleet run as `config.sim` says (its values are validated by SimConfig)."""
    o = config.sim
    if o.report:
        plots.require_matplotlib()  # before the run, not after a minute of it
    with tempfile.TemporaryDirectory(prefix="gmmap-sim-") as tmp:
        record, replays = run_fleet(config, Path(tmp))
        grading = grade(record, replays)
        if o.report:
            write_report(grading, record, Path(o.report))
    report = grading.report
    print(summary(report))
    return 0 if report.scans_stored == report.scans_published else 1
