"""The command line's flags as `gmmap` parses them: comma-separated numbers that begin with a
negative one, as a flag's separate argument."""

from __future__ import annotations

import pytest

from services import cli
from services.cli_flags import joined_number_lists, resolve_config


def parsed(*argv: str):
    return cli.build_parser().parse_args(list(argv))


def test_number_lists_may_begin_with_a_negative_number_as_separate_arguments():
    server = parsed("server", "--ros-map", "/map", "--ros-map-z", "-1,2", "--ros-map-resolution", "0.2")
    assert resolve_config(server).ros2.z_band == (-1.0, 2.0)
    replay = parsed("replay", "scans.xyz", "--bbox", "-5,-5,-1,5,5,2", "--origin", "-1,0,0.5")
    assert replay.bbox == [-5.0, -5.0, -1.0, 5.0, 5.0, 2.0] and replay.origin == [-1.0, 0.0, 0.5]
    export = parsed("export", "--from", "map.npz", "--format", "pgm", "--bbox", "-5,-5.5,5,5", "--out", "m")
    assert export.bbox == [-5.0, -5.5, 5.0, 5.0]
    assert parsed("replay", "scans.xyz", "--bbox=-5,-5,5,5").bbox == [-5.0, -5.0, 5.0, 5.0]


def test_only_a_flag_and_a_negative_number_list_are_joined():
    assert joined_number_lists(["--bbox", "-1,2", "-3,4"]) == ["--bbox=-1,2", "-3,4"]
    for argv in (
        ["--max-range", "-1"],  # one number: argparse's own
        ["-v", "-1,2"],
        ["--robot", "-a,b"],
        ["--ros-map-z=0,1", "-1,2"],
        ["log", "-1,2"],
        ["--", "--bbox", "-1,2"],
    ):
        assert joined_number_lists(argv) == argv


def test_a_list_after_a_flag_that_takes_none_is_still_refused(capsys):
    with pytest.raises(SystemExit):
        parsed("inspect", "scans.xyz", "--json", "-1,2")
    assert "--json" in capsys.readouterr().err


@pytest.mark.parametrize("duration", ["-5", "nan", "soon"])
def test_demo_refuses_a_duration_below_zero(duration, capsys):
    with pytest.raises(SystemExit) as stop:
        parsed("demo", "--duration", duration)
    assert stop.value.code == 2 and "expected seconds >= 0" in capsys.readouterr().err
