"""Crash and restart trials with real processes: nothing acknowledged may ever be lost.

Two agents (robots a and b) replay slices of the raw Intel log with its SLAM corrections at
--rate scans/s into a `gmmap server` on 127.0.0.1. Three kinds of trial:

  server  kill -9 of the server when the store holds a random number of scans, restart on the
          same data dir: at the kill, every scan an agent holds as acknowledged is in the store
          and PRAGMA integrity_check is ok; after the restart both agents finish (exit 0) and the
          store holds every scan, each row valid.
  router  agents -> `gmmap router` <- server; kill -9 of the router mid-run, restart after a
          random pause: agents and server reconnect, agents resend, nothing is lost.
  agent   kill -9 of agent a mid-run, restart with the same outbox: it resumes (skips what was
          acknowledged, the resender sends what was held) and both finish with nothing lost.

Prints one line per trial and a summary (JSON with --json); exits 1 when a check fails. Usage:

    .venv/bin/python bench/crash_trials.py [--server 10] [--router 3] [--agent 3] [--scans 300]
        [--rate 100] [--seed 0] [--json]
"""

from __future__ import annotations

import argparse
import json
import os
import random
import signal
import sqlite3
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from services.map_server.check import check_store  # noqa: E402
from services.sim.processes import free_port  # noqa: E402

DATA = ROOT.parent / "shared" / "data"
RAW, CORRECTED = DATA / "radish" / "intel.clf.bz2", DATA / "carmen" / "intel-corrected.log.gz"
FINISH_S = 180  # an agent must be done this long after the last disturbance


def read_ids(db: Path, query: str, *args) -> set[int]:
    """Ids from a SQLite file another process is writing (read-only, WAL), empty if not there yet."""
    if not db.exists():
        return set()
    conn = sqlite3.connect(f"file:{db}?mode=ro", uri=True, timeout=10)
    try:
        return {i for (i,) in conn.execute(query, args)}
    except sqlite3.OperationalError:  # the schema is not written yet
        return set()
    finally:
        conn.close()


class Trial:
    """The processes of one trial, in its own directory; everything is killed at the end."""

    def __init__(self, work: Path, scans: int, rate: float):
        self.work, self.rate = work, rate
        self.slices = {"a": (0, scans), "b": (455, 455 + scans)}  # two stretches of the run
        self.procs: list[subprocess.Popen] = []
        self.env = dict(os.environ, PYTHONPATH=str(ROOT), PYTHONUNBUFFERED="1")
        self.data = work / "data"

    def start(self, name: str, *args: str, banner: str | None = None) -> subprocess.Popen:
        log = self.work / f"{name}.log"  # a restart appends to the same log
        offset = log.stat().st_size if log.exists() else 0
        with log.open("ab") as out:
            proc = subprocess.Popen(
                [sys.executable, "-m", "services.cli", *args],
                cwd=self.work,
                env=self.env,
                stdout=out,
                stderr=subprocess.STDOUT,
            )
        self.procs.append(proc)
        deadline = time.monotonic() + 60
        while banner and banner.encode() not in log.read_bytes()[offset:]:
            if proc.poll() is not None or time.monotonic() > deadline:
                raise RuntimeError(f"{name} did not start:\n{log.read_text(errors='replace')[-2000:]}")
            time.sleep(0.02)
        return proc

    def server(self, zenoh_args: list[str], hport: int) -> subprocess.Popen:
        return self.start(
            "server",
            "server",
            *zenoh_args,
            "--http",
            f"127.0.0.1:{hport}",
            "--data-dir",
            str(self.data),
            banner="gmmap server ready",
        )

    def agent(self, robot: str, port: int) -> subprocess.Popen:
        a, b = self.slices[robot]
        return self.start(
            f"agent-{robot}",
            "agent",
            "--robot",
            robot,
            "--zenoh-connect",
            f"tcp/127.0.0.1:{port}",
            "--source",
            f"carmen:{RAW}",
            "--corrections",
            str(CORRECTED),
            "--scans",
            f"{a}:{b}",
            "--rate",
            str(self.rate),
            "--resend",
            "0.5",
            "--timeout",
            str(FINISH_S),
            "--outbox",
            str(self.outbox(robot)),
        )

    def outbox(self, robot: str) -> Path:
        return self.work / f"outbox-{robot}.db"

    def stored(self, robot: str | None = None) -> set[int]:
        if robot is None:
            return read_ids(self.data / "gmmap.db", "SELECT node FROM scans")
        return read_ids(self.data / "gmmap.db", "SELECT node FROM scans WHERE robot = ?", robot)

    def acked(self, robot: str) -> set[int]:
        return read_ids(self.outbox(robot), "SELECT id FROM acked WHERE kind = 'scan'")

    def lost(self) -> int:
        """Scans an agent holds as acknowledged that the store lacks (must stay 0)."""
        return sum(len(self.acked(r) - self.stored(r)) for r in self.slices)

    def wait_stored(self, count: int, timeout: float = 120) -> None:
        deadline = time.monotonic() + timeout
        while len(self.stored()) < count:
            if time.monotonic() > deadline:
                raise RuntimeError(f"fewer than {count} scans stored after {timeout} s")
            time.sleep(0.02)

    def finish(self, agents: dict[str, subprocess.Popen]) -> dict[str, int | str]:
        codes = {}
        for robot, proc in agents.items():
            try:
                codes[robot] = proc.wait(FINISH_S + 30)
            except subprocess.TimeoutExpired:
                codes[robot] = "still running"
        return codes

    def complete(self) -> bool:
        return all(self.stored(r) == set(range(*self.slices[r])) for r in self.slices)

    def close(self) -> None:
        for proc in self.procs:
            if proc.poll() is None:
                proc.kill()
                proc.wait()


