"""DDS participants that a ROS 2 graph sees as a node's topics (Cyclone DDS, no ROS install).

ROS 2 maps a topic ``/a/b`` of type ``pkg/msg/T`` onto the DDS topic ``rt/a/b`` of type
``pkg::msg::dds_::T_`` carrying the message's CDR bytes (:mod:`uwdock.ros.messages`). This
module makes Cyclone DDS topics of those names: the DDS type (for discovery and XTypes) is built
from the same Jazzy definition the bytes come from, and the bytes themselves are ``rosbags``'
serialisation, handed to DDS as they are (so what the node publishes is byte for byte what a
ROS 2 node would send for the same values; ``tests/test_ros_wire.py``). Jazzy endpoints
advertise their type hash in USER_DATA (``typehash=RIHS01_...;``); so do these.

Discovery is unicast on the loopback interface by default (:func:`loopback_config`: no
multicast, the peers are 127.0.0.1's participant ports), so tests and CI never send a packet off
the machine; ``loopback=False`` takes Cyclone's own configuration (``CYCLONEDDS_URI``), which is
what a vehicle uses.

Everything here is single-threaded from the caller's side: readers are polled (``take``) or
waited on (:meth:`DdsGraph.wait`), no callback runs on DDS's threads.
"""

from __future__ import annotations

import dataclasses
import functools
import time
import types
from dataclasses import dataclass
from typing import Any

import numpy as np
from cyclonedds.core import (
    InstanceState,
    Policy,
    Qos,
    ReadCondition,
    SampleState,
    ViewState,
    WaitSet,
)
from cyclonedds.domain import Domain, DomainParticipant
from cyclonedds.idl import IdlStruct
from cyclonedds.idl import types as idl
from cyclonedds.pub import DataWriter
from cyclonedds.sub import DataReader
from cyclonedds.topic import Topic

from uwdock.ros import messages as rm
from uwdock.ros.names import dds_topic_name
from uwdock.ros.qos import QosProfile

__all__ = ["DdsGraph", "Received", "dds_qos", "idl_type", "loopback_config"]


def dds_qos(profile: QosProfile, typename: str) -> Qos:
    """The Cyclone QoS of a profile, with the type hash in USER_DATA as Jazzy's rmw
    advertises it."""
    rel = (
        Policy.Reliability.BestEffort
        if profile.reliability == "best_effort"
        else Policy.Reliability.Reliable(max_blocking_time=1_000_000_000)
    )
    dur = (
        Policy.Durability.Volatile
        if profile.durability == "volatile"
        else Policy.Durability.TransientLocal
    )
    userdata = f"typehash={rm.type_hash(typename)};".encode()
    return Qos(rel, dur, Policy.History.KeepLast(profile.depth), Policy.Userdata(userdata))


def loopback_config(domain_id: int) -> str:
    """Cyclone DDS configuration that stays on 127.0.0.1: the loopback interface only, no
    multicast, unicast discovery of the participants on this machine (participant indices
    allocated automatically, up to 32 per domain), 62 kB fragments (a camera frame in tens of
    datagrams, not thousands) and 5 ms heartbeats, so a reliable writer's
    :meth:`Publisher.wait_for_acks` returns within milliseconds (lock-step simulation).

    Cyclone binds its unicast receive sockets to the wildcard address when one interface is
    configured (``ddsi_init.c``: per-interface sockets only for several); it announces and
    sends on 127.0.0.1 only, and joins no multicast group."""
    return (
        f'<CycloneDDS><Domain Id="{int(domain_id)}"><General>'
        '<Interfaces><NetworkInterface address="127.0.0.1"/></Interfaces>'
        "<AllowMulticast>false</AllowMulticast>"
        "<MaxMessageSize>65500B</MaxMessageSize><FragmentSize>62000B</FragmentSize>"
        "</General><Discovery>"
        "<ParticipantIndex>auto</ParticipantIndex>"
        "<MaxAutoParticipantIndex>32</MaxAutoParticipantIndex>"
        '<Peers><Peer address="127.0.0.1"/></Peers>'
        "</Discovery><Internal>"
        '<HeartbeatInterval min="1ms" minsched="2ms">5ms</HeartbeatInterval>'
        "</Internal></Domain></CycloneDDS>"
    )


