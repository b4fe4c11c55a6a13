"""A zenoh network transport for :class:`isac_twin.bus.bus.Bus`, wire-compatible with rmw_zenoh.

Each bus topic maps to one zenoh key expression (see
:mod:`isac_twin.transport.keyexpr`), payloads are CDR with the 4-byte
encapsulation header (:mod:`isac_twin.transport.cdr`), and every sample carries
the rmw_zenoh attachment (sequence number, source timestamp, GID).

Sessions default to **peer mode on loopback with multicast scouting off**:
endpoints are explicit (``listen=["tcp/127.0.0.1:7448"]`` on one side,
``connect=[...]`` on the other) so tests never touch another address. A
router (``rmw_zenohd`` / ``zenohd``) is just a ``connect`` endpoint; ``mode``
may be ``"client"`` to go through it only.

Graph: the transport is one ROS 2 node (``name`` in ``config.namespace``) and
declares rmw_zenoh liveliness tokens (:mod:`isac_twin.transport.liveliness`) for
the node and for every publisher and subscriber, so ``ros2 node list`` and
``ros2 topic list`` on an rmw_zenoh machine show it; it also follows every
token of its domain (:meth:`ZenohTransport.graph`), so it sees ROS 2 nodes.

QoS (:mod:`isac_twin.transport.qos`, per topic by convention or
``config.qos``): reliability goes to the zenoh publisher, KEEP_ALL + RELIABLE
blocks on congestion (otherwise samples are dropped), TRANSIENT_LOCAL topics
(``/tf_static``) use zenoh-ext's advanced publisher with a cache of ``depth``
samples and advanced subscribers that query it, as rmw_zenoh does, so a late
joiner gets the latched messages.

Faults: :meth:`ZenohTransport.partition` closes the session (the network is
gone for this process: publications are dropped, nothing arrives) and
:meth:`ZenohTransport.heal` reopens it with the same configuration and
re-declares every publisher and subscriber. Zenoh reconnects peers by itself
(``connect`` endpoints are retried), so a restarted remote process is
rejoined without help.
"""

from __future__ import annotations

import hashlib
import json
import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import zenoh
import zenoh.ext

from . import cdr
from . import liveliness as lv
from .keyexpr import Attachment, parse_topic_key, topic_key
from .qos import QosProfile, qos_for

log = logging.getLogger(__name__)


@dataclass
class ZenohConfig:
    """Where and how a process joins the zenoh network.

    Attributes:
        mode: ``"peer"`` (default), ``"client"`` (through a router) or ``"router"``.
        listen: endpoints to listen on, e.g. ``["tcp/127.0.0.1:7448"]``.
        connect: endpoints to connect to (peers or a router), retried forever.
        multicast: multicast scouting (off by default: explicit endpoints only).
        domain_id: ROS_DOMAIN_ID, the first key chunk.
        distro: ``"jazzy"`` (RIHS01 type hashes) or ``"humble"``.
        retry_period_s: s between reconnection attempts to ``connect`` endpoints.
        namespace: ROS namespace of this process's node (``/`` or ``/name``).
        qos: per-topic :class:`QosProfile` overrides of :func:`qos_for`.
    """

    mode: str = "peer"
    listen: list[str] = field(default_factory=list)
    connect: list[str] = field(default_factory=list)
    multicast: bool = False
    domain_id: int = 0
    distro: str = "jazzy"
    retry_period_s: float = 0.2
    namespace: str = "/"
    qos: dict[str, QosProfile] = field(default_factory=dict)

    def qos_of(self, topic: str) -> QosProfile:
        """The QoS profile of ``topic`` (override, else convention)."""
        return self.qos.get(topic) or qos_for(topic)

    def to_zenoh(self) -> zenoh.Config:
        if self.mode not in ("peer", "client", "router"):
            raise ValueError(f"zenoh mode: expected peer, client or router, got {self.mode!r}")
        c = zenoh.Config()
        c.insert_json5("mode", json.dumps(self.mode))
        c.insert_json5("listen/endpoints", json.dumps(list(self.listen)))
        c.insert_json5("connect/endpoints", json.dumps(list(self.connect)))
        c.insert_json5("scouting/multicast/enabled", json.dumps(bool(self.multicast)))
        # rmw_zenoh's session config timestamps samples (advanced subscribers order by them)
        c.insert_json5("timestamping/enabled", json.dumps(
            {"router": True, "peer": True, "client": True}))
        # keep trying endpoints that are not up yet (the other process may start later)
        c.insert_json5("connect/timeout_ms", "-1")
        c.insert_json5("connect/exit_on_failure", "false")
        period = max(int(self.retry_period_s * 1000), 10)
        c.insert_json5("connect/retry", json.dumps(
            {"period_init_ms": period, "period_max_ms": max(period, 1000),
             "period_increase_factor": 2}))
        return c


