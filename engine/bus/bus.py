"""The topic bus: the paper's master node, in process.

Nodes publish and subscribe to named topics carrying the ROS-shaped messages
of :mod:`isac_twin.bus.msgs`. A topic's type is fixed by the first node that
advertises or subscribes to it; afterwards a mismatching advertise,
subscribe or publish raises :class:`BusError` naming the topic, the expected
type and the one given.

Delivery semantics (the twin runs single-threaded):

* ``node.subscribe(topic, type, callback)`` -- **synchronous**: ``publish``
  calls every callback of the topic, in subscription order, before it
  returns. An exception in a callback propagates to the publisher (the twin
  should fail loudly, not drop data silently).
* ``node.subscribe(topic, type)`` without a callback -- **queued**: messages
  wait in the :class:`Subscription`'s FIFO until ``take()``/``drain()``;
  unbounded by default so every message arrives; with ``queue_size`` the
  oldest are dropped (counted in ``dropped``), like a ROS ``KEEP_LAST`` QoS.

Either way, every subscriber sees every message of a topic in publish order.
``publish`` is thread-safe: a per-bus lock serialises deliveries, so
messages from several threads are still seen in one global order by all
subscribers (callbacks must not block on other publishing threads).

The bus is also the interface a network transport implements:
:class:`Transport` lists what a transport (e.g. zenoh) must provide. A bus
created with ``Bus(transport=...)`` forwards local publications to it and
injects the transport's messages into local subscribers.
"""

from __future__ import annotations

import logging
import threading
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Protocol, runtime_checkable

from ..errors import BusError
from .msgs import MESSAGE_TYPES

log = logging.getLogger(__name__)


def resolve_type(msg_type: type | str) -> type:
    """The message class for a class or a ROS type name (``"sensor_msgs/msg/Imu"``).

    Raises:
        BusError: an unknown name, or a class that is not a message type.
    """
    if isinstance(msg_type, str):
        try:
            return MESSAGE_TYPES[msg_type]
        except KeyError:
            raise BusError(f"unknown message type {msg_type!r} (known: "
                           f"{', '.join(sorted(MESSAGE_TYPES))})") from None
    if isinstance(msg_type, type) and getattr(msg_type, "ROS_TYPE", None) in MESSAGE_TYPES \
            and MESSAGE_TYPES[msg_type.ROS_TYPE] is msg_type:
        return msg_type
    raise BusError(f"{msg_type!r} is not a message type of isac_twin.bus.msgs (known: "
                   f"{', '.join(sorted(MESSAGE_TYPES))})")


@runtime_checkable
class Transport(Protocol):
    """What a network transport must provide to carry a :class:`Bus` across processes.

    Messages cross as the :mod:`isac_twin.bus.msgs` dataclasses; serialisation (CDR
    for ROS 2 / rmw_zenoh, MCAP) is the transport's business. A transport
    must deliver each remote message exactly once, in the order the remote
    published it per topic, and must not echo back what this bus published.
    """

    def advertise(self, topic: str, type_name: str) -> None:
        """Declare that this process publishes ``topic`` with ROS type ``type_name``."""

    def publish(self, topic: str, type_name: str, msg: Any) -> None:
        """Send a message published locally on ``topic``."""

    def subscribe(self, topic: str, type_name: str,
                  deliver: Callable[[str, Any], None]) -> None:
        """Receive ``topic`` from remote peers; call ``deliver(topic, msg)`` for each
        message, from any thread (the bus serialises deliveries)."""

    def close(self) -> None:
        """Release the network resources."""


class Subscription:
    """A subscriber's handle: its queue (queued mode) and counters.

    Attributes:
        topic, node: names. callback: the callback, or ``None`` in queued mode.
        received: messages delivered so far. dropped: messages lost to ``queue_size``.
    """

    def __init__(self, topic: str, node: str, callback: Callable | None,
                 queue_size: int | None):
        self.topic, self.node, self.callback = topic, node, callback
        self.queue: deque = deque(maxlen=queue_size)
        self.received = 0
        self.dropped = 0

    def _deliver(self, msg) -> None:
        self.received += 1
        if self.callback is not None:
            self.callback(msg)
        else:
            if self.queue.maxlen is not None and len(self.queue) == self.queue.maxlen:
                self.dropped += 1
            self.queue.append(msg)

    def take(self):
        """The oldest queued message, or ``None`` if the queue is empty."""
        return self.queue.popleft() if self.queue else None

    def drain(self) -> list:
        """All queued messages, oldest first, emptying the queue."""
        out = list(self.queue)
        self.queue.clear()
        return out

    def __len__(self) -> int:
        return len(self.queue)


