"""What a request may read: the robots of a token limited to some, and the whole fleet otherwise."""

from __future__ import annotations

import pytest

from services.api.auth import EVERYONE, Access
from services.api.params import ApiError

DOCK = Access("dock", frozenset({"a", "c"}))


def test_a_fleet_token_reads_what_the_request_names():
    assert EVERYONE.select(None) is None
    assert EVERYONE.select(("b",)) == ("b",)
    assert Access("ops").select(()) == ()  # an empty selection selects no robot
    EVERYONE.require_fleet("/metrics")


def test_a_limited_token_reads_its_robots_and_only_those():
    assert DOCK.select(None) == ("a", "c")  # sorted: one tile cache key per set of robots
    assert DOCK.select(("c",)) == ("c",)
    assert DOCK.select(()) == ()
    with pytest.raises(ApiError) as error:
        DOCK.select(("a", "b", "z"))
    assert (error.value.status, error.value.field) == (403, "robots")
    assert "robot b, z" in error.value.message
    with pytest.raises(ApiError) as error:
        DOCK.select(("b",), "robot")
    assert (error.value.status, error.value.field) == (403, "robot")
    with pytest.raises(ApiError, match="whole fleet") as error:
        DOCK.require_fleet("/metrics")
    assert error.value.status == 403