@dataclass
class TopicStats:
    """Per-topic counters of a :class:`ZenohTransport` (plain numbers, any thread).

    Attributes:
        sent, received, decode_errors: samples.
        last_source_ns: source timestamp (ns, the publisher's clock) of the last sample.
        last_receive_ns: local wall clock (ns) when the last sample arrived.
        lost: gaps in the publishers' sequence numbers.
    """

    sent: int = 0
    received: int = 0
    decode_errors: int = 0
    lost: int = 0
    last_source_ns: int = 0
    last_receive_ns: int = 0


class ZenohTransport:
    """:class:`isac_twin.bus.bus.Transport` over zenoh (rmw_zenoh key expressions, CDR).

    Example::

        robot = Bus(transport=ZenohTransport(ZenohConfig(listen=["tcp/127.0.0.1:7448"])))
        twin = Bus(transport=ZenohTransport(ZenohConfig(connect=["tcp/127.0.0.1:7448"])))

    Args:
        config: :class:`ZenohConfig` (default: an isolated peer, no endpoints).
        name: the ROS node name this process appears as (letters, digits, ``_``).
        on_sample: optional ``f(topic, msg, attachment | None, receive_ns)`` called for
            every received sample before delivery (clock-offset estimation, stats).
    """

    def __init__(self, config: ZenohConfig | None = None, *, name: str = "isac_twin",
                 on_sample: Callable[[str, Any, Attachment | None, int], None] | None = None):
        self.config = config or ZenohConfig()
        self.name = lv.check_node_name(name)
        lv.check_namespace(self.config.namespace)
        for t, q in self.config.qos.items():
            if not isinstance(q, QosProfile):
                raise ValueError(f"ZenohConfig.qos[{t!r}]: expected a QosProfile, got {q!r}")
        self.on_sample = on_sample
        self.stats: dict[str, TopicStats] = {}
        self._lock = threading.RLock()
        self._adverts: dict[str, str] = {}  # topic -> type name
        self._subs: dict[str, tuple[str, Callable]] = {}
        self._publishers: dict[str, Any] = {}
        self._subscribers: dict[str, Any] = {}
        self._seq: dict[str, int] = {}
        self._last_seq: dict[tuple[str, bytes], int] = {}
        self._warned_hash: set[str] = set()
        self._eids: dict[tuple[str, str], int] = {}  # (kind, topic) -> entity id
        self._tokens: dict[tuple[str, str], Any] = {}
        self._token_keys: dict[tuple[str, str], str] = {}
        self._graph: dict[str, lv.GraphEntity] = {}
        self._graph_sub = None
        self._session: zenoh.Session | None = None
        self._closed = False
        self._open()

    # ------------------------------------------------------------ session
    @property
    def session(self) -> zenoh.Session | None:
        """The open zenoh session (None while partitioned or closed)."""
        return self._session

    @property
    def connected(self) -> bool:
        return self._session is not None

    def zid(self) -> str:
        return str(self._session.zid()) if self._session is not None else ""

    def peers(self) -> list[str]:
        """Zenoh ids of the peers/routers this session is connected to."""
        if self._session is None:
            return []
        info = self._session.info
        return [str(z) for z in list(info.peers_zid()) + list(info.routers_zid())]

    def wait_for_peers(self, n: int = 1, timeout: float = 10.0) -> bool:
        """Block until at least ``n`` peers are connected; False after ``timeout`` s."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if len(self.peers()) >= n:
                return True
            time.sleep(0.02)
        return False

    def _open(self) -> None:
        self._session = zenoh.open(self.config.to_zenoh())
        log.info("zenoh session %s open (%s, listen %s, connect %s)", self._session.zid(),
                 self.config.mode, self.config.listen, self.config.connect)
        self._tokens.clear()
        self._token_keys.clear()
        with self._lock:
            self._graph.clear()
        self._declare_token("NN", "")
        self._graph_sub = self._session.liveliness().declare_subscriber(
            lv.subscription_key(self.config.domain_id), self._on_token, history=True)
        for topic, type_name in list(self._adverts.items()):
            self._declare_publisher(topic, type_name)
        for topic, (type_name, deliver) in list(self._subs.items()):
            self._declare_subscriber(topic, type_name, deliver)

    def partition(self) -> None:
        """Simulate a network partition: close the session (publications are dropped,
        nothing is received) until :meth:`heal`."""
        with self._lock:
            s, doomed = self._detach()
        del doomed  # undeclared outside the lock (see _detach)
        if s is not None:
            s.close()
            log.warning("zenoh transport %s: partitioned (session closed)", self.name)

    def _detach(self) -> tuple:
        """Take the session and every declared entity off this transport (call with
        the lock held); returns ``(session, entities)``. The caller drops the
        entities *after* releasing the lock: dropping a zenoh subscriber undeclares
        it, which waits for its running callback, and a callback may be waiting
        for this lock (it publishes, or records a graph token) -- dropping them
        under the lock deadlocked a robot's SIGTERM now and then."""
        s, self._session = self._session, None
        doomed = (self._publishers, self._subscribers, self._tokens, self._graph_sub)
        self._publishers, self._subscribers, self._tokens = {}, {}, {}
        self._graph_sub = None
        self._graph.clear()
        return s, doomed

    def heal(self) -> None:
        """Reopen the session after :meth:`partition` and re-declare every entity."""
        with self._lock:
            if self._session is None and not self._closed:
                self._open()
                log.warning("zenoh transport %s: healed (session reopened)", self.name)

    # ------------------------------------------------------------ Transport protocol
    def advertise(self, topic: str, type_name: str) -> None:
        with self._lock:
            if topic in self._adverts:
                return
            self._adverts[topic] = type_name
            self._seq.setdefault(topic, 0)
            self.stats.setdefault(topic, TopicStats())
            if self._session is not None:
                self._declare_publisher(topic, type_name)

    def publish(self, topic: str, type_name: str, msg: Any) -> None:
        """Serialize and put ``msg``; dropped (counted as sent) while partitioned."""
        if topic not in self._adverts:
            self.advertise(topic, type_name)
        payload = cdr.encode(msg)
        with self._lock:
            self._seq[topic] += 1
            att = Attachment(self._seq[topic], time.time_ns(), self._gid(topic))
            pub = self._publishers.get(topic)
            self.stats[topic].sent += 1
            if pub is None:
                return
            try:
                pub.put(payload, attachment=att.to_bytes())
            except Exception as exc:  # noqa: BLE001 - a closing session must not kill a publisher
                log.debug("zenoh put on %s failed: %s", topic, exc)

    def subscribe(self, topic: str, type_name: str, deliver: Callable[[str, Any], None]) -> None:
        with self._lock:
            if topic in self._subs:
                return
            self._subs[topic] = (type_name, deliver)
            self.stats.setdefault(topic, TopicStats())
            if self._session is not None:
                self._declare_subscriber(topic, type_name, deliver)

    def close(self) -> None:
        """Undeclare everything and close the session (idempotent)."""
        with self._lock:
            self._closed = True
            s, doomed = self._detach()
        del doomed  # undeclared outside the lock (see _detach)
        if s is not None:
            s.close()

    # ------------------------------------------------------------ ROS 2 graph
    def graph(self, *, remote_only: bool = False) -> list[lv.GraphEntity]:
        """Every entity of the ROS 2 graph in this domain (from liveliness tokens),
        ours included unless ``remote_only``."""
        me = self.zid()
        with self._lock:
            ents = list(self._graph.values())
        return [e for e in ents if not (remote_only and e.zid == me)]

    def ros_nodes(self) -> list[str]:
        """Fully qualified node names, as ``ros2 node list`` prints them."""
        return sorted({e.node_fqn for e in self.graph() if e.kind == "NN"})

    def ros_topics(self) -> dict[str, set[str]]:
        """``{topic: {type, ...}}`` of every publisher and subscription, as
        ``ros2 topic list -t`` prints them."""
        out: dict[str, set[str]] = {}
        for e in self.graph():
            if e.kind in ("MP", "MS"):
                out.setdefault(e.topic, set()).add(e.type_name)
        return out

    def token_key(self, kind: str, topic: str = "") -> str | None:
        """The liveliness key expression this transport declared for ``(kind, topic)``."""
        return self._token_keys.get((kind, topic))

    def _on_token(self, sample: zenoh.Sample) -> None:
        key = str(sample.key_expr)
        with self._lock:
            if sample.kind == zenoh.SampleKind.DELETE:
                self._graph.pop(key, None)
                return
            try:
                self._graph[key] = lv.parse_token(key)
            except ValueError as exc:
                log.warning("ignoring a malformed liveliness token: %s", exc)

    def _declare_token(self, kind: str, topic: str, type_name: str = "") -> None:
        """Declare the liveliness token of our node (``NN``) or of an endpoint."""
        c = self.config
        if kind == "NN":
            key = lv.node_token(c.domain_id, self.zid(), 0, c.namespace, self.name)
        else:
            eid = self._eids.setdefault((kind, topic), len(self._eids) + 1)
            h = self.key(topic, type_name).rsplit("/", 1)[1]
            key = lv.endpoint_token(kind, c.domain_id, self.zid(), 0, eid, c.namespace,
                                    self.name, topic, type_name, h, c.qos_of(topic))
        self._token_keys[(kind, topic)] = key
        self._tokens[(kind, topic)] = self._session.liveliness().declare_token(key)

    def __enter__(self) -> ZenohTransport:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # ------------------------------------------------------------ internals
    def key(self, topic: str, type_name: str, *, any_hash: bool = False) -> str:
        """The key expression of ``topic`` under this transport's domain and distro."""
        return topic_key(topic, type_name, domain_id=self.config.domain_id,
                         distro=self.config.distro, any_hash=any_hash)

    def _gid(self, topic: str) -> bytes:
        """The publisher's 16-byte GID: a hash of its liveliness token (rmw_zenoh hashes the
        same string with XXH3-128; any stable unique 16 bytes serve)."""
        key = self._token_keys.get(("MP", topic)) or f"{self.zid()}|{topic}"
        return hashlib.sha256(key.encode()).digest()[:16]

    def _declare_publisher(self, topic: str, type_name: str) -> None:
        q = self.config.qos_of(topic)
        key = self.key(topic, type_name)
        cc = zenoh.CongestionControl.BLOCK if (q.history == "keep_all"
                                              and q.reliability == "reliable") \
            else zenoh.CongestionControl.DROP
        rel = zenoh.Reliability.RELIABLE if q.reliability == "reliable" \
            else zenoh.Reliability.BEST_EFFORT
        if q.transient_local:
            self._publishers[topic] = zenoh.ext.declare_advanced_publisher(
                self._session, key, congestion_control=cc, reliability=rel,
                cache=zenoh.ext.CacheConfig(q.depth), publisher_detection=True,
                sample_miss_detection=zenoh.ext.MissDetectionConfig())
        else:
            self._publishers[topic] = self._session.declare_publisher(
                key, congestion_control=cc, reliability=rel)
        self._declare_token("MP", topic, type_name)

    def _declare_subscriber(self, topic: str, type_name: str, deliver) -> None:
        own_hash = self.key(topic, type_name).rsplit("/", 1)[1]

        def on_sample(sample: zenoh.Sample) -> None:
            now = time.time_ns()
            st = self.stats[topic]
            key = str(sample.key_expr)
            h = key.rsplit("/", 1)[-1]
            if h != own_hash and key not in self._warned_hash:
                self._warned_hash.add(key)
                log.warning("%s: type hash %s differs from ours (%s): another distro or "
                            "message version; decoding anyway", topic, h, own_hash)
            try:
                msg = cdr.decode(sample.payload.to_bytes(), type_name)
            except Exception as exc:  # noqa: BLE001
                st.decode_errors += 1
                log.warning("%s: undecodable %s sample (%s); dropped", topic, type_name, exc)
                return
            att = None
            if sample.attachment is not None:
                try:
                    att = Attachment.from_bytes(sample.attachment.to_bytes())
                except ValueError as exc:
                    log.debug("%s: %s", topic, exc)
            if att is not None:
                k = (topic, att.source_gid)
                prev = self._last_seq.get(k)
                if prev is not None and att.sequence_number > prev + 1:
                    st.lost += att.sequence_number - prev - 1
                self._last_seq[k] = att.sequence_number
                st.last_source_ns = att.source_timestamp_ns
            st.received += 1
            st.last_receive_ns = now
            try:
                if self.on_sample is not None:
                    self.on_sample(topic, msg, att, now)
                deliver(topic, msg)
            except Exception:  # noqa: BLE001 - never let a callback kill zenoh's thread
                log.exception("%s: delivering a remote sample failed", topic)

        key = self.key(topic, type_name, any_hash=True)
        q = self.config.qos_of(topic)
        if q.transient_local:
            self._subscribers[topic] = zenoh.ext.declare_advanced_subscriber(
                self._session, key, on_sample, allowed_origin=zenoh.Locality.REMOTE,
                history=zenoh.ext.HistoryConfig(detect_late_publishers=True,
                                                max_samples=q.depth))
        else:
            self._subscribers[topic] = self._session.declare_subscriber(
                key, on_sample, allowed_origin=zenoh.Locality.REMOTE)
        self._declare_token("MS", topic, type_name)


__all__ = ["ZenohConfig", "ZenohTransport", "TopicStats", "parse_topic_key"]
