"""The one configuration: defaults owned by each section, files, flags, validation by field."""

from __future__ import annotations

import dataclasses
import re

import numpy as np
import pytest
import yaml

from gmm_core import FitConfig
from gmm_core.reconstruct import ReconstructionConfig
from gmm_core.scan import DENSE_3D_COMPONENT_SIZE
from services import cli
from services.cli_flags import resolve_config
from services.config import ConfigError, GmmapConfig, load_config
from services.zenoh_config import DEFAULT_ENDPOINT
from support.paths import ROOT


def resolved(*argv: str) -> GmmapConfig:
    """The configuration a `gmmap` command line resolves to."""
    return resolve_config(cli.build_parser().parse_args(list(argv)))


def test_defaults_are_the_sections_own():
    config = load_config()
    assert config.fit == FitConfig() and config.reconstruction == ReconstructionConfig()
    assert config.server.listen == (DEFAULT_ENDPOINT,) and config.agent.zenoh_connect == (DEFAULT_ENDPOINT,)
    # A server that connects to a router need not listen.
    assert dataclasses.replace(config.server, zenoh_connect=("tcp/127.0.0.1:1",)).listen == ()


def test_the_readme_example_file_runs_as_the_defaults(tmp_path):
    """Copied as it is, README's example changes nothing; its commented-out values are valid too."""
    section = (ROOT / "README.md").read_text().split("## Configuration", 1)[1]
    example = section.split("```toml\n", 1)[1].split("```", 1)[0]
    path = tmp_path / "gmmap.toml"
    path.write_text(example)
    config, defaults = load_config(path), GmmapConfig()
    for dim in (2, 3):
        assert config.fit.for_dimension(dim) == defaults.fit.for_dimension(dim)
    assert config.reconstruction == defaults.reconstruction
    assert (config.server.listen, config.server.data_dir) == (defaults.server.listen, defaults.server.data_dir)
    path.write_text(re.sub("^# ", "", example, flags=re.MULTILINE))
    assert load_config(path).fit.points_per_component is not None


def test_the_3d_component_size_rule_has_one_home():
    assert FitConfig().for_dimension(2).component_size is None
    assert FitConfig().for_dimension(3).component_size == DENSE_3D_COMPONENT_SIZE
    assert FitConfig(component_size=0.5).for_dimension(3).component_size == 0.5


@pytest.mark.parametrize("suffix", [".toml", ".yaml"])
def test_a_file_round_trips_and_flags_win_over_it(tmp_path, suffix):
    config = load_config(
        overrides={
            "fit": {"max_range": 30.0, "component_size": 0.5},
            "server": {"zenoh_listen": ["tcp/127.0.0.1:7500"], "http": ""},
            "agent": {"robot": "r1", "source": "sim:office:0:2"},
        }
    )
    path = tmp_path / f"gmmap{suffix}"
    path.write_text(config.to_toml() if suffix == ".toml" else yaml.safe_dump(config.to_dict()))
    assert load_config(path) == config
    flagged = resolved("agent", "--config", str(path), "--max-range", "12", "--points-per-component", "5")
    assert flagged.fit.max_range == 12.0 and flagged.fit.points_per_component == 5.0
    assert flagged.fit.component_size == 0.5 and flagged.agent.robot == "r1"  # from the file


def test_cli_flags_reach_their_sections():
    config = resolved(
        "server",
        "--zenoh-connect",
        "tcp/127.0.0.1:7448",
        "--samples-per-cell",
        "2",
        "--prior",
        "0.5",
        "--robot-quota-mb",
        "0",
    )
    assert config.server.listen == () and config.server.zenoh_connect == ("tcp/127.0.0.1:7448",)
    assert config.reconstruction == ReconstructionConfig(samples_per_cell=2.0, prior=0.5)
    assert config.server.robot_quota_mb == 0.0
    agent = resolved("agent", "--robot", "a", "--source", "x.log", "--resend", "0.5", "--max-components", "64")
    assert (agent.agent.resend_s, agent.fit.max_components) == (0.5, 64)


@pytest.mark.parametrize(
    "overrides, field",
    [
        ({"fit": {"max_range": -1.0}}, "fit.max_range"),
        ({"fit": {"points_per_component": float("nan")}}, "fit.points_per_component"),
        ({"fit": {"max_iter": 2.5}}, "fit.max_iter"),
        ({"fit": {"colour": "red"}}, "fit.colour"),
        ({"reconstruction": {"prior": 0.0}}, "reconstruction.prior"),
        ({"server": {"synchronous": "sometimes"}}, "server.synchronous"),
        ({"server": {"zenoh_listen": [], "zenoh_connect": []}}, "server.zenoh_listen"),
        ({"server": {"zenoh_listen": ["notanendpoint"]}}, "server.zenoh_listen"),
        ({"server": {"zenoh_connect": ["tcp/127.0.0.1:port"]}}, "server.zenoh_connect"),
        ({"agent": {"robot": "not a robot id"}}, "agent.robot"),
        ({"agent": {"encoding": "json"}}, "agent.encoding"),
        ({"sim": {"robots": 0}}, "sim.robots"),
        ({"simulator": {}}, "simulator"),
    ],
)
def test_a_bad_value_is_refused_naming_its_field(overrides, field):
    with pytest.raises(ConfigError, match=f"^{field}: "):
        load_config(overrides=overrides)


def test_bad_files_are_refused_with_the_path(tmp_path):
    broken = tmp_path / "broken.toml"
    broken.write_text("[fit\nmax_range = ")
    with pytest.raises(ConfigError, match="broken.toml is not valid TOML"):
        load_config(broken)
    with pytest.raises(ConfigError, match="must end in .toml"):
        load_config(tmp_path / "gmmap.ini")
    with pytest.raises(ConfigError, match="cannot read"):
        load_config(tmp_path / "missing.toml")


def test_the_command_line_reports_a_bad_config_and_exits_2(tmp_path, capsys):
    path = tmp_path / "bad.toml"
    path.write_text("[fit]\nmax_range = 0\n")
    assert cli.main(["agent", "--robot", "a", "--source", "x", "--config", str(path)]) == 2
    assert "fit.max_range: must be a finite number > 0" in capsys.readouterr().err
    assert cli.main(["agent", "--source", "x"]) == 2
    assert "agent.robot: required" in capsys.readouterr().err


def test_fit_config_validates_itself():
    with pytest.raises(ValueError, match="fit.component_size"):
        FitConfig(component_size=0.0)
    with pytest.raises(ValueError, match="fit.max_components"):
        FitConfig(max_components=np.int64(0))
    assert FitConfig(max_components=np.int64(8)).max_components == 8
