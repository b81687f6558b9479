"""The point query as a robot asks it over Zenoh (`gmmap/<fleet>/map/points`), on the served mine map.

    PYTHONPATH=. .venv/bin/python bench/points_served.py [--repeats 5]

bench/points.py times `point_probabilities` in process; this runs the product as bench/region_served.py
does: a `gmmap server` (one tracer thread, on one core) is sent the map of bench/mine_map.py over
Zenoh, and a robot's session asks `query_points` (services/agent/map_client.py) for points drawn
uniformly within 10 m of the last robot (1, 10 and 100 scattered, and the 4,096 cell centres of a
16 x 16 x 16 lattice there), each with `auto`, `analytic` and `mc`; the wall time of each query from
the robot's side (encode, Zenoh on loopback, the server's evaluation, decode), the median of
`--repeats`, the first query of each kind (the server's cold nodes) apart.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

import mine_map  # noqa: E402
from query3d import RESOLUTION, machine_line  # noqa: E402
from region_served import Served  # noqa: E402

from protocol.messages import POINT_METHODS  # noqa: E402
from services.agent.map_client import MapQueryError, query_points  # noqa: E402

REACH = 10.0  # m around the last robot


def timed(served: Served, points: np.ndarray, method: str) -> tuple[float, str]:
    start = time.perf_counter()
    reply = query_points(served.session, mine_map.FLEET, points, RESOLUTION, method=method, timeout=120)
    return time.perf_counter() - start, reply.method


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()
    messages, updates, position = mine_map.load()
    rng = np.random.default_rng(0)
    sets = {f"{n} scattered": position + rng.uniform(-REACH, REACH, (n, 3)) for n in (1, 10, 100)}
    lattice = np.stack(np.meshgrid(*[np.arange(16)] * 3, indexing="ij"), -1).reshape(-1, 3)
    sets["lattice of 4,096"] = position + (lattice + 0.5) * RESOLUTION
    print(machine_line())
    print(f"mine sim map: {len(messages)} nodes; cells of {RESOLUTION} m; wall time a query from the robot's side")
    print("| points | method asked | ran | first query | then, median | per point, then |")
    print("|---|---|---|---|---|---|")
    with tempfile.TemporaryDirectory() as data:
        served = Served(data)
        try:
            served.fill(messages, updates)
            for name, points in sets.items():
                for method in POINT_METHODS:
                    try:
                        first, ran = timed(served, points, method)
                    except MapQueryError as refused:  # beyond a request's limits: the server says so
                        print(f"| {name} | {method} | refused: {refused} | | | |", flush=True)
                        continue
                    then = float(np.median([timed(served, points, method)[0] for _ in range(args.repeats)]))
                    print(
                        f"| {name} | {method} | {ran} | {1e3 * first:.1f} ms | {1e3 * then:.1f} ms "
                        f"| {1e3 * then / len(points):.3f} ms |",
                        flush=True,
                    )
        finally:
            served.close()


if __name__ == "__main__":
    main()
