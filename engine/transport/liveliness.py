"""rmw_zenoh graph liveliness tokens: how ``ros2 node list`` / ``ros2 topic list`` see us.

Format (rmw_zenoh ``docs/design.md``, "Graph Cache"; ``liveliness_utils.cpp``)::

    node:      @ros2_lv/<domain>/<zid>/<nid>/<nid>/NN/<enclave>/<namespace>/<node>
    endpoint:  @ros2_lv/<domain>/<zid>/<nid>/<eid>/<MP|MS|SS|SC>/<enclave>/<namespace>/<node>/
               <topic>/<DDS type>/<type hash>/<qos>

* ``<zid>``: the zenoh session id as zenoh prints it; ``<nid>``/``<eid>``: ids unique
  within the session (rmw_zenoh counts them per context);
* names are *mangled*: every ``/`` becomes ``%`` (empty namespace and enclave: ``%``;
  ``/robot1/scan`` -> ``%robot1%scan``);
* ``<qos>``: :meth:`isac_twin.transport.qos.QosProfile.to_keyexpr`.

A token exists while its entity does; zenoh removes it when the session closes,
so the graph follows processes that die.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

from .cdr import dds_type_name
from .qos import QosProfile

ADMIN_SPACE = "@ros2_lv"
KINDS = {"NN": "node", "MP": "publisher", "MS": "subscription", "SS": "service",
         "SC": "client"}
_NODE_NAME = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*$")


def mangle(name: str) -> str:
    """``/`` -> ``%`` (rmw_zenoh's ``mangle_name``)."""
    return name.replace("/", "%")


def demangle(name: str) -> str:
    return name.replace("%", "/")


def check_node_name(name: str) -> str:
    """A ROS node name (letters, digits, ``_``; not starting with a digit) or ValueError."""
    if not _NODE_NAME.match(name or ""):
        raise ValueError(f"ROS node name {name!r}: expected letters, digits and '_', "
                         "not starting with a digit")
    return name


def check_namespace(ns: str) -> str:
    """A ROS namespace (``/`` or ``/a/b``) or ValueError."""
    if ns != "/" and not (ns.startswith("/") and all(_NODE_NAME.match(p)
                                                     for p in ns[1:].split("/"))):
        raise ValueError(f"ROS namespace {ns!r}: expected '/' or '/name[/name...]'")
    return ns


def node_token(domain_id: int, zid: str, nid: int, namespace: str, node: str,
               enclave: str = "/") -> str:
    """The liveliness key expression of a node."""
    return (f"{ADMIN_SPACE}/{int(domain_id)}/{zid}/{nid}/{nid}/NN/{mangle(enclave)}/"
            f"{mangle(namespace)}/{mangle(node)}")


def endpoint_token(kind: str, domain_id: int, zid: str, nid: int, eid: int, namespace: str,
                   node: str, topic: str, type_name: str, type_hash: str, qos: QosProfile,
                   enclave: str = "/") -> str:
    """The liveliness key expression of a publisher (``MP``), subscription (``MS``), ...

    Args:
        topic: fully qualified ROS name (``/robot1/scan``).
        type_name: ROS type (``sensor_msgs/msg/LaserScan``); written in its DDS form.
        type_hash: ``RIHS01_...`` (or ``TypeHashNotSupported`` on Humble).
    """
    if kind not in KINDS or kind == "NN":
        raise ValueError(f"liveliness entity kind: expected MP, MS, SS or SC, got {kind!r}")
    return (f"{ADMIN_SPACE}/{int(domain_id)}/{zid}/{nid}/{eid}/{kind}/{mangle(enclave)}/"
            f"{mangle(namespace)}/{mangle(node)}/{mangle(topic)}/{dds_type_name(type_name)}/"
            f"{type_hash}/{qos.to_keyexpr()}")


@dataclass(frozen=True)
class GraphEntity:
    """One entity of the ROS 2 graph, parsed from its liveliness token.

    Attributes:
        key: the token's key expression. kind: ``NN``/``MP``/``MS``/``SS``/``SC``.
        domain_id, zid, nid, eid: ids. namespace, node, enclave: demangled names.
        topic, type_name, type_hash, qos: endpoint fields (None for a node);
            ``type_name`` as ROS writes it (``pkg/msg/Type``).
    """

    key: str
    kind: str
    domain_id: int
    zid: str
    nid: str
    eid: str
    enclave: str
    namespace: str
    node: str
    topic: str | None = None
    type_name: str | None = None
    type_hash: str | None = None
    qos: QosProfile | None = None

    @property
    def node_fqn(self) -> str:
        """``/ns/node`` as ``ros2 node list`` prints it."""
        return ("" if self.namespace == "/" else self.namespace) + "/" + self.node


def parse_token(key: str) -> GraphEntity:
    """Parse a ``@ros2_lv/...`` key expression; ValueError naming the bad chunk."""
    parts = str(key).split("/")
    if len(parts) < 9 or parts[0] != ADMIN_SPACE:
        raise ValueError(f"not an rmw_zenoh liveliness token (expected '{ADMIN_SPACE}/' and "
                         f">= 9 chunks): {key!r}")
    if any(not p for p in parts):
        raise ValueError(f"liveliness token with an empty chunk: {key!r}")
    kind = parts[5]
    if kind not in KINDS:
        raise ValueError(f"liveliness token chunk 5 {kind!r}: expected one of {sorted(KINDS)}")
    try:
        domain = int(parts[1])
    except ValueError:
        raise ValueError(f"liveliness token chunk 1 (domain id) {parts[1]!r} is not a number") \
            from None
    base = dict(key=str(key), kind=kind, domain_id=domain, zid=parts[2], nid=parts[3],
                eid=parts[4], enclave=demangle(parts[6]), namespace=demangle(parts[7]),
                node=demangle(parts[8]))
    if kind == "NN":
        return GraphEntity(**base)
    if len(parts) < 13:
        raise ValueError(f"liveliness token of a {KINDS[kind]} needs 13 chunks "
                         f"(topic, type, hash, qos), got {len(parts)}: {key!r}")
    dds = parts[10]
    try:
        pkg, sub, _dds, name = dds.split("::")
        type_name = f"{pkg}/{sub}/{name[:-1] if name.endswith('_') else name}"
    except ValueError:
        raise ValueError(f"liveliness token chunk 10 {dds!r}: expected pkg::msg::dds_::Type_") \
            from None
    return GraphEntity(**base, topic=demangle(parts[9]), type_name=type_name,
                       type_hash=parts[11], qos=QosProfile.from_keyexpr(parts[12]))


def subscription_key(domain_id: int) -> str:
    """What a graph cache subscribes to: every token of the domain."""
    return f"{ADMIN_SPACE}/{int(domain_id)}/**"
