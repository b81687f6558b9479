"""The house rule (docs/ARCHITECTURE.md, "Conventions"): a module does one job, in no more than
500 lines."""

from __future__ import annotations

from support.paths import ROOT

MAX_LINES = 500
FOLDERS = ("gmm_core", "protocol", "services", "tests", "bench", "examples")


def test_no_module_is_over_500_lines():
    lengths = {
        path.relative_to(ROOT).as_posix(): len(path.read_text(encoding="utf-8").splitlines())
        for folder in FOLDERS
        for path in sorted((ROOT / folder).rglob("*.py"))
    }
    offenders = [f"{path} ({lines})" for path, lines in lengths.items() if lines > MAX_LINES]
    assert not offenders, f"over {MAX_LINES} lines: " + ", ".join(offenders)
