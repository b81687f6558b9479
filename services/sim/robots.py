"""`python -m services.sim.robots`: several simulated robots in one process, a full agent each.

Every robot keeps what a robot has of its own: its Agent, Zenoh session, link (relay port),
outbox and resender. Only the Python interpreter, numba's compiled fit and the simulated world
are shared: on one machine, twenty agent processes would spend most of a core on twenty
interpreters and twenty copies of the world, a core the map server needs.

With --start DIR the robots prepare their run first (every scan simulated, fitted and encoded:
Agent.prepare), then the process writes DIR/ready-NAME and waits for DIR/go, so the timed run
measures the server and the links, not the fit. With --time-scale X they publish at X times
their simulated rate: X simulated seconds per wall second.
"""

from __future__ import annotations

import argparse
import sys
import threading
import time
from pathlib import Path

from services.agent.config import AgentConfig
from services.agent.run import run_agent
from services.agent.sources import simulated_nodes
from services.config import load_config
from services.datasets.keyframes import KeyframeConfig
from services.sim.fleet import SimSource, correction_interval, robot_name


def wait_for_start(start: Path | None, name: str) -> None:
    """Say this process is prepared, and wait for the harness to start the timed run."""
    if start is None:
        return
    (start / f"ready-{name}").touch()
    while not (start / "go").exists():
        time.sleep(0.05)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m services.sim.robots", description=__doc__.splitlines()[0])
    p.add_argument("members", nargs="+", metavar="INDEX:PORT", help="a robot of the fleet and its Zenoh endpoint")
    p.add_argument("--world", required=True)
    p.add_argument("--robots", type=int, required=True, help="robots in the whole fleet")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--fleet", default="default")
    p.add_argument("--scans", type=int, required=True)
    p.add_argument("--rate", type=float, required=True, help="scans per simulated second")
    p.add_argument("--time-scale", type=float, default=1.0, help="simulated seconds per wall second")
    p.add_argument("--start", type=Path, help="prepare, write START/ready-NAME, then wait for START/go")
    p.add_argument("--name", default="robots", help="this process, in the ready file's name")
    p.add_argument("--workdir", type=Path, default=Path("."), help="where each robot's outbox goes")
    p.add_argument("--zenoh-config")
    p.add_argument("--config", help="a gmmap configuration file: its [fit] section is the robots' fit")
    args = p.parse_args(argv)
    fit = load_config(args.config).fit
    # A simulated robot publishes every scan, so that load and bandwidth figures compare across runs.
    every_scan = KeyframeConfig.every_scan()
    codes: dict[str, int] = {}
    every = correction_interval(args.rate)  # loop closures by simulated time, whatever the time scale
    prepared = threading.Barrier(len(args.members), action=lambda: wait_for_start(args.start, args.name))

    def robot(index: int, port: int) -> None:
        name = robot_name(index)
        source = str(SimSource(args.world, index, args.robots, args.seed))
        try:
            codes[name] = run_agent(
                AgentConfig(
                    robot=name,
                    source=source,
                    fleet=args.fleet,
                    zenoh_connect=(f"tcp/127.0.0.1:{port}",),
                    zenoh_config=args.zenoh_config,
                    scans=f"0:{args.scans}",
                    rate=args.rate * args.time_scale,
                    update_every=every,
                    outbox=str(args.workdir / f"outbox-{name}.db"),
                ),
                fit,
                every_scan,
                nodes=simulated_nodes(source, f"0:{args.scans}", args.rate, every),
                ready=None if args.start is None else prepared.wait,
            )
        except Exception as error:  # noqa: BLE001 - one robot's failure is reported, the others go on
            print(f"robot {name}: {type(error).__name__}: {error}", file=sys.stderr, flush=True)
            codes[name] = 2
            prepared.abort()  # the others would wait for this one forever

    threads = []
    for member in args.members:
        index, port = (int(v) for v in member.split(":"))
        threads.append(threading.Thread(target=robot, args=(index, port), name=f"robot-{index}"))
        threads[-1].start()
    for thread in threads:
        thread.join()
    for name, code in sorted(codes.items()):
        print(f"robot {name}: exit {code}", file=sys.stderr, flush=True)
    return max(codes.values())


if __name__ == "__main__":
    sys.exit(main())