# --------------------------------------------------------------------------- DDS types

_PRIMITIVES: dict[str, Any] = {
    "bool": bool,
    "byte": idl.uint8,
    "char": idl.uint8,
    "int8": idl.int8,
    "uint8": idl.uint8,
    "int16": idl.int16,
    "uint16": idl.uint16,
    "int32": idl.int32,
    "uint32": idl.uint32,
    "int64": idl.int64,
    "uint64": idl.uint64,
    "float32": idl.float32,
    "float64": idl.float64,
}


def _field_type(node: tuple) -> Any:
    """The ``cyclonedds.idl`` annotation of a ``rosbags`` field definition."""
    from rosbags.typesys.base import Nodetype  # with the type store (messages.typestore)

    kind, arg = node
    if kind == Nodetype.BASE:
        name, bound = arg
        if name == "string":
            return idl.bounded_str[bound] if bound else str
        if name in _PRIMITIVES:
            return _PRIMITIVES[name]
        raise TypeError(f"ROS type {name!r} has no DDS mapping here")
    if kind == Nodetype.NAME:
        return idl_type(arg)
    if kind == Nodetype.ARRAY:
        sub, length = arg
        return idl.array[_field_type(sub), length]
    if kind == Nodetype.SEQUENCE:
        sub, bound = arg
        return idl.sequence[_field_type(sub), bound] if bound else idl.sequence[_field_type(sub)]
    raise TypeError(f"unknown field kind {kind!r}")


def _wire_serialize(self, buffer=None, endianness=None, use_version_2=None) -> bytes:
    """A published sample is its CDR bytes (``_cdr``): DDS writes them as they are."""
    return self._cdr


def _wire_deserialize(cls, data, has_header: bool = True, use_version_2=None):
    """A received sample keeps its CDR bytes; :mod:`uwdock.ros.messages` reads them."""
    obj = cls.__new__(cls)
    obj._cdr = bytes(data)
    return obj


def _make_class(typename: str, wire: bool) -> type:
    """A Cyclone DDS type named as ROS 2 names it, with the fields of its Jazzy definition;
    ``wire``: a published message's type, whose samples are their CDR bytes (its fields exist
    only to describe the type to discovery; XTypes reads base classes as base types, so the
    byte pass-through is set on the class itself, not inherited)."""
    _, fields = rm.typestore().fielddefs[typename]
    annotations = {name: _field_type(node) for name, node in fields}
    if not annotations:  # an empty ROS message carries one uint8 on the wire
        annotations = {"structure_needs_at_least_one_member": idl.uint8}

    def body(ns: dict) -> None:
        ns["__annotations__"] = annotations
        ns["__module__"] = __name__
        if wire:
            ns["serialize"] = _wire_serialize
            ns["deserialize"] = classmethod(_wire_deserialize)

    cls = types.new_class(
        typename.replace("/", "_") + ("_wire" if wire else ""),
        (IdlStruct,),
        {"typename": rm.dds_type_name(typename)},
        exec_body=body,
    )
    return dataclasses.dataclass(cls)


@functools.cache
def idl_type(typename: str) -> type:
    """The DDS type of a ROS 2 message as a plain Cyclone ``IdlStruct`` (its fields, its own
    CDR serialiser): the description discovery announces, and an independent serialiser of
    the same layout (``tests/test_ros_wire.py`` checks the two agree byte for byte)."""
    return _make_class(typename, wire=False)


@functools.cache
def _wire_class(typename: str) -> type:
    """The DDS type of a published message: raw CDR passes through it."""
    return _make_class(typename, wire=True)


# --------------------------------------------------------------------------- endpoints