def kill9(proc: subprocess.Popen) -> None:
    proc.send_signal(signal.SIGKILL)
    proc.wait()


def server_trial(trial: Trial, rng: random.Random) -> dict:
    zport, hport = free_port(), free_port()
    listen = ["--zenoh-listen", f"tcp/127.0.0.1:{zport}"]
    server = trial.server(listen, hport)
    agents = {r: trial.agent(r, zport) for r in trial.slices}
    total = sum(b - a for a, b in trial.slices.values())
    target = rng.randint(1, int(total * 0.9))
    trial.wait_stored(target)
    kill9(server)
    at_kill = {
        "stored": len(trial.stored()),
        "acked": sum(len(trial.acked(r)) for r in trial.slices),
        "lost": trial.lost(),
    }
    dead = check_store(trial.data)
    restarted = time.monotonic()
    trial.server(listen, hport)
    ready = time.monotonic() - restarted
    codes = trial.finish(agents)
    final = check_store(trial.data)
    return {
        "kill_at_stored": target,
        **at_kill,
        "integrity_at_kill": dead.integrity,
        "bad_rows_at_kill": len(dead.bad),
        "restart_s": round(ready, 2),
        "finish_s": round(time.monotonic() - restarted, 1),
        "exit_codes": codes,
        "complete": trial.complete(),
        "lost_final": trial.lost(),
        "integrity": final.integrity,
        "bad_rows": len(final.bad),
        "scans": final.scans,
        "ok": (
            at_kill["lost"] == 0
            and dead.ok
            and final.ok
            and trial.complete()
            and trial.lost() == 0
            and all(c == 0 for c in codes.values())
        ),
    }


def router_trial(trial: Trial, rng: random.Random) -> dict:
    rport, hport = free_port(), free_port()
    router_args = ["router", "--listen", f"tcp/127.0.0.1:{rport}"]
    router = trial.start("router", *router_args, banner="gmmap router ready")
    trial.server(["--zenoh-connect", f"tcp/127.0.0.1:{rport}"], hport)
    agents = {r: trial.agent(r, rport) for r in trial.slices}
    total = sum(b - a for a, b in trial.slices.values())
    trial.wait_stored(rng.randint(1, int(total * 0.6)))
    kill9(router)
    at_kill = len(trial.stored())
    pause = rng.uniform(0.2, 3.0)
    time.sleep(pause)
    during = len(trial.stored())
    restarted = time.monotonic()
    trial.start("router", *router_args, banner="gmmap router ready")
    trial.wait_stored(during + 1)
    resumed = time.monotonic() - restarted
    codes = trial.finish(agents)
    final = check_store(trial.data)
    return {
        "kill_at_stored": at_kill,
        "router_down_s": round(pause, 2),
        "stored_while_down": during - at_kill,
        "first_scan_after_restart_s": round(resumed, 2),
        "finish_s": round(time.monotonic() - restarted, 1),
        "exit_codes": codes,
        "complete": trial.complete(),
        "lost": trial.lost(),
        "integrity": final.integrity,
        "bad_rows": len(final.bad),
        "ok": final.ok and trial.complete() and trial.lost() == 0 and all(c == 0 for c in codes.values()),
    }


