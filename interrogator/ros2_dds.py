"""``stream --publish ros2:///NAMESPACE``: estimates as ROS 2 topics on the DDS wire.

Cyclone DDS (the ``cyclonedds`` package, ``pip install 'fbgforce[ros2]'``; no ROS
installation) publishes the two topics with the DDS names and types that ROS 2 maps them to
(:mod:`fbgforce.interrogator.ros2`, docs/ros2.md):

- ``NAMESPACE/wrench``: ``geometry_msgs/msg/WrenchStamped`` (DDS ``rt/NAMESPACE/wrench``,
  ``geometry_msgs::msg::dds_::WrenchStamped_``);
- ``NAMESPACE/contact``: ``fbgforce_msgs/msg/Contact`` (``fbgforce_msgs::msg::dds_::Contact_``).

With them it serves the stream's health and commands (docs/ros2.md, "Health, tare and
reset"):

- ``/diagnostics``: ``diagnostic_msgs/msg/DiagnosticArray`` once a second, one
  ``DiagnosticStatus`` named after the namespace (:meth:`Ros2Publisher.publish_status`);
- ``NAMESPACE/tare`` and ``NAMESPACE/reset``: ``std_srvs/srv/Trigger`` services laid out on the
  DDS wire as ``rmw_cyclonedds`` lays out a service: request topic
  ``rq/NAMESPACE/tareRequest`` of ``std_srvs::srv::dds_::Trigger_Request_``, reply topic
  ``rr/NAMESPACE/tareReply`` of ``std_srvs::srv::dds_::Trigger_Response_``, each sample led by
  the request header (the client's GUID as an int64 and its sequence number, int64) that the
  reply echoes, so the client takes it as the answer to its call.

QoS: reliable, keep last :data:`~fbgforce.interrogator.ros2.HISTORY_DEPTH`, transient local
(a late subscriber that asks for it gets the last second), ``max_blocking_time`` 0: a write
never waits for a subscriber, so a slow or vanished one cannot stall the estimator. Data
representation XCDR1 only (what rmw_cyclonedds's endpoints use), and USER_DATA
``typehash=RIHS01_...;`` as ROS 2 Iron and newer announce it for every endpoint.

The two published types serialise through ``rosbags``' generated CDR code (part of the same
extra) when it is installed: the same bytes as cyclonedds's generic serialiser (a test checks)
in a fifteenth of its time (about 2.7 µs instead of 38 µs per message here). ``fbgforce
stream`` runs this publisher in its publishing process
(:class:`~fbgforce.interrogator.publish.PublisherProcess`), away from the estimator.
"""
# No `from __future__ import annotations`: cyclonedds reads the field types of the IdlStruct
# dataclasses at run time and cannot resolve them from strings.
import time
from collections import OrderedDict
from dataclasses import dataclass
from typing import Any, Optional

import numpy as np

from fbgforce import contract
from fbgforce.errors import InputError
from fbgforce.interrogator import ros2 as R

try:
    from cyclonedds.core import DDSException, Policy, Qos
    from cyclonedds.domain import DomainParticipant
    from cyclonedds.idl import IdlStruct
    from cyclonedds.idl import types as T
    from cyclonedds.pub import DataWriter
    from cyclonedds.sub import DataReader
    from cyclonedds.topic import Topic
    from cyclonedds.util import duration
except ImportError as exc:  # optional extra
    raise ImportError("ros2:// needs the cyclonedds package: pip install 'fbgforce[ros2]'"
                      ) from exc


@dataclass
class Time(IdlStruct, typename=R.dds_type_name("builtin_interfaces/msg/Time")):
    sec: T.int32
    nanosec: T.uint32


@dataclass
class Header(IdlStruct, typename=R.dds_type_name("std_msgs/msg/Header")):
    stamp: Time
    frame_id: str


@dataclass
class Vector3(IdlStruct, typename=R.dds_type_name("geometry_msgs/msg/Vector3")):
    x: T.float64
    y: T.float64
    z: T.float64


@dataclass
class Wrench(IdlStruct, typename=R.dds_type_name("geometry_msgs/msg/Wrench")):
    force: Vector3
    torque: Vector3


