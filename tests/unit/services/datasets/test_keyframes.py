"""The keyframe policy: which scans become nodes, and the replay/inspect commands that apply it."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from gmm_core.pose import Pose
from services.cli import main
from services.config import ConfigError, load_config
from services.datasets.keyframes import KeyframeConfig, KeyframeFilter, keyframes, turned


def rotation(axis, degrees: float) -> np.ndarray:
    """Rodrigues' formula: the closed form the angle of a composition is checked against."""
    k = np.asarray(axis, float) / np.linalg.norm(axis)
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    a = math.radians(degrees)
    return np.eye(3) + math.sin(a) * K + (1 - math.cos(a)) * K @ K


def test_turned_is_the_rotation_angle_in_2d_and_3d():
    rng = np.random.default_rng(0)
    for _ in range(50):
        a, b = rng.uniform(-180, 180, 2)
        assert turned(Pose.from_xytheta(0, 0, math.radians(a)), Pose.from_xytheta(1, 2, math.radians(b))) == (
            pytest.approx(abs((b - a + 180) % 360 - 180), abs=1e-6)
        )
        R0 = rotation(rng.normal(size=3), rng.uniform(0, 180))
        angle = rng.uniform(0, 179)
        moved = Pose(R0 @ rotation(rng.normal(size=3), angle), rng.normal(size=3))
        assert turned(Pose(R0, np.zeros(3)), moved) == pytest.approx(angle, abs=1e-6)


def straight_line(n: int, step: float) -> list[tuple[Pose, float]]:
    return [(Pose.from_xytheta(k * step, 0.0, 0.0), float(k)) for k in range(n)]


def kept(config: KeyframeConfig, items) -> list[int]:
    return [k for k, _ in keyframes(enumerate(items), config, lambda item: item[1])]


def test_distance_angle_and_period_each_make_a_node_and_zero_turns_each_off():
    assert kept(KeyframeConfig(distance=0.2, angle=0, period=0), straight_line(10, 0.07)) == [0, 3, 6, 9]
    assert kept(KeyframeConfig.every_scan(), straight_line(5, 0.0)) == [0, 1, 2, 3, 4]
    standing = straight_line(10, 0.0)
    assert kept(KeyframeConfig(distance=0.2, angle=10, period=0), standing) == [0]  # still: one node
    assert kept(KeyframeConfig(distance=0.2, angle=10, period=4), standing) == [0, 4, 8]
    spinning = [(Pose.from_xytheta(0, 0, math.radians(4 * k)), float(k)) for k in range(8)]
    assert kept(KeyframeConfig(distance=0.2, angle=10, period=0), spinning) == [0, 3, 6]
    assert kept(KeyframeConfig(distance=0.2, angle=0, period=0), spinning) == [0]


def test_the_distance_is_measured_from_the_last_node_not_the_last_scan():
    decide = KeyframeFilter(KeyframeConfig(distance=1.0, angle=0, period=0))
    steps = [decide.keep(Pose.from_xytheta(0.4 * k, 0, 0), float(k)) for k in range(6)]
    assert steps == [True, False, False, True, False, False]  # 0, 1.2; creeping 0.4 m steps add up


def test_the_keyframe_section_validates_itself_and_is_configurable():
    with pytest.raises(ConfigError, match="keyframe.distance"):
        load_config(overrides={"keyframe": {"distance": -1.0}})
    assert load_config(overrides={"keyframe": {"angle": 0}}).keyframe.angle == 0.0


def test_inspect_reports_scans_before_and_after_keyframing(intel_scans, data_dir, capsys):
    log = str(data_dir / "carmen" / "freiburg-079-corrected.log.gz")
    assert main(["inspect", log, "--json", "--keyframe-distance", "0.5", "--keyframe-angle", "0"]) == 0
    report = json.loads(capsys.readouterr().out)
    from services.datasets import read_scans

    scans = list(read_scans(log))
    expect = kept(KeyframeConfig(distance=0.5, angle=0, period=0), [(s.pose, s.stamp) for s in scans])
    assert report["scans_read"] == len(scans) == 4791
    assert report["scans"] == len(expect) < len(scans) / 4
    assert report["raw_bytes"] == sum(4 * (len(scans[k].hits) + len(scans[k].no_return)) for k in expect)