@dataclass
class Received:
    """One sample taken from a reader.

    Attributes:
        msg: the message, or None when its bytes did not deserialise (``error`` says why).
        cdr: the sample's CDR bytes as they came off the wire.
        source_ns: the writer's source timestamp (ns since the epoch, DDS's clock).
        error: why ``msg`` is None.
    """

    msg: Any
    cdr: bytes
    source_ns: int
    error: str = ""


class Publisher:
    """A DDS writer of one ROS 2 topic (made by :meth:`DdsGraph.publisher`)."""

    def __init__(
        self, graph: DdsGraph, topic: str, typename: str, qos: QosProfile, raw: bool = False
    ) -> None:
        self.topic, self.typename, self.qos = topic, typename, qos
        cls = _wire_class(typename)
        self._cls = cls
        self._topic = graph.topic(topic, typename, raw)
        self._writer = DataWriter(graph.participant, self._topic, qos=dds_qos(qos, typename))
        self.count = 0

    def publish(self, msg: Any) -> bytes:
        """Serialise ``msg`` and write it; returns the CDR bytes written."""
        cdr = rm.serialize(msg, self.typename)
        self.publish_cdr(cdr)
        return cdr

    def publish_cdr(self, cdr: bytes) -> None:
        """Write a sample's CDR bytes as they are."""
        sample = self._cls.__new__(self._cls)
        sample._cdr = cdr
        self._writer.write(sample)
        self.count += 1

    def wait_for_acks(self, timeout_s: float) -> bool:
        """Block until every matched reliable reader has the samples written (True), or the
        timeout passes (False)."""
        try:
            return bool(self._writer.wait_for_acks(int(timeout_s * 1e9)))
        except Exception:  # DDSException(RETCODE_TIMEOUT)
            return False

    def matched(self) -> int:
        """How many readers are matched now."""
        return len(self._writer.get_matched_subscriptions())

    @property
    def gid(self) -> bytes:
        """The writer's 16-byte GUID (ROS 2's gid of the publisher)."""
        return self._writer.guid.bytes


class Subscription:
    """A DDS reader of one ROS 2 topic (made by :meth:`DdsGraph.subscription`)."""

    def __init__(
        self, graph: DdsGraph, topic: str, typename: str, qos: QosProfile, raw: bool = False
    ) -> None:
        self.topic, self.typename, self.qos = topic, typename, qos
        self._topic = graph.topic(topic, typename, raw)
        self._reader = DataReader(graph.participant, self._topic, qos=dds_qos(qos, typename))
        self.condition = ReadCondition(
            self._reader, SampleState.NotRead | ViewState.Any | InstanceState.Any
        )

    def take(self, n: int = 64) -> list[Received]:
        """Every sample waiting (up to ``n``), oldest first; a sample whose bytes are not a
        message of the type comes back with ``msg`` None and the reason."""
        out = []
        for s in self._reader.take(N=n):
            info = getattr(s, "sample_info", None)
            if info is None or not info.valid_data:
                continue  # a writer gone or disposing its instance: no message
            cdr = getattr(s, "_cdr", b"")
            src = int(getattr(info, "source_timestamp", 0) or 0)
            try:
                out.append(Received(rm.deserialize(cdr, self.typename), cdr, src))
            except ValueError as exc:
                out.append(Received(None, cdr, src, str(exc)))
        return out

    def matched(self) -> int:
        """How many writers are matched now."""
        return len(self._reader.get_matched_publications())

    @property
    def gid(self) -> bytes:
        """The reader's 16-byte GUID (ROS 2's gid of the subscription)."""
        return self._reader.guid.bytes


#: Domains configured in this process (Cyclone takes one configuration per domain id).
_DOMAINS: dict[int, tuple[Domain, bool]] = {}