@dataclass
class _Topic:
    name: str
    msg_type: type
    publishers: list[str] = field(default_factory=list)
    subscriptions: list[Subscription] = field(default_factory=list)
    count: int = 0


@dataclass(frozen=True)
class TopicInfo:
    """One topic in the :class:`Registry`."""

    name: str
    type_name: str
    publishers: tuple[str, ...]
    subscribers: tuple[str, ...]
    messages: int  #: published so far


@dataclass(frozen=True)
class NodeInfo:
    """One node in the :class:`Registry`."""

    name: str
    publishes: tuple[str, ...]
    subscribes: tuple[str, ...]


@dataclass(frozen=True)
class Registry:
    """A snapshot of the bus: nodes and topics with types, publishers, subscribers."""

    nodes: tuple[NodeInfo, ...]
    topics: tuple[TopicInfo, ...]

    def topic(self, name: str) -> TopicInfo:
        for t in self.topics:
            if t.name == name:
                return t
        raise KeyError(name)

    def table(self) -> str:
        """A printable table (what ``isac-twin topics`` prints)."""
        rows = [("TOPIC", "TYPE", "PUBLISHERS", "SUBSCRIBERS", "MSGS")]
        for t in self.topics:
            rows.append((t.name, t.type_name, ", ".join(t.publishers) or "-",
                         ", ".join(t.subscribers) or "-", str(t.messages)))
        w = [max(len(r[i]) for r in rows) for i in range(5)]
        lines = ["  ".join(c.ljust(w[i]) for i, c in enumerate(r)).rstrip() for r in rows]
        lines.insert(1, "  ".join("-" * x for x in w))
        lines.append("")
        lines.append(f"{len(self.nodes)} nodes: " + ", ".join(n.name for n in self.nodes))
        return "\n".join(lines)

    def __str__(self) -> str:
        return self.table()


class Node:
    """A participant on the bus. Create with :meth:`Bus.node`."""

    def __init__(self, bus: Bus, name: str):
        self.bus, self.name = bus, name
        self.advertised: dict[str, type] = {}
        self.subscriptions: list[Subscription] = []

    def advertise(self, topic: str, msg_type: type | str) -> None:
        """Declare that this node publishes ``topic`` with ``msg_type`` (class or ROS name)."""
        t = self.bus._topic(topic, resolve_type(msg_type), f"node {self.name!r} advertises")
        with self.bus._lock:
            if self.name not in t.publishers:
                t.publishers.append(self.name)
            self.advertised[topic] = t.msg_type
        if self.bus.transport is not None:
            self.bus.transport.advertise(topic, t.msg_type.ROS_TYPE)

    def publish(self, topic: str, msg) -> None:
        """Publish ``msg`` on an advertised ``topic``; returns after synchronous delivery.

        Raises:
            BusError: the topic is not advertised by this node, or ``msg`` is not
                of the topic's type.
        """
        want = self.advertised.get(topic)
        if want is None:
            raise BusError(f"node {self.name!r} publishes on {topic!r} without advertising it "
                           f"(call advertise({topic!r}, <type>) first)")
        if type(msg) is not want:
            raise BusError(f"topic {topic!r} carries {want.ROS_TYPE}, node {self.name!r} "
                           f"published a {type(msg).__module__}.{type(msg).__qualname__}")
        self.bus._dispatch(topic, msg)
        if self.bus.transport is not None:
            self.bus.transport.publish(topic, want.ROS_TYPE, msg)

    def subscribe(self, topic: str, msg_type: type | str, callback: Callable | None = None,
                  *, queue_size: int | None = None) -> Subscription:
        """Receive ``topic``: ``callback(msg)`` synchronously, or queued if no callback.

        Args:
            queue_size: bound of the queue in queued mode (default unbounded).
        """
        if queue_size is not None and queue_size < 1:
            raise BusError(f"queue_size must be >= 1 or None, got {queue_size}")
        t = self.bus._topic(topic, resolve_type(msg_type), f"node {self.name!r} subscribes")
        sub = Subscription(topic, self.name, callback, queue_size)
        first_remote = False
        with self.bus._lock:
            first_remote = not t.subscriptions
            t.subscriptions.append(sub)
            self.subscriptions.append(sub)
        if self.bus.transport is not None and first_remote:
            self.bus.transport.subscribe(topic, t.msg_type.ROS_TYPE, self.bus._deliver_remote)
        return sub

    def __repr__(self) -> str:
        return f"Node({self.name!r})"


