"""`gmmap` subprocesses of a simulation or demo: a map server and robot agents, each logging to a file."""

from __future__ import annotations

import functools
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

from services.host import die_with_parent
from services.map_server.config import ServerConfig
from services.sim.fleet import SimSource

ROOT = Path(__file__).resolve().parents[2]  # the package's parent, for `python -m services.cli`
SERVER_READY = "gmmap server ready"


_handed_out: set[int] = set()  # free_port's ports so far, this process
_handed_out_lock = threading.Lock()


def free_port() -> int:
    """A loopback TCP port that is free now and that this process has not handed out before: the
    port is released at once, so two calls in a row could get the same one (a server's Zenoh and
    HTTP ports once did: "address already in use")."""
    while True:
        with socket.socket() as s:
            s.bind(("127.0.0.1", 0))
            port = s.getsockname()[1]
        with _handed_out_lock:
            if port not in _handed_out:
                _handed_out.add(port)
                return port


def http_security_args(server: ServerConfig) -> tuple[str, ...]:
    """`gmmap server` flags for the TLS, tokens and --http-insecure of `server`, with absolute paths:
    a child runs in its work directory."""
    files = (
        ("--http-tls-cert", server.http_tls_cert),
        ("--http-tls-key", server.http_tls_key),
        ("--http-tokens", server.http_tokens),
    )
    args = [arg for flag, path in files if path for arg in (flag, os.path.abspath(path))]
    return (*args, "--http-insecure") if server.http_insecure else tuple(args)


# A simulated robot publishes every scan (no keyframe policy), so load and bandwidth figures compare.
EVERY_SCAN = ("--keyframe-distance", "0", "--keyframe-angle", "0", "--keyframe-period", "0")


class Processes:
    """Children started with `python -m services.cli`; `close` stops whatever still runs."""

    def __init__(self, workdir: Path):
        self.workdir = workdir
        self.running: dict[str, subprocess.Popen] = {}
        self.log_start: dict[str, int] = {}  # where the running child's lines begin in its (appended) log
        self.cpu_s: dict[str, float] = {}  # user + system seconds of each child that was reaped
        path = os.pathsep.join(filter(None, [str(ROOT), os.environ.get("PYTHONPATH")]))
        self.env = dict(os.environ, PYTHONPATH=path, PYTHONUNBUFFERED="1")

    def log_path(self, name: str) -> Path:
        return self.workdir / f"{name}.log"

    def log_tail(self, name: str, chars: int = 2000) -> str:
        return self.log_path(name).read_text(errors="replace")[-chars:]

    def start(self, name: str, *args: str, module: str = "services.cli", env: dict | None = None) -> subprocess.Popen:
        """A child under `name` (its log `name`.log, appended to); a name is reused only once its child has ended."""
        previous = self.running.get(name)
        if previous is not None and previous.poll() is None:  # replaced, it would outlive `close`
            raise ValueError(f"a process named {name} is still running")
        with open(self.log_path(name), "ab") as log:
            self.log_start[name] = log.seek(0, os.SEEK_END)
            # A session of its own: Ctrl-C reaches the parent only, which stops the children in order.
            proc = subprocess.Popen(
                [sys.executable, "-m", module, *args],
                cwd=self.workdir,
                env={**self.env, **(env or {})},
                stdout=log,
                stderr=subprocess.STDOUT,
                start_new_session=True,
                preexec_fn=functools.partial(die_with_parent, os.getpid()),
            )
        self.running[name] = proc
        return proc

    def wait_ready(self, name: str, banner: str, timeout: float = 60.0) -> subprocess.Popen:
        """The child once `banner` is in its log; OSError with the log's end if it exits or `timeout` s pass."""
        proc = self.running[name]
        deadline = time.monotonic() + timeout
        # Only this child's lines: a restarted one must not be taken for ready on its predecessor's banner.
        while banner.encode() not in self.log_path(name).read_bytes()[self.log_start[name] :]:
            if proc.poll() is not None or time.monotonic() > deadline:
                raise OSError(f"{name} did not print {banner!r}:\n{self.log_tail(name)}")
            time.sleep(0.05)
        return proc

    def server(
        self,
        zenoh_port: int | None,
        http: str,
        data_dir: Path,
        fleet: str = "default",
        *extra: str,
        name: str = "server",
    ) -> subprocess.Popen:
        """A map server listening on `zenoh_port` (None: no listener; `extra` options say how it connects)."""
        listen = ("--zenoh-listen", f"tcp/127.0.0.1:{zenoh_port}") if zenoh_port is not None else ()
        self.start(name, "server", "--fleet", fleet, *listen, "--http", http, "--data-dir", str(data_dir), *extra)
        return self.wait_ready(name, SERVER_READY)

    def agent(
        self, robot: str, source: str, zenoh_port: int, rate: float, scans: int, fleet: str = "default", *extra: str
    ) -> subprocess.Popen:
        """A simulated robot publishing its first `scans` scans at `rate` per second."""
        return self.start(
            f"agent-{robot}",
            "agent",
            "--robot",
            robot,
            "--fleet",
            fleet,
            "--source",
            source,
            "--scans",
            f"0:{scans}",
            "--rate",
            f"{rate:g}",
            "--zenoh-connect",
            f"tcp/127.0.0.1:{zenoh_port}",
            "--outbox",
            str(self.workdir / f"outbox-{robot}.db"),
            *EVERY_SCAN,
            *extra,
        )

    def robots(
        self,
        name: str,
        members: list[tuple[int, int]],
        source: SimSource,
        rate: float,
        scans: int,
        fleet: str = "default",
        *extra: str,
    ) -> subprocess.Popen:
        """Simulated robots (index, Zenoh port) of one fleet in one process (services.sim.robots)."""
        return self.start(
            name,
            *(f"{i}:{port}" for i, port in members),
            "--world",
            source.world,
            "--robots",
            str(source.robots),
            "--seed",
            str(source.seed),
            "--fleet",
            fleet,
            "--scans",
            str(scans),
            "--rate",
            f"{rate:g}",
            "--workdir",
            str(self.workdir),
            *extra,
            # One numba thread per process: robots fit and simulate one scan at a time,
            # and idle OpenMP threads would spin on the cores the server needs.
            module="services.sim.robots",
            env={"NUMBA_NUM_THREADS": "1"},
        )

    def reap(self, name: str, block: bool = False) -> int | None:
        """The child's exit code once it has ended (its CPU time noted), else None."""
        proc = self.running[name]
        if proc.returncode is None:
            pid, status, usage = os.wait4(proc.pid, 0 if block else os.WNOHANG)
            if pid == 0:
                return None
            proc.returncode = os.waitstatus_to_exitcode(status)  # Popen must not wait for it again
            self.cpu_s[name] = usage.ru_utime + usage.ru_stime
        return proc.returncode

    def stop(self, name: str, timeout: float = 15.0) -> int:
        """SIGTERM, then SIGKILL after `timeout` s; the exit code."""
        proc = self.running[name]
        if proc.returncode is None:
            proc.send_signal(signal.SIGTERM)
            deadline = time.monotonic() + timeout
            while self.reap(name) is None:
                if time.monotonic() > deadline:
                    proc.kill()
                    return self.reap(name, block=True)
                time.sleep(0.05)
        return proc.returncode

    def close(self) -> None:
        for name, proc in self.running.items():
            if proc.returncode is None:
                proc.kill()
                self.reap(name, block=True)
