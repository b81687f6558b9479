"""Keys and liveliness tokens against the examples of rmw_zenoh's docs/design.md, written out here."""

from __future__ import annotations

import pytest
import zenoh

from services.ros2.config import Ros2Config
from services.ros2.names import (
    KEEP_LAST,
    RELIABLE,
    TRANSIENT_LOCAL,
    VOLATILE,
    RosNode,
    TopicKeys,
    dds_type,
    full_name,
    qos_chunk,
    ros_type,
    session_id,
)

STRING_HASH = "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18"  # design.md's
ADD_TWO_INTS = "example_interfaces::srv::dds_::AddTwoInts_"


def test_topic_keys_are_those_of_the_design_notes():
    assert TopicKeys("rmw_zenoh", 0, "/chatter").publication("std_msgs/msg/String", "jazzy") == (
        f"0/chatter/std_msgs::msg::dds_::String_/{STRING_HASH}"
    )
    assert TopicKeys("rmw_zenoh", 0, full_name("chatter", "/robot1")).publication("std_msgs/msg/String", "jazzy") == (
        f"0/robot1/chatter/std_msgs::msg::dds_::String_/{STRING_HASH}"
    )
    assert TopicKeys("bridge", 0, full_name("scan", "/bot1")).publication("sensor_msgs/msg/LaserScan", "jazzy") == (
        "bot1/scan"
    )


@pytest.mark.parametrize("mapping", ["rmw_zenoh", "bridge"])
def test_a_subscription_matches_publications_of_any_hash_and_no_other_topic(mapping):
    keys = TopicKeys(mapping, 3, "/bot1/scan")
    published = keys.publication("sensor_msgs/msg/LaserScan", "jazzy")
    assert zenoh.KeyExpr(keys.subscription).intersects(zenoh.KeyExpr(published))
    other = TopicKeys(mapping, 3, "/bot1/scan/raw").publication("sensor_msgs/msg/LaserScan", "jazzy")
    assert not zenoh.KeyExpr(keys.subscription).intersects(zenoh.KeyExpr(other))
    if mapping == "rmw_zenoh":
        kilted = f"3/bot1/scan/sensor_msgs::msg::dds_::LaserScan_/{'RIHS01_' + '0' * 64}"
        assert zenoh.KeyExpr(keys.subscription).intersects(zenoh.KeyExpr(kilted))
        assert not zenoh.KeyExpr(keys.subscription).intersects(zenoh.KeyExpr(published.replace("3/", "0/", 1)))
        assert keys.message_type(published) == "sensor_msgs/msg/LaserScan"


def test_a_bridges_namespace_goes_before_absolute_names_too_and_rmw_zenohs_does_not():
    bridge = Ros2Config(mapping="bridge", namespace="/bot1")
    for topic in ("/scan", "scan"):  # zenoh-bridge-ros2dds' ros2_name_to_key_expr: namespace / name
        keys = TopicKeys.of(topic, bridge)
        assert keys.name == "/scan" and keys.publication("sensor_msgs/msg/LaserScan", "jazzy") == "bot1/scan"
        assert keys.subscription == "bot1/scan"
    assert TopicKeys.of("/slam/path", Ros2Config(mapping="bridge")).subscription == "slam/path"
    rmw_zenoh = Ros2Config(domain=3, namespace="/bot1")
    assert TopicKeys.of("/scan", rmw_zenoh).subscription == "3/scan/*/*"
    assert TopicKeys.of("scan", rmw_zenoh).subscription == "3/bot1/scan/*/*"
    assert TopicKeys.of("scan", rmw_zenoh).name == "/bot1/scan"


def test_type_names():
    assert dds_type("nav_msgs/msg/OccupancyGrid") == "nav_msgs::msg::dds_::OccupancyGrid_"
    assert ros_type("nav_msgs::msg::dds_::OccupancyGrid_") == "nav_msgs/msg/OccupancyGrid"
    for bad in ("nav_msgs::msg::OccupancyGrid_", ADD_TWO_INTS, "x", "a::msg::dds_::_"):
        assert ros_type(bad) is None


def test_full_names():
    assert full_name("/scan", "/bot1") == "/scan"
    assert full_name("scan", "/bot1/") == "/bot1/scan"
    assert full_name("scan") == "/scan"
    with pytest.raises(ValueError, match="topic"):
        full_name("scan//x")


def test_liveliness_tokens_are_those_of_the_design_notes():
    listener = RosNode(2, "aac3178e146ba6f1fc6e6a4085e77f21", "listener")
    assert listener.token == "@ros2_lv/2/aac3178e146ba6f1fc6e6a4085e77f21/0/0/NN/%/%/listener"
    qos = qos_chunk(RELIABLE, VOLATILE, KEEP_LAST, 10)
    assert qos == "::,10:,:,:,,"
    assert listener.entity_token(10, "MS", "/chatter", "std_msgs/msg/String", "jazzy", qos) == (
        "@ros2_lv/2/aac3178e146ba6f1fc6e6a4085e77f21/0/10/MS/%/%/listener/%chatter/std_msgs::msg::dds_::String_/"
        f"{STRING_HASH}/::,10:,:,:,,"
    )
    assert RosNode(0, "1", "n", "/bot1").token == "@ros2_lv/0/1/0/0/NN/%/%bot1/n"
    assert qos_chunk(RELIABLE, TRANSIENT_LOCAL, KEEP_LAST, 1) == ":1:,1:,:,:,,"


class _Zid:
    def __init__(self, text: str):
        self.text = text

    def __str__(self) -> str:
        return self.text


def test_session_id_prints_each_byte_most_significant_first_unpadded():
    # zid_to_str: the 16 bytes of the little-endian u128 from the last, "%x" each
    assert session_id(_Zid("a1b2")) == "0" * 14 + "a1b2"
    assert session_id(_Zid("10203")) == "0" * 13 + "1" + "2" + "3"
    assert session_id(_Zid("f" * 32)) == "ff" * 16
