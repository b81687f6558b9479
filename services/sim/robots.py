"""`python -m services.sim.robots`: several simulated robots in one process, a full agent each.

Every robot keeps what a robot has of its own: its Agent, Zenoh session, link (relay port),
outbox and resender. Only the Python interpreter, numba's compiled fit and the simulated world
are shared: on one machine, twenty agent processes would spend most of a core on twenty
interpreters and twenty copies of the world, a core the map server needs.
"""

from __future__ import annotations

import argparse
import sys
import threading
from pathlib import Path

from services.agent.agent import run_agent
from services.agent.config import AgentConfig
from services.config import load_config
from services.datasets.keyframes import KeyframeConfig
from services.sim.fleet import SimSource, robot_name


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m services.sim.robots", description=__doc__.splitlines()[0])
    p.add_argument("members", nargs="+", metavar="INDEX:PORT", help="a robot of the fleet and its Zenoh endpoint")
    p.add_argument("--world", required=True)
    p.add_argument("--robots", type=int, required=True, help="robots in the whole fleet")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--fleet", default="default")
    p.add_argument("--scans", type=int, required=True)
    p.add_argument("--rate", type=float, required=True)
    p.add_argument("--workdir", type=Path, default=Path("."), help="where each robot's outbox goes")
    p.add_argument("--zenoh-config")
    p.add_argument("--config", help="a gmmap configuration file: its [fit] section is the robots' fit")
    args = p.parse_args(argv)
    fit = load_config(args.config).fit
    # A simulated robot publishes every scan, so that load and bandwidth figures compare across runs.
    every_scan = KeyframeConfig.every_scan()
    codes: dict[str, int] = {}

    def robot(index: int, port: int) -> None:
        name = robot_name(index)
        try:
            codes[name] = run_agent(
                AgentConfig(
                    robot=name,
                    source=str(SimSource(args.world, index, args.robots, args.seed)),
                    fleet=args.fleet,
                    zenoh_connect=(f"tcp/127.0.0.1:{port}",),
                    zenoh_config=args.zenoh_config,
                    scans=f"0:{args.scans}",
                    rate=args.rate,
                    outbox=str(args.workdir / f"outbox-{name}.db"),
                ),
                fit,
                every_scan,
            )
        except Exception as error:  # noqa: BLE001 - one robot's failure is reported, the others go on
            print(f"robot {name}: {type(error).__name__}: {error}", file=sys.stderr, flush=True)
            codes[name] = 2

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