class DdsGraph:
    """One DDS participant: the node's or the simulated vehicle's handle on the ROS 2 graph.

    Args:
        domain_id: the DDS domain (ROS_DOMAIN_ID), 0 ... 232.
        loopback: keep discovery and traffic on 127.0.0.1 (:func:`loopback_config`); False:
            Cyclone's own configuration (``CYCLONEDDS_URI`` or its defaults).

    Raises:
        ValueError: a domain id outside 0 ... 232, or a domain already configured otherwise
            in this process.
    """

    def __init__(self, domain_id: int, loopback: bool = True) -> None:
        if isinstance(domain_id, bool) or not isinstance(domain_id, int):
            raise ValueError(f"domain id must be an integer, got {domain_id!r}")
        if not 0 <= domain_id <= 232:
            raise ValueError(f"domain id must be 0 ... 232, got {domain_id}")
        known = _DOMAINS.get(domain_id)
        if known is None:
            dom = Domain(domain_id, loopback_config(domain_id) if loopback else None)
            _DOMAINS[domain_id] = (dom, loopback)
        elif known[1] != loopback:
            raise ValueError(f"DDS domain {domain_id} is already configured otherwise here")
        self.domain_id = domain_id
        self.participant = DomainParticipant(domain_id)
        self._topics: dict[str, Topic] = {}
        self._waitset = WaitSet(self.participant)
        self.subscriptions: list[Subscription] = []

    def topic(self, topic: str, typename: str, raw: bool = False) -> Topic:
        """The DDS topic of a ROS 2 topic (one per name in this participant); ``raw``: the
        name as it is (ROS 2's own ``ros_discovery_info`` has no ``rt/`` prefix)."""
        name = topic if raw else dds_topic_name(topic)
        t = self._topics.get(name)
        if t is None:
            t = self._topics[name] = Topic(self.participant, name, _wire_class(typename))
        return t

    def publisher(self, topic: str, typename: str, qos: QosProfile) -> Publisher:
        """A writer of ``topic`` (``/a/b``) of type ``typename`` (``pkg/msg/T``)."""
        return Publisher(self, topic, typename, qos)

    def announce_node(self, name: str, endpoints: list, namespace: str = "/") -> Publisher:
        """Tell ROS 2's graph that a node ``namespace/name`` owns ``endpoints`` (publishers and
        subscriptions): ``rmw_dds_common/ParticipantEntitiesInfo`` on ``ros_discovery_info``
        (latched), as every ROS 2 participant publishes it, so ``ros2 node list`` and ``ros2
        node info`` show the node. Returns the writer (keep it alive)."""
        typename = "rmw_dds_common/msg/ParticipantEntitiesInfo"
        cls = rm.typestore().types
        gid = cls["rmw_dds_common/msg/Gid"]

        def g(raw: bytes):
            return gid(data=np.frombuffer(raw, dtype=np.uint8).copy())

        info = cls["rmw_dds_common/msg/NodeEntitiesInfo"](
            node_namespace=namespace,
            node_name=name,
            reader_gid_seq=[g(e.gid) for e in endpoints if isinstance(e, Subscription)],
            writer_gid_seq=[g(e.gid) for e in endpoints if isinstance(e, Publisher)],
        )
        msg = cls[typename](gid=g(self.participant.guid.bytes), node_entities_info_seq=[info])
        pub = Publisher(
            self, "ros_discovery_info", typename, QosProfile("reliable", 1, "transient_local"), True
        )
        pub.publish(msg)
        return pub

    def subscription(
        self, topic: str, typename: str, qos: QosProfile, raw: bool = False
    ) -> Subscription:
        """A reader of ``topic`` (``raw``: a DDS name without the ``rt/`` prefix);
        :meth:`wait` wakes on its samples."""
        sub = Subscription(self, topic, typename, qos, raw)
        self._waitset.attach(sub.condition)
        self.subscriptions.append(sub)
        return sub

    def wait(self, timeout_s: float) -> bool:
        """Block until a subscription has a sample not yet taken (True) or ``timeout_s``
        passes (False)."""
        if timeout_s <= 0:
            return False
        return self._waitset.wait(int(timeout_s * 1e9)) > 0

    def wait_matched(self, endpoints: list, timeout_s: float) -> bool:
        """Wait until each of ``endpoints`` (publishers / subscriptions) has a match."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if all(e.matched() > 0 for e in endpoints):
                return True
            time.sleep(0.01)
        return all(e.matched() > 0 for e in endpoints)