def serialise(msg: Any, ros_type: str, generic: Any, buffer: Optional[Any],
              endianness: Optional[Any], use_version_2: Optional[bool]) -> bytes:
    """A published message's CDR bytes through rosbags' serialiser for ``ros_type`` (it reads
    the same attribute names); ``generic`` (cyclonedds's) for anything but plain XCDR1, or
    without rosbags."""
    store = R.rosbags_typestore()
    if store is None or buffer is not None or endianness is not None or use_version_2:
        return bytes(generic(buffer, endianness, use_version_2))
    return bytes(store.serialize_cdr(msg, ros_type))


@dataclass
class WrenchStamped(IdlStruct, typename=R.dds_type_name(R.WRENCH_TYPE)):
    header: Header
    wrench: Wrench

    def serialize(self, buffer: Optional[Any] = None, endianness: Optional[Any] = None,
                  use_version_2: Optional[bool] = None) -> bytes:
        return serialise(self, R.WRENCH_TYPE, super().serialize, buffer, endianness,
                         use_version_2)


@dataclass
class Contact(IdlStruct, typename=R.dds_type_name(R.CONTACT_TYPE)):
    """``fbgforce_msgs/msg/Contact``, fields in the order of ``Contact.msg`` (a test checks)."""

    header: Header
    seq: T.uint32
    sample_seq: T.uint32
    contact: bool
    contact_confidence: T.float32
    force: T.float64
    x: T.float64
    y: T.float64
    status: T.uint32

    def serialize(self, buffer: Optional[Any] = None, endianness: Optional[Any] = None,
                  use_version_2: Optional[bool] = None) -> bytes:
        return serialise(self, R.CONTACT_TYPE, super().serialize, buffer, endianness,
                         use_version_2)


@dataclass
class KeyValue(IdlStruct, typename=R.dds_type_name(R.KEY_VALUE_TYPE)):
    key: str
    value: str


@dataclass
class DiagnosticStatus(IdlStruct, typename=R.dds_type_name(R.DIAGNOSTIC_STATUS_TYPE)):
    level: T.byte
    name: str
    message: str
    hardware_id: str
    values: T.sequence[KeyValue]


@dataclass
class DiagnosticArray(IdlStruct, typename=R.dds_type_name(R.DIAGNOSTICS_TYPE)):
    header: Header
    status: T.sequence[DiagnosticStatus]


@dataclass
class TriggerRequest(IdlStruct, typename=R.dds_service_type_name(R.TRIGGER_TYPE, "Request")):
    """``std_srvs/srv/Trigger``'s request as rmw_cyclonedds puts it on the wire: the request
    header (client GUID, sequence number), then the empty request's placeholder byte."""

    guid: T.int64
    seq: T.int64
    structure_needs_at_least_one_member: T.uint8


@dataclass
class TriggerResponse(IdlStruct, typename=R.dds_service_type_name(R.TRIGGER_TYPE, "Response")):
    """``std_srvs/srv/Trigger``'s response led by the request header it answers."""

    guid: T.int64
    seq: T.int64
    success: bool
    message: str


def writer_qos(msg_type: str) -> Any:
    """The QoS of the writer of ``msg_type`` (module docstring; the same as
    :data:`~fbgforce.interrogator.ros2.OFFERED_QOS_PROFILES`), with the user data a ROS 2
    endpoint announces (:func:`~fbgforce.interrogator.ros2.endpoint_user_data`)."""
    policies = [Policy.Reliability.Reliable(duration(seconds=0)),
                Policy.History.KeepLast(R.HISTORY_DEPTH), Policy.Durability.TransientLocal,
                Policy.Liveliness.Automatic(duration(infinite=True)),
                Policy.DataRepresentation(use_cdrv0_representation=True)]
    user_data = R.endpoint_user_data(msg_type)
    if user_data:
        policies.append(Policy.Userdata(user_data))
    return Qos(*policies)


def service_qos() -> Any:
    """The QoS of ROS 2's services (``rmw_qos_profile_services_default``: reliable, volatile,
    keep last 10), XCDR1."""
    return Qos(Policy.Reliability.Reliable(duration(seconds=1)), Policy.History.KeepLast(10),
               Policy.Durability.Volatile,
               Policy.DataRepresentation(use_cdrv0_representation=True))