class Bus:
    """The in-process topic bus and its registry.

    Example::

        bus = Bus()
        sim, ui = bus.node("sim"), bus.node("ui")
        sim.advertise("/robot1/odom", Odometry)
        sub = ui.subscribe("/robot1/odom", "nav_msgs/msg/Odometry")   # queued
        sim.publish("/robot1/odom", Odometry())
        msgs = sub.drain()

    Args:
        transport: optional :class:`Transport` to bridge to other processes.
    """

    def __init__(self, transport: Transport | None = None):
        self._nodes: dict[str, Node] = {}
        self._topics: dict[str, _Topic] = {}
        self._lock = threading.RLock()
        self.transport = transport

    def node(self, name: str) -> Node:
        """Create the node ``name`` (names are unique on a bus)."""
        if not isinstance(name, str) or not name:
            raise BusError(f"a node name is a non-empty string, got {name!r}")
        with self._lock:
            if name in self._nodes:
                raise BusError(f"a node named {name!r} already exists on this bus")
            n = self._nodes[name] = Node(self, name)
        return n

    def get_node(self, name: str) -> Node:
        try:
            return self._nodes[name]
        except KeyError:
            raise BusError(f"no node named {name!r} (nodes: {', '.join(self._nodes)})") from None

    def remove_node(self, name: str) -> None:
        """Remove a node with its publications and subscriptions (topics stay registered)."""
        with self._lock:
            n = self._nodes.pop(name, None)
            if n is None:
                raise BusError(f"no node named {name!r}")
            for t in self._topics.values():
                if name in t.publishers:
                    t.publishers.remove(name)
                t.subscriptions = [s for s in t.subscriptions if s.node != name]

    def has_subscribers(self, topic: str) -> bool:
        """Whether a message published on ``topic`` now would reach anyone: a
        subscription on this bus (callback or queued), or a transport (remote
        peers may subscribe). A publisher may skip building a costly message that
        nobody receives (the twin's CSI, issue #19); a subscriber that arrives
        later gets the messages published from then on, as with any topic."""
        if self.transport is not None:
            return True
        t = self._topics.get(topic)
        return t is not None and bool(t.subscriptions)

    def topic_type(self, topic: str) -> type:
        """The message class of a registered topic."""
        try:
            return self._topics[topic].msg_type
        except KeyError:
            raise BusError(f"unknown topic {topic!r}") from None

    def registry(self) -> Registry:
        """A snapshot of all nodes and topics (sorted by name)."""
        with self._lock:
            topics = tuple(
                TopicInfo(t.name, t.msg_type.ROS_TYPE, tuple(t.publishers),
                          tuple(dict.fromkeys(s.node for s in t.subscriptions)), t.count)
                for t in sorted(self._topics.values(), key=lambda t: t.name))
            nodes = tuple(
                NodeInfo(n.name, tuple(sorted(n.advertised)),
                         tuple(sorted({s.topic for s in n.subscriptions})))
                for n in sorted(self._nodes.values(), key=lambda n: n.name))
        return Registry(nodes, topics)

    # ---------------------------------------------------------------- internals
    def _topic(self, name: str, msg_type: type, who: str) -> _Topic:
        if not isinstance(name, str) or not name:
            raise BusError(f"a topic name is a non-empty string, got {name!r}")
        with self._lock:
            t = self._topics.get(name)
            if t is None:
                t = self._topics[name] = _Topic(name, msg_type)
            elif t.msg_type is not msg_type:
                raise BusError(f"topic {name!r} carries {t.msg_type.ROS_TYPE}; {who} it as "
                               f"{msg_type.ROS_TYPE}")
            return t

    def _dispatch(self, topic: str, msg) -> None:
        with self._lock:
            t = self._topics[topic]
            t.count += 1
            subs = list(t.subscriptions)
            for s in subs:
                s._deliver(msg)

    def _deliver_remote(self, topic: str, msg) -> None:
        t = self._topics.get(topic)
        if t is None or type(msg) is not t.msg_type:
            log.warning("transport delivered %r on %r, expected %s; dropped",
                        type(msg).__name__, topic, t.msg_type.ROS_TYPE if t else "no topic")
            return
        self._dispatch(topic, msg)
