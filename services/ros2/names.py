"""ROS 2 names on Zenoh: topic key expressions in both layouts, type names and hashes, and the
liveliness tokens of rmw_zenoh's graph (as its docs/design.md specifies them, ROS 2 Jazzy on).

- `rmw_zenoh`: `<domain>/<fully qualified topic without its outer slashes>/<DDS type name>/<type hash>`,
  e.g. `0/scan/sensor_msgs::msg::dds_::LaserScan_/RIHS01_64c1...`; subscribers put `*` for the hash,
  so a publisher of another distribution's hash still arrives (the type name must match).
- `bridge` (zenoh-bridge-ros2dds): the topic name without its leading slash, under the bridge's
  namespace (`bot1/scan`); the key names no type. The bridge puts its namespace before every name it
  routes, absolute or relative (its ros2_name_to_key_expr): the DDS robot behind it has its topics at
  its root, so `/scan` and `scan` are both `bot1/scan`.

Liveliness tokens, one per entity, live in the hermetic `@ros2_lv` space:
`@ros2_lv/<domain>/<session id>/<node id>/<entity id>/<kind>/<enclave>/<namespace>/<node name>`
and, for a publisher (MP) or subscription (MS), `/<topic>/<DDS type>/<type hash>/<qos>`; names are
mangled ('/' -> '%'), an empty one is `%`. `ros2 node list` and `ros2 topic info` read them.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

from .config import Ros2Config, check_topic

ADMIN_SPACE = "@ros2_lv"
HASH_WILDCARD = "*"

# rmw_zenoh's QoS defaults, left out of a token's QoS chunk (rmw/types.h enum values)
RELIABLE = 1
TRANSIENT_LOCAL, VOLATILE = 1, 2
KEEP_LAST = 1
_DEFAULT_QOS = (RELIABLE, VOLATILE, KEEP_LAST, 42)


def full_name(topic: str, namespace: str = "") -> str:
    """The fully qualified name of `topic`: absolute names stay, relative ones go under `namespace`."""
    check_topic("topic", topic)
    if topic.startswith("/"):
        return "/" + topic.strip("/")
    return "/" + "/".join(p for p in (namespace.strip("/"), topic.strip("/")) if p)


def dds_type(msgtype: str) -> str:
    """`sensor_msgs/msg/LaserScan` -> `sensor_msgs::msg::dds_::LaserScan_` (the CDR type name)."""
    package, kind, name = msgtype.split("/")
    return f"{package}::{kind}::dds_::{name}_"


def ros_type(dds: str) -> str | None:
    """The inverse of dds_type; None for a chunk that is not a DDS type name of a ROS message."""
    parts = dds.split("::")
    if len(parts) != 4 or parts[1] != "msg" or parts[2] != "dds_" or not parts[3].endswith("_") or len(parts[3]) < 2:
        return None
    return f"{parts[0]}/msg/{parts[3][:-1]}"


@functools.cache
def typestore(distro: str):
    """rosbags' message definitions of a ROS 2 distribution (CDR and RIHS01 hashes without ROS)."""
    try:
        from rosbags.typesys import Stores, get_typestore
    except ModuleNotFoundError:
        raise ValueError("ROS 2 messages need rosbags: pip install 'gmmap[ros]'") from None
    return get_typestore(Stores[f"ROS2_{distro.upper()}"])


@functools.cache
def type_hash(msgtype: str, distro: str) -> str:
    """The RIHS01 hash (REP 2016) of a message type in `distro`, as rosidl generates it."""
    return typestore(distro).hash_rihs01(msgtype)