def diagnostics_qos() -> Any:
    """``/diagnostics``' QoS (reliable, volatile, keep last 10, as ROS 2 publishers of it
    use), with the type hash a ROS 2 endpoint announces."""
    policies = [Policy.Reliability.Reliable(duration(seconds=0)), Policy.History.KeepLast(10),
                Policy.Durability.Volatile,
                Policy.DataRepresentation(use_cdrv0_representation=True)]
    user_data = R.endpoint_user_data(R.DIAGNOSTICS_TYPE)
    if user_data:
        policies.append(Policy.Userdata(user_data))
    return Qos(*policies)


def diagnostic_values(health: dict[str, Any]) -> list[tuple[str, str]]:
    """The key-values of the ``DiagnosticStatus`` of a health snapshot, in this order (values
    as text, as ``diagnostic_msgs/KeyValue`` holds them)."""
    commands = health.get("commands", {})
    values = [("rate_hz", f"{health['rate_hz']:.1f}"), ("samples_received", health["received"]),
              ("samples_lost", health["lost"]), ("reconnects", health["reconnects"]),
              ("silent_s", f"{health['silent_s']:.3f}"),
              ("samples_lost_last_s", health["lost_last_s"]),
              ("reconnects_last_s", health["reconnects_last_s"]),
              ("estimates_last_s", health["estimates_last_s"])]
    values += [(f"{name.lower()}_last_s", count)
               for name, count in health["flags_last_s"].items()]
    values += [("tracker_offset_pm", f"{health['tracker_offset_pm']:.3f}"),
               ("tracker_bound_pm", f"{health['tracker_bound_pm']:.3f}"),
               ("model_digest", health["model_digest"]),
               ("tares", commands.get("tare", 0)), ("resets", commands.get("reset", 0)),
               ("commands_failed", commands.get("failed", 0))]
    return [(k, str(v)) for k, v in values]


