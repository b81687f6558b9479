"""`gmmap agent`: one agent over a whole source (a log, a simulated robot), until its nodes are
published and acknowledged; a finite source ends when the outbox is empty."""

from __future__ import annotations

import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import replace

from gmm_core import FitConfig
from services.config import summary
from services.datasets.keyframes import KeyframeConfig
from services.zenoh_config import zenoh_config

from .agent import Agent, closure_schedule
from .config import AgentConfig
from .outbox import Outbox
from .outcome import run_outcome
from .sources import Node, SimulatedNodes, default_update_every, load_nodes


def _requeued(agent: Agent) -> str:
    """What the store lacked of what earlier stores acknowledged, for the summary line."""
    parts = [f"sent again {n} acknowledged by store {s or '(unnamed, protocol v1)'}" for s, n in agent.requeued.items()]
    if agent.refitted:
        parts.append(f"{agent.refitted} scans no longer kept were fitted again")
    if agent.lost:
        parts.append(f"{len(agent.lost)} scans no longer kept are lost")
    if not parts:
        return ""
    lacked = sum(agent.requeued.values()) + agent.refitted + len(agent.lost)
    return f" (the store lacked {lacked} acknowledged messages: {'; '.join(parts)})"


def run_agent(
    o: AgentConfig,
    fit: FitConfig,
    keyframe: KeyframeConfig,
    nodes: Sequence[Node] | SimulatedNodes | None = None,
    ready: Callable[[], None] | None = None,
) -> int:
    """Run one agent until its source is published and acknowledged; the process exit code: 0, 1 if
    messages are not acknowledged within the timeout, 3 if the server refused some for good (outcome.py).

    `nodes`: the source's nodes when the caller built them (else read from `o.source`); `ready`:
    with it, every node is fitted ahead (Agent.prepare) and `ready()` is called, which returns when
    publishing may start (a simulated fleet starts its timed run once every robot is prepared).
    """
    o.check_runnable()
    started = time.perf_counter()
    print(f"gmmap agent {o.robot} config: {summary(agent=o, fit=fit, keyframe=keyframe)}", file=sys.stderr, flush=True)
    if o.update_every is None:
        o = replace(o, update_every=default_update_every(o.source, o.rate))
    if nodes is None:
        nodes = load_nodes(
            o.source, o.corrections, o.scans, rate=o.rate, update_every=o.update_every, **o.reader_options()
        )
    if o.odometry_only:  # a robot without a SLAM back end: same nodes, odometry stays final
        nodes = [replace(n, corrected=None) for n in nodes]
    outbox = Outbox(o.outbox_path, o.fleet, o.robot, o.keep_acked_bytes)
    agent = Agent(o, outbox, zenoh_config("client", connect=o.zenoh_connect, config_file=o.zenoh_config), fit, keyframe)
    try:
        from tqdm import tqdm

        closures = closure_schedule(nodes, o.update_every)  # of the source: prepared nodes are a list
        if ready is not None:
            with tqdm(total=len(nodes), desc=f"{o.robot} prepare", unit="scan", file=sys.stderr, leave=False) as bar:
                nodes = agent.prepare(nodes, bar.update)
            ready()
            started = time.perf_counter()
        # Against the store's inventory first, when it answers soon: what it lacks is sent again.
        agent.wait_reconciled(min(o.timeout, 5.0))
        with tqdm(total=len(nodes), desc=f"{o.robot} publish", unit="scan", file=sys.stderr, leave=False) as bar:
            updates = agent.publish_all(nodes, bar.update, closures)
        reconciled = agent.wait_reconciled(o.timeout)
        if reconciled:  # a store that answered late may lack what is no longer kept
            agent.refit(nodes)
        published = time.perf_counter()
        # no store answered within the timeout: say so now rather than wait a second one
        pending = agent.wait_acknowledged(o.timeout if reconciled else 0.0)
        resumed = f" ({agent.resumed} of them from a previous run: resumed)" if agent.resumed else ""
        skipped = f" (keyframes of {len(nodes)} read)" if agent.kept < len(nodes) else ""
        success = (
            f"{agent.kept} scans{skipped}{resumed} and {updates} pose-graph updates "
            f"acknowledged by store {agent.store}{_requeued(agent)}; "
            f"published after {published - started:.1f} s, all acknowledged after "
            f"{time.perf_counter() - started:.1f} s"
        )
        hint = f" (is a server for fleet {o.fleet!r} reachable at {','.join(o.zenoh_connect)}?)"
        return run_outcome(agent, pending, success, hint)
    finally:
        agent.close()
        outbox.close()