@dataclass(frozen=True)
class TopicKeys:
    """Key expressions of one fully qualified topic in one layout."""

    mapping: str  # "rmw_zenoh" or "bridge"
    domain: int
    name: str  # fully qualified, "/bot1/scan"; a bridge's topic as its DDS side names it
    prefix: str = ""  # before the name in every key: a bridge's namespace ("bot1"); '' for rmw_zenoh

    @classmethod
    def of(cls, topic: str, ros: Ros2Config) -> TopicKeys:
        """The keys of `topic` as `ros` reaches it: rmw_zenoh puts a relative name under the namespace;
        a bridge puts its namespace before every name, the DDS side's names being at its root."""
        if ros.mapping == "bridge":
            return cls(ros.mapping, ros.domain, full_name(topic), ros.namespace.strip("/"))
        return cls(ros.mapping, ros.domain, full_name(topic, ros.namespace))

    @property
    def _path(self) -> str:
        return "/".join(p for p in (self.prefix, self.name.strip("/")) if p)

    def publication(self, msgtype: str, distro: str) -> str:
        """Where a publisher of `msgtype` puts its samples."""
        if self.mapping == "bridge":
            return self._path
        return f"{self.domain}/{self._path}/{dds_type(msgtype)}/{type_hash(msgtype, distro)}"

    @property
    def subscription(self) -> str:
        """What a subscriber listens to: every type and hash on the topic in rmw_zenoh's layout."""
        if self.mapping == "bridge":
            return self._path
        return f"{self.domain}/{self._path}/*/{HASH_WILDCARD}"

    def message_type(self, key: str) -> str | None:
        """The ROS type a received key names (rmw_zenoh), None in the bridge layout or for a bad key."""
        if self.mapping == "bridge":
            return None
        chunks = key.split("/")
        return ros_type(chunks[-2]) if len(chunks) >= 3 else None


def mangle(name: str) -> str:
    """A name in a liveliness token: '/' -> '%', and '%' for an empty one."""
    return name.replace("/", "%") or "%"


def qos_chunk(reliability: int, durability: int, history: int, depth: int) -> str:
    """rmw_zenoh's compact QoS: `<rel>:<dur>:<hist>,<depth>:<deadline>:<lifespan>:<liveliness>`, each
    value left empty where it is rmw_zenoh's default (durations infinite, liveliness automatic)."""
    values = [str(v) if v != d else "" for v, d in zip((reliability, durability, history, depth), _DEFAULT_QOS)]
    return f"{values[0]}:{values[1]}:{values[2]},{values[3]}:,:,:,,"


def session_id(zid) -> str:
    """rmw_zenoh's session id chunk: the Zenoh id's 16 bytes, most significant first, each in hex
    without padding (its zid_to_str)."""
    value = int(str(zid), 16)
    return "".join(f"{b:x}" for b in value.to_bytes(16, "big"))


@dataclass(frozen=True)
class RosNode:
    """One ROS node of gmmap in rmw_zenoh's graph; it mints the tokens of its entities."""

    domain: int
    session: str  # session_id(...) of its Zenoh session
    name: str  # ROS node name: letters, digits, '_'
    namespace: str = ""  # "/bot1" or ""
    node_id: int = 0
    enclave: str = ""

    @property
    def _head(self) -> str:
        return f"{ADMIN_SPACE}/{self.domain}/{self.session}/{self.node_id}"

    @property
    def _tail(self) -> str:
        ns = "/" + self.namespace.strip("/") if self.namespace.strip("/") else ""
        return f"{mangle(self.enclave)}/{mangle(ns)}/{self.name}"

    @property
    def token(self) -> str:
        return f"{self._head}/{self.node_id}/NN/{self._tail}"

    def entity_token(self, entity_id: int, kind: str, topic: str, msgtype: str, distro: str, qos: str) -> str:
        """The token of a publisher (kind MP) or subscription (MS) of this node on `topic` (fully qualified)."""
        return (
            f"{self._head}/{entity_id}/{kind}/{self._tail}/{mangle(topic)}/{dds_type(msgtype)}/"
            f"{type_hash(msgtype, distro)}/{qos}"
        )


def node_name(prefix: str, robot: str) -> str:
    """A ROS node name for gmmap's `prefix` and a robot or fleet id (ROS names take no '-')."""
    return f"{prefix}_{robot}".replace("-", "_")
