"""The `ros2` section validates itself, naming the field; `--source ros2` refuses file options."""

from __future__ import annotations

import pytest

from services.cli import main
from services.config import ConfigError, load_config
from services.ros2.config import Ros2Config


@pytest.mark.parametrize(
    ("values", "field"),
    [
        ({"mapping": "dds"}, "ros2.mapping"),
        ({"domain": 233}, "ros2.domain"),
        ({"domain": -1}, "ros2.domain"),
        ({"distro": "humble"}, "ros2.distro"),  # no RIHS01 hashes before Iron
        ({"odom_topic": "odom//x"}, "ros2.odom_topic"),
        ({"map_topic": "/9map"}, "ros2.map_topic"),
        ({"namespace": "/a b"}, "ros2.namespace"),
        ({"map_z": "2,1"}, "ros2.map_z"),
        ({"map_z": "nan,1"}, "ros2.map_z"),
        ({"map_period": 0}, "ros2.map_period"),
        ({"hold_scans": 0}, "ros2.hold_scans"),
    ],
)
def test_bad_values_name_their_field(values, field):
    with pytest.raises(ConfigError, match=field):
        load_config(None, {"ros2": values})


def test_defaults_and_the_z_band():
    assert Ros2Config().mapping == "rmw_zenoh" and Ros2Config().z_band is None
    assert Ros2Config(map_z="-0.5, 1.5").z_band == (-0.5, 1.5)


def test_a_ros2_agent_refuses_file_source_options(capsys):
    args = ["agent", "--robot", "r", "--source", "ros2", "--scan-topic", "/scan", "--pose-topic", "/odom"]
    assert main(args) == 2
    assert "agent.pose_topic: a ros2 source does not take it (--odom-topic)" in capsys.readouterr().err
    assert main(["agent", "--robot", "r", "--source", "ros2"]) == 2
    assert "agent.scan_topic" in capsys.readouterr().err
