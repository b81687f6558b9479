"""How a run of `gmmap agent` ends (services/agent/outcome.py), file source or ROS 2: the exit code
and the last line, whose words scripts read."""

from __future__ import annotations

from services.agent.outcome import run_outcome

DETAIL = "this map is 2D, the message is 3D"


def last_line(capsys) -> str:
    [line] = capsys.readouterr().err.splitlines()
    return line


def test_all_acknowledged_is_0_with_the_callers_line(offline_agent, capsys):
    assert run_outcome(offline_agent, 0, "all acknowledged by store s") == 0
    assert last_line(capsys) == "gmmap agent r: all acknowledged by store s"


def test_messages_not_acknowledged_are_1_and_stay_in_the_outbox_also_when_some_were_refused(offline_agent, capsys):
    outbox = offline_agent.outbox
    outbox.reject("scan", (0,), "dimension", DETAIL)
    assert run_outcome(offline_agent, 2, "unused", " (is a server reachable?)") == 1
    assert last_line(capsys) == (
        f"gmmap agent r: 2 messages not acknowledged after 120 s; they stay in {outbox.path} and are resent "
        "by the next run (is a server reachable?)"
    )


def test_messages_refused_for_good_are_3_with_the_last_reason_and_the_table(offline_agent, capsys):
    outbox = offline_agent.outbox
    outbox.reject("scan", (0, 1), "quota", "over")
    outbox.reject("scan", (2,), "dimension", DETAIL)
    offline_agent.unsent = 5
    assert run_outcome(offline_agent, 0, "unused", " (is a server reachable?)") == 3
    assert last_line(capsys) == (
        f"gmmap agent r: the server refused 3 messages for good (dimension: {DETAIL}); they are not stored and "
        f"not resent (listed in table `rejected` of {outbox.path}); 5 scans were not published"
    )
