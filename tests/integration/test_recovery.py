"""Restarts in the middle of a run, one trial each (bench/crash_trials.py runs many): the Zenoh
router between agents and server is killed and restarted; an agent is killed and restarted on
its outbox. Nothing acknowledged may be lost, and everything must arrive in the end."""

from __future__ import annotations

import signal
import time

from protocol import parse_key, scan_wildcard
from services.map_server.check import check_store
from support.net import free_port, wait_for
from support.processes import HALVES, acked_nodes, stored_nodes, written_nodes

RATE = "150"  # scans per second per agent: the 455 scans of a half take about 3 s


def assert_complete_and_sound(data, tmp_path) -> None:
    for robot, (start, stop) in (("a", (0, 455)), ("b", (455, 910))):
        assert stored_nodes(data, robot) == set(range(start, stop)), robot
        assert acked_nodes(tmp_path / f"outbox-{robot}.db") <= stored_nodes(data, robot)
    check = check_store(data)
    assert check.ok and check.scans == 910, (check.integrity, check.bad[:3])


def test_router_killed_and_restarted_mid_run_loses_nothing(procs, data_dir, tmp_path):
    rport, data = free_port(), tmp_path / "data"
    router_args = ("router", "router", "--listen", f"tcp/127.0.0.1:{rport}")
    router = procs.ready(procs.start(*router_args), "gmmap router ready")
    procs.server("server", data, 0, free_port(), "--zenoh-connect", f"tcp/127.0.0.1:{rport}")
    agents = [procs.agent(r, rport, data_dir, "--rate", RATE, "--resend", "0.5", "--timeout", "60") for r in HALVES]
    # Both under way: an agent that has stored nothing may not have opened its outbox yet (under
    # load one can start seconds after the other), and reading it would fail on a file not there.
    wait_for(
        lambda: min(len(stored_nodes(data, r)) for r in HALVES) >= 50,
        60,
        "50 stored scans of each robot",
        interval=0.02,
    )

    router.send_signal(signal.SIGKILL)
    router.wait()
    outboxes = {r: tmp_path / f"outbox-{r}.db" for r in HALVES}
    written_at_kill = {r: written_nodes(outboxes[r]) for r in HALVES}  # or just after it
    acked_at_kill = {r: acked_nodes(outboxes[r]) for r in HALVES}
    for robot in HALVES:
        assert acked_at_kill[robot] <= stored_nodes(data, robot)
    time.sleep(1.0)  # down for a while
    for robot, agent in zip(HALVES, agents):  # the first may have been through before the second started
        if len(acked_at_kill[robot]) < 455:
            assert agent.poll() is None, f"agent {robot} finished without a router"
    # No path from agents to server while it is down: what the agents wrote since cannot be stored.
    # (The count of stored scans may still grow: the server's queue holds what arrived before the kill.)
    for robot in HALVES:
        assert not (written_nodes(outboxes[robot]) - written_at_kill[robot]) & stored_nodes(data, robot), robot

    # Same port, a new process: agents (clients) and server (peer) reconnect by themselves.
    procs.ready(procs.start(*router_args), "gmmap router ready")
    for a in agents:
        assert procs.finish(a, 90) == 0, procs.log(a)
    assert_complete_and_sound(data, tmp_path)


def test_agent_killed_and_restarted_resumes_from_its_outbox(procs, session_to, data_dir, tmp_path):
    zport, hport, data = free_port(), free_port(), tmp_path / "data"
    procs.server("server", data, zport, hport)
    options = ("--rate", RATE, "--resend", "0.5", "--timeout", "60")
    agents = {r: procs.agent(r, zport, data_dir, *options) for r in HALVES}
    wait_for(lambda: len(stored_nodes(data, "a")) >= 100, 60, "100 stored scans of a", interval=0.02)
    # Stored is not yet acknowledged: on a loaded machine the Acks reach the outbox later (a fresh-clone
    # run killed the agent with none recorded, and the test had nothing to check).
    wait_for(lambda: len(acked_nodes(tmp_path / "outbox-a.db")) >= 50, 60, "50 acknowledged scans of a")

    agents["a"].send_signal(signal.SIGKILL)
    agents["a"].wait()
    acked, written = acked_nodes(tmp_path / "outbox-a.db"), written_nodes(tmp_path / "outbox-a.db")
    assert acked and acked <= stored_nodes(data, "a")

    published = []  # (fleet, robot, "scan", node) of every scan published from here on, resends too
    spy = session_to(zport).declare_subscriber(
        scan_wildcard("default"), lambda sample: published.append(parse_key(str(sample.key_expr)))
    )
    agents["a"] = procs.agent("a", zport, data_dir, *options)
    for agent in agents.values():
        assert procs.finish(agent, 90) == 0, procs.log(agent)
    assert_complete_and_sound(data, tmp_path)
    spy.undeclare()
    # It resumed: the scans acknowledged before the kill were neither fitted nor sent again (how
    # often the others were sent depends on resend timeouts, hence on the machine's load).
    sent_by_restarted = {node for _, robot, _, node in published if robot == "a"}
    assert not sent_by_restarted & acked, sorted(sent_by_restarted & acked)[:10]
    assert sent_by_restarted >= set(range(455)) - written  # the spy saw what only the new run could send
    summary = procs.log(agents["a"]).strip().splitlines()[-1]
    assert "455 scans (" in summary and "resumed" in summary, summary
    assert int(summary.split("455 scans (")[1].split()[0]) == len(written)  # skipped: not fitted
