"""Fuzzing the Zenoh ingest of a real server process: bench/fuzz_ingest.py with 2,000 messages
(the benchmark run sends 10^5), and its report checked here field by field."""

from __future__ import annotations

import json
import subprocess
import sys

from support.paths import ROOT


def test_fuzzed_ingest_keeps_the_server_up_counts_every_rejection_and_stores_nothing_invalid():
    run = subprocess.run(
        [
            sys.executable,
            str(ROOT / "bench" / "fuzz_ingest.py"),
            "--messages",
            "2000",
            "--seed",
            "11",
            "--max-seconds",
            "60",
            "--json",
        ],
        capture_output=True,
        text=True,
        timeout=180,
        cwd=ROOT,
    )
    report = json.loads(run.stdout.strip().splitlines()[-1])
    assert report["sent"] == 2000
    assert report["alive"] and report["exit_code"] == 0, report
    # Every message accounted for, every rejection counted under the reason the decoder names.
    assert report["accepted"] + report["rejected"] == 2000, report
    assert report["rejections_match_oracle"], report
    assert report["rejected"] > 1500 and report["accepted"] > 20  # mostly garbage, some valid
    assert {"scan/message", "scan/type", "scan/dimension", "unknown/key.robot"} <= report["rejected_by_reason"].keys()
    # Nothing invalid stored; the valid part of the fuzz did land; the server logged no traceback.
    assert report["store"]["integrity"] == "ok" and report["store"]["bad_rows"] == 0, report["store"]
    assert report["store"]["scans"] > 10
    assert report["log_tracebacks"] == 0
    assert run.returncode == 0