def agent_trial(trial: Trial, rng: random.Random) -> dict:
    zport, hport = free_port(), free_port()
    trial.server(["--zenoh-listen", f"tcp/127.0.0.1:{zport}"], hport)
    agents = {r: trial.agent(r, zport) for r in trial.slices}
    a0, a1 = trial.slices["a"]
    target = rng.randint(1, int((a1 - a0) * 0.9))
    deadline = time.monotonic() + 120
    while len(trial.stored("a")) < target and time.monotonic() < deadline:
        time.sleep(0.02)
    kill9(agents["a"])
    held = read_ids(trial.outbox("a"), "SELECT id FROM outbox WHERE kind = 'scan'")
    skipped = len(trial.acked("a") | held)
    restarted = time.monotonic()
    agents["a"] = trial.agent("a", zport)
    codes = trial.finish(agents)
    final = check_store(trial.data)
    log = trial.work.joinpath("agent-a.log").read_text(errors="replace")
    return {
        "kill_at_stored_a": target,
        "held_in_outbox": len(held),
        "skipped_on_restart": skipped,
        "finish_s": round(time.monotonic() - restarted, 1),
        "exit_codes": codes,
        "complete": trial.complete(),
        "lost": trial.lost(),
        "integrity": final.integrity,
        "bad_rows": len(final.bad),
        "agent_log_tracebacks": log.count("Traceback"),
        "ok": final.ok and trial.complete() and trial.lost() == 0 and all(c == 0 for c in codes.values()),
    }


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--server", type=int, default=10, help="server kill -9 trials")
    parser.add_argument("--router", type=int, default=3, help="router kill -9 and restart trials")
    parser.add_argument("--agent", type=int, default=3, help="agent kill -9 and restart trials")
    parser.add_argument("--scans", type=int, default=300, help="scans per robot")
    parser.add_argument("--rate", type=float, default=100.0, help="scans per second per robot")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args()
    if not RAW.exists():
        print(f"the Intel logs are not in {DATA}", file=sys.stderr)
        return 2
    rng = random.Random(args.seed)
    results = []
    plan = (
        [("server", server_trial)] * args.server
        + [("router", router_trial)] * args.router
        + [("agent", agent_trial)] * args.agent
    )
    for number, (kind, run) in enumerate(plan, 1):
        with tempfile.TemporaryDirectory(prefix=f"gmmap-{kind}-") as tmp:
            trial = Trial(Path(tmp), args.scans, args.rate)
            started = time.monotonic()
            try:
                result = run(trial, rng)
            except Exception as error:  # a trial that cannot even run is a failed trial
                result = {"ok": False, "error": f"{type(error).__name__}: {error}"}
            finally:
                trial.close()
            result = {"trial": number, "kind": kind, "seconds": round(time.monotonic() - started, 1), **result}
        results.append(result)
        if not args.json:
            print(json.dumps(result), flush=True)
    summary = {
        kind: {
            "trials": sum(r["kind"] == kind for r in results),
            "ok": sum(r["kind"] == kind and r["ok"] for r in results),
        }
        for kind in ("server", "router", "agent")
    }
    if args.json:
        print(json.dumps({"summary": summary, "trials": results}))
    else:
        print(json.dumps({"summary": summary}))
    return 0 if all(r["ok"] for r in results) else 1


if __name__ == "__main__":
    sys.exit(main())