class Ros2Publisher:
    """Publishes ``NAMESPACE/wrench`` and ``NAMESPACE/contact`` for every estimate, the health
    on ``/diagnostics`` and serves ``NAMESPACE/tare`` and ``NAMESPACE/reset`` (module
    docstring).

    ``ros2:///NAMESPACE[?frame_id=ID&domain=N]`` (:func:`fbgforce.interrogator.ros2.parse_url`).
    The status of each ``Contact`` holds the runtime's flags and the link's
    (:func:`fbgforce.interrogator.ros2.link_flags`). A write that fails is counted in
    ``send_errors``; the stream goes on."""

    def __init__(self, url: str) -> None:
        self.url = url
        self.namespace, self.frame_id, domain = R.parse_url(url)
        try:
            self.participant = DomainParticipant(domain)
        except DDSException as exc:
            raise InputError(f"cannot join DDS domain {domain}: {exc}", column="--publish") from None
        self.topics = {"wrench": R.topic_in(self.namespace, R.WRENCH_TOPIC),
                       "contact": R.topic_in(self.namespace, R.CONTACT_TOPIC)}
        self.wrench_writer = DataWriter(self.participant, Topic(
            self.participant, R.dds_topic_name(self.topics["wrench"]), WrenchStamped),
            qos=writer_qos(R.WRENCH_TYPE))
        self.contact_writer = DataWriter(self.participant, Topic(
            self.participant, R.dds_topic_name(self.topics["contact"]), Contact),
            qos=writer_qos(R.CONTACT_TYPE))
        self.diagnostics_writer = DataWriter(self.participant, Topic(
            self.participant, R.dds_topic_name(R.DIAGNOSTICS_TOPIC), DiagnosticArray),
            qos=diagnostics_qos())
        self.services: dict[str, str] = {}
        self._requests: dict[str, Any] = {}
        self._replies: dict[str, Any] = {}
        for name in R.SERVICES:
            service = R.topic_in(self.namespace, name)
            self.services[name] = service
            request_topic, reply_topic = R.dds_service_topics(service)
            self._requests[name] = DataReader(self.participant, Topic(
                self.participant, request_topic, TriggerRequest), qos=service_qos())
            self._replies[name] = DataWriter(self.participant, Topic(
                self.participant, reply_topic, TriggerResponse), qos=service_qos())
        # Requests taken and not answered yet: token -> (service, guid, seq).
        self._open: dict[int, tuple[str, int, int]] = {}
        self._tokens = 0
        self._seen: OrderedDict[tuple[int, int, str], None] = OrderedDict()
        self.seq = 0
        self.sent = 0
        self.send_errors = 0
        self.status_sent = 0
        self.requests = {name: 0 for name in R.SERVICES}
        self.flagged = {c.name.lower(): 0 for c in contract.LINK_STATUS}
        self._last_sample_seq: int | None = None
        R.rosbags_typestore()  # generates the serialisers now rather than at the first estimate

    def publish(self, records: np.ndarray) -> None:
        """Publish a batch of :data:`~fbgforce.interrogator.publish.ESTIMATE_DTYPE` records."""
        si = R.estimates_si(records)
        sample_seq = (records["sample_seq"] & 0xFFFFFFFF).tolist()
        link, self._last_sample_seq = R.link_flags(self._last_sample_seq, sample_seq)
        for c in contract.LINK_STATUS:
            self.flagged[c.name.lower()] += int(np.count_nonzero(link & c.value))
        # Python scalars once per batch: indexing numpy arrays per field costs more.
        rows = zip(sample_seq, R.stamps_ns(records["t_us"], time.time_ns()).tolist(),
                   si["contact"].tolist(), si["confidence"].tolist(), si["force"].tolist(),
                   si["x"].tolist(), si["y"].tolist(), si["torque_x"].tolist(),
                   si["torque_y"].tolist(), (si["status"] | link).tolist())
        for sample, stamp, touch, confidence, force, x, y, torque_x, torque_y, status in rows:
            header = Header(Time(*R.split_stamp(stamp)), self.frame_id)
            wrench = WrenchStamped(header, Wrench(Vector3(0.0, 0.0, force),
                                                  Vector3(torque_x, torque_y, 0.0)))
            contact = Contact(header, self.seq & 0xFFFFFFFF, sample, touch,
                              confidence, force, x, y, status)
            self.seq += 1
            try:
                self.wrench_writer.write(wrench)
                self.contact_writer.write(contact)
                self.sent += 1
            except DDSException:
                self.send_errors += 1

    def publish_status(self, health: dict[str, Any]) -> None:
        """Publish the health snapshot on ``/diagnostics``: one ``DiagnosticStatus`` named
        after the namespace, its level (0 OK, 1 WARN, 2 ERROR), message and key-values
        (:func:`diagnostic_values`)."""
        header = Header(Time(*R.split_stamp(time.time_ns())), "")
        status = DiagnosticStatus(
            level=int(health["level"]), name=self.namespace,
            message=health["message"], hardware_id=f"fbgforce {self.frame_id}",
            values=[KeyValue(k, v) for k, v in diagnostic_values(health)])
        try:
            self.diagnostics_writer.write(DiagnosticArray(header, [status]))
            self.status_sent += 1
        except DDSException:
            self.send_errors += 1

    def poll_commands(self) -> list[tuple[str, int]]:
        """The requests that arrived on the services since the last call, as (command,
        token); a request taken twice (same client GUID, sequence number and service) once."""
        out = []
        for name, reader in self._requests.items():
            for req in reader.take(N=64):
                if not isinstance(req, TriggerRequest):
                    continue  # an InvalidSample: a client went away
                key = (req.guid, req.seq, name)
                if key in self._seen:
                    continue
                self._seen[key] = None
                while len(self._seen) > 1024:
                    self._seen.popitem(last=False)
                self._tokens += 1
                self._open[self._tokens] = (name, req.guid, req.seq)
                self.requests[name] += 1
                out.append((name, self._tokens))
        return out

    def answer(self, token: int, answer: dict[str, Any]) -> None:
        """Reply to the request ``token`` with the command's answer: ``success`` and the
        message (what was done, with the baseline's change in pm, or why not)."""
        opened = self._open.pop(token, None)
        if opened is None:
            return
        name, guid, seq = opened
        try:
            self._replies[name].write(TriggerResponse(guid, seq, bool(answer["ok"]),
                                                      answer["message"]))
        except DDSException:
            self.send_errors += 1

    def stats(self) -> dict[str, Any]:
        return {"url": self.url, "sent": self.sent, "send_errors": self.send_errors,
                "topics": self.topics, "link_flags": dict(self.flagged),
                "status_sent": self.status_sent, "services": dict(self.services),
                "requests": dict(self.requests)}

    def close(self) -> None:
        # Deleting the participant deletes its writers; subscribers see the writers go.
        self.wrench_writer = self.contact_writer = None  # type: ignore[assignment]
        self.diagnostics_writer = None  # type: ignore[assignment]
        self._requests, self._replies = {}, {}
        self.participant = None  # type: ignore[assignment]
