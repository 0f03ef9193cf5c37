"""``stream --publish ros2:///NAMESPACE``: estimates as ROS 2 topics on the DDS wire.

Cyclone DDS (the ``cyclonedds`` package, ``pip install 'fbgforce[ros2]'``; no ROS
installation) publishes the two topics with the DDS names and types that ROS 2 maps them to
(:mod:`fbgforce.interrogator.ros2`, docs/ros2.md):

- ``NAMESPACE/wrench``: ``geometry_msgs/msg/WrenchStamped`` (DDS ``rt/NAMESPACE/wrench``,
  ``geometry_msgs::msg::dds_::WrenchStamped_``);
- ``NAMESPACE/contact``: ``fbgforce_msgs/msg/Contact`` (``fbgforce_msgs::msg::dds_::Contact_``).

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


class Ros2Publisher:
    """Publishes ``NAMESPACE/wrench`` and ``NAMESPACE/contact`` for every estimate.

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
        self.seq = 0
        self.sent = 0
        self.send_errors = 0
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

    def stats(self) -> dict[str, Any]:
        return {"url": self.url, "sent": self.sent, "send_errors": self.send_errors,
                "topics": self.topics, "link_flags": dict(self.flagged)}

    def close(self) -> None:
        # Deleting the participant deletes its writers; subscribers see the writers go.
        self.wrench_writer = self.contact_writer = None  # type: ignore[assignment]
        self.participant = None  # type: ignore[assignment]
