"""How a run of `gmmap agent` ends, whatever its source (run.py, services/ros2/live.py): its last
line on stderr and the process exit code."""

from __future__ import annotations

import sys

from .agent import Agent


def run_outcome(agent: Agent, pending: int, success: str, hint: str = "") -> int:
    """Print how the run ended; its exit code. 1: `pending` messages were not acknowledged within
    the timeout (they stay in the outbox; `hint`, if any, ends the line); else 3: the server refused
    messages for good (table `rejected` of the outbox); else 0, and the line is `success`."""
    o, outbox = agent.options, agent.outbox
    refused = outbox.rejected()
    if pending:
        code = 1
        line = (
            f"{pending} messages not acknowledged after {o.timeout:.0f} s; they stay in {outbox.path} "
            f"and are resent by the next run{hint}"
        )
    elif refused:
        code = 3
        line = (
            f"the server refused {len(refused)} messages for good ({refused[-1][2]}: {refused[-1][3]}); they are "
            f"not stored and not resent (listed in table `rejected` of {outbox.path}); {agent.unsent} scans "
            "were not published"
        )
    else:
        code, line = 0, success
    print(f"gmmap agent {o.robot}: {line}", file=sys.stderr, flush=True)
    return code
