"""matplotlib is needed for --report only, and its absence stops `gmmap sim --report` before the run."""

import subprocess
import sys

import pytest

import services.sim.run
from services.cli import main
from services.config import load_config
from support.paths import ROOT


@pytest.fixture
def no_matplotlib(monkeypatch):
    monkeypatch.setitem(sys.modules, "matplotlib", None)  # `import matplotlib` raises ImportError

    def no_run(*_):
        raise AssertionError("the fleet ran")

    monkeypatch.setattr(services.sim.run, "run_fleet", no_run)


def test_report_without_matplotlib_fails_before_the_run(no_matplotlib, tmp_path):
    with pytest.raises(ValueError, match=r"install gmmap\[sim\]"):
        services.sim.run.run_sim(load_config(overrides={"sim": {"report": str(tmp_path / "report")}}))


def test_the_cli_says_what_to_install(no_matplotlib, tmp_path, capsys):
    assert main(["sim", "--report", str(tmp_path / "report")]) == 2
    assert "install gmmap[sim]" in capsys.readouterr().err
    assert not (tmp_path / "report").exists()


def test_the_simulator_imports_without_matplotlib():
    code = "import sys, services.sim.run; sys.exit('matplotlib' in sys.modules)"
    assert subprocess.run([sys.executable, "-c", code], cwd=ROOT).returncode == 0
