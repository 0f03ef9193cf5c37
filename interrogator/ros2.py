"""ROS 2 conventions shared by the DDS publisher and the rosbag2 (MCAP) log: names, message
definitions, the pad frame and the estimates in SI units (docs/ros2.md).

Nothing here needs a ROS installation or a DDS library: :mod:`fbgforce.interrogator.ros2_dds`
puts these messages on the DDS wire (``stream --publish ros2:///NAMESPACE``) and
:mod:`fbgforce.interrogator.mcaplog` writes them to MCAP (``record --out LOG.mcap``).

Pad frame (``header.frame_id``, default :data:`DEFAULT_FRAME_ID`): origin at the pad's
top-left corner, x to the right, y down, z = x × y, into the pad; metres. The estimated force
presses into the pad, so ``wrench.force = (0, 0, F)`` with F ≥ 0, and its torque about the
origin is ``r × F = (y·F, −x·F, 0)`` for a contact at ``r = (x, y, 0)``: a ROS 2 tool recovers
the location as ``x = −torque.y / force.z``, ``y = torque.x / force.z``.
"""
from __future__ import annotations

import os
import re
import time
from functools import lru_cache
from pathlib import Path
from typing import Any, Sequence
from urllib.parse import parse_qs, urlsplit

import numpy as np

from fbgforce import contract
from fbgforce.errors import InputError
from fbgforce.units import estimate_shown

#: The message package shipped with fbgforce (a ROS 2 package: package.xml, CMakeLists.txt).
MSG_PACKAGE = "fbgforce_msgs"
MSG_PACKAGE_DIR = Path(__file__).resolve().parent / MSG_PACKAGE
DEFAULT_FRAME_ID = "fbgforce_pad"
#: Topics of ``stream --publish ros2:///NAMESPACE``, below the namespace.
WRENCH_TOPIC = "wrench"
CONTACT_TOPIC = "contact"
#: The health, once a second (``diagnostic_msgs``' conventional topic, outside the namespace).
DIAGNOSTICS_TOPIC = "/diagnostics"
DIAGNOSTICS_TYPE = "diagnostic_msgs/msg/DiagnosticArray"
DIAGNOSTIC_STATUS_TYPE = "diagnostic_msgs/msg/DiagnosticStatus"
KEY_VALUE_TYPE = "diagnostic_msgs/msg/KeyValue"
#: Services of ``stream --publish ros2:///NAMESPACE``, below the namespace.
SERVICES = ("tare", "reset")
TRIGGER_TYPE = "std_srvs/srv/Trigger"
WRENCH_TYPE = "geometry_msgs/msg/WrenchStamped"
CONTACT_TYPE = f"{MSG_PACKAGE}/msg/Contact"
PEAKS_TYPE = f"{MSG_PACKAGE}/msg/Peaks"
STAGE_TYPE = f"{MSG_PACKAGE}/msg/Stage"
#: Messages the publisher keeps for reliable repair and late transient-local subscribers:
#: one second at 1 kHz. The writer never blocks: the oldest message makes room.
HISTORY_DEPTH = 1000
#: The QoS every topic is offered with (reliable, keep last :data:`HISTORY_DEPTH`, transient
#: local, automatic liveliness, no deadline, lifespan or lease: 0 s = the default, infinite)
#: in rosbag2's ``offered_qos_profiles`` form: a YAML list, policies as rmw's enum integers
#: (metadata version 8), which every rosbag2 from Humble on reads.
OFFERED_QOS_PROFILES = f"""- history: 1
  depth: {HISTORY_DEPTH}
  reliability: 1
  durability: 1
  deadline:
    sec: 0
    nsec: 0
  lifespan:
    sec: 0
    nsec: 0
  liveliness: 1
  liveliness_lease_duration:
    sec: 0
    nsec: 0
  avoid_ros_namespace_conventions: false"""

#: Definitions of the standard messages used, as ROS 2 ships them (without comments).
STANDARD_MSGS = {
    "builtin_interfaces/msg/Time": "int32 sec\nuint32 nanosec\n",
    "std_msgs/msg/Header": "builtin_interfaces/Time stamp\nstring frame_id\n",
    "geometry_msgs/msg/Vector3": "float64 x\nfloat64 y\nfloat64 z\n",
    "geometry_msgs/msg/Wrench": "Vector3 force\nVector3 torque\n",
    "geometry_msgs/msg/WrenchStamped": "std_msgs/Header header\nWrench wrench\n",
}
_NAME = re.compile(r"[A-Za-z_][A-Za-z0-9_]*\Z")
_FIELD_TYPE = re.compile(r"^\s*([A-Za-z_][A-Za-z0-9_/]*)(\[\d*\])?\s+[A-Za-z_]")
_PRIMITIVES = {"bool", "byte", "char", "int8", "uint8", "int16", "uint16", "int32", "uint32",
               "int64", "uint64", "float32", "float64", "string", "wstring"}


def dds_topic_name(topic: str) -> str:
    """The DDS topic of a ROS 2 topic: ``/a/b`` -> ``rt/a/b``."""
    return "rt/" + topic.lstrip("/")


def dds_type_name(msg_type: str) -> str:
    """The DDS type of a ROS 2 message type: ``pkg/msg/Name`` -> ``pkg::msg::dds_::Name_``."""
    pkg, kind, name = msg_type.split("/")
    return f"{pkg}::{kind}::dds_::{name}_"


def dds_service_type_name(srv_type: str, part: str) -> str:
    """The DDS type of a service's ``Request`` or ``Response``: ``pkg/srv/Name`` ->
    ``pkg::srv::dds_::Name_Request_``."""
    pkg, kind, name = srv_type.split("/")
    return f"{pkg}::{kind}::dds_::{name}_{part}_"


def dds_service_topics(service: str) -> tuple[str, str]:
    """The DDS request and reply topics of a ROS 2 service, as rmw_cyclonedds names them:
    ``/a/tare`` -> (``rq/a/tareRequest``, ``rr/a/tareReply``)."""
    name = service.lstrip("/")
    return f"rq/{name}Request", f"rr/{name}Reply"


def msg_text(msg_type: str) -> str:
    """The ``.msg`` text of a message of the project's package or a standard one."""
    if msg_type in STANDARD_MSGS:
        return STANDARD_MSGS[msg_type]
    pkg, _, name = msg_type.split("/")
    if pkg != MSG_PACKAGE:
        raise KeyError(msg_type)
    return (MSG_PACKAGE_DIR / "msg" / f"{name}.msg").read_text(encoding="utf-8")


def _dependencies(msg_type: str) -> list[str]:
    """Message types a definition refers to, as ``pkg/msg/Name``, in order of appearance."""
    pkg = msg_type.split("/")[0]
    out = []
    for line in msg_text(msg_type).splitlines():
        m = _FIELD_TYPE.match(line.split("#", 1)[0])
        if m is None or "=" in line.split("#", 1)[0] or m.group(1) in _PRIMITIVES:
            continue
        ref = m.group(1)
        ref_pkg, ref_name = ref.split("/") if "/" in ref else (pkg, ref)
        out.append(f"{ref_pkg}/msg/{ref_name}")
    return out


@lru_cache(maxsize=None)
def rosbags_typestore() -> Any | None:
    """rosbags' type store (the newest ROS 2 release's standard messages) with the project's
    messages registered, or None without rosbags (part of the ``[ros2]`` extra)."""
    try:
        from rosbags.typesys import Stores, get_types_from_msg, get_typestore
    except ImportError:
        return None
    store = get_typestore(Stores.LATEST)
    for msg_type in (CONTACT_TYPE, PEAKS_TYPE, STAGE_TYPE):
        store.register(get_types_from_msg(msg_text(msg_type), msg_type))
    return store


def type_hash(msg_type: str) -> str | None:
    """The REP-2011 type hash (``RIHS01_`` + 64 hex digits) that ROS 2 from Iron on computes
    for a message type and announces in discovery and in rosbag2 logs; None without rosbags."""
    store = rosbags_typestore()
    return None if store is None else str(store.hash_rihs01(msg_type))


def endpoint_user_data(msg_type: str) -> bytes:
    """The USER_DATA QoS a ROS 2 (Iron or newer) endpoint of ``msg_type`` announces:
    ``typehash=RIHS01_...;`` (empty without rosbags; Humble sends none either)."""
    digest = type_hash(msg_type)
    return b"" if digest is None else f"typehash={digest};".encode("ascii")


def full_msgdef(msg_type: str) -> str:
    """The definition with every nested one, in rosbag2's concatenated form (what an MCAP
    schema of encoding ``ros2msg`` holds)."""
    order: list[str] = []
    todo = _dependencies(msg_type)
    while todo:
        dep = todo.pop(0)
        if dep not in order:
            order.append(dep)
            todo.extend(_dependencies(dep))
    parts = [msg_text(msg_type).rstrip("\n")]
    for dep in order:
        pkg, _, name = dep.split("/")
        parts.append("=" * 80 + f"\nMSG: {pkg}/{name}\n" + msg_text(dep).rstrip("\n"))
    return "\n".join(parts) + "\n"


def parse_url(url: str) -> tuple[str, str, int]:
    """``ros2:///NAMESPACE[?frame_id=ID&domain=N]`` -> (namespace, frame_id, domain).

    The namespace is ``/`` followed by ROS 2 name tokens (``/robot/left_tip``; empty: the
    root). Without ``domain=`` the domain is :func:`default_domain`, as ROS 2 nodes choose it.
    """
    parts = urlsplit(url)
    if parts.scheme != "ros2" or parts.netloc:
        raise InputError(f"expected ros2:///NAMESPACE[?frame_id=ID&domain=N], not {url!r}",
                         column="--publish")
    tokens = [t for t in parts.path.split("/") if t]
    if parts.path.rstrip("/").count("//") or not all(_NAME.match(t) for t in tokens):
        raise InputError(f"{parts.path!r} is not a ROS 2 namespace (tokens of letters, digits "
                         f"and '_', not starting with a digit)", column="--publish")
    query = parse_qs(parts.query, keep_blank_values=True)
    unknown = sorted(set(query) - {"frame_id", "domain"})
    if unknown:
        raise InputError(f"unknown ros2:// option(s) {', '.join(unknown)} (frame_id, domain)",
                         column="--publish")
    frame_id = query.get("frame_id", [DEFAULT_FRAME_ID])[-1]
    domain = _domain_id(query["domain"][-1], "domain") if "domain" in query else default_domain()
    return "/" + "/".join(tokens), frame_id, domain


def default_domain() -> int:
    """The DDS domain a ROS 2 node would join: ``ROS_DOMAIN_ID``, else 0."""
    text = os.environ.get("ROS_DOMAIN_ID", "").strip()
    return _domain_id(text, "ROS_DOMAIN_ID") if text else 0


def _domain_id(text: str, name: str) -> int:
    if not text.isdigit() or int(text) > 232:
        raise InputError(f"{name} must be an integer 0..232, not {text!r}", column="--publish")
    return int(text)


def topic_in(namespace: str, name: str) -> str:
    """``NAMESPACE/name`` (``/name`` in the root namespace)."""
    return namespace.rstrip("/") + "/" + name


def link_flags(previous_seq: int | None, seqs: Sequence[int]) -> tuple[np.ndarray, int | None]:
    """Link status bits (:data:`fbgforce.contract.LINK_STATUS`) of consecutive samples from
    their 32-bit sample counters, and the last counter (pass it back for the next batch).

    A step of 1 sets nothing, a larger forward step ``SAMPLES_LOST``, a backward step
    (half the counter range or more, modulo 2**32) ``DEVICE_RESTART``."""
    lost = contract.LINK_STATUS[0].value
    restart = contract.LINK_STATUS[1].value
    flags = np.zeros(len(seqs), dtype=np.uint32)
    prev = previous_seq
    for i, s in enumerate(seqs):
        s &= 0xFFFFFFFF
        if prev is not None:
            step = (s - prev) & 0xFFFFFFFF
            if step >= 1 << 31:
                flags[i] = restart
            elif step > 1:
                flags[i] = lost
        prev = s
    return flags, prev


def stamps_ns(t_us: np.ndarray, now_ns: int | None = None) -> np.ndarray:
    """``header.stamp`` of each sample, ns, from its device time ``t_us`` (µs), or the host's
    time now where the protocol carries none (FiSpec: -1)."""
    t_us = np.asarray(t_us, dtype=np.int64)
    host = time.time_ns() if now_ns is None else now_ns
    return np.where(t_us >= 0, t_us * 1000, host)


def split_stamp(ns: int) -> tuple[int, int]:
    """``builtin_interfaces/Time`` (sec, nanosec) of a time in ns."""
    sec, nanosec = divmod(int(ns), 1_000_000_000)
    return sec, nanosec


def estimates_si(ints: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """The published estimate in SI units from the runtime's integers
    (:func:`fbgforce.interrogator.publish.estimate_integers`): ``contact`` (bool),
    ``confidence`` (0..1), ``force`` (N), ``x``, ``y`` (m, NaN where no estimate is shown:
    neither contact nor RELEASING, :func:`fbgforce.units.estimate_shown`) and the torque about
    the pad origin ``torque_x``, ``torque_y`` (N·m, 0 there)."""
    contact = np.asarray(ints["contact"], dtype=bool)
    shown = estimate_shown(contact, ints["status"])
    force = np.asarray(ints["force_mN"], dtype=np.float64) / 1000.0
    x0 = np.where(shown, np.asarray(ints["x_um"], dtype=np.float64) / 1e6, 0.0)
    y0 = np.where(shown, np.asarray(ints["y_um"], dtype=np.float64) / 1e6, 0.0)
    return {"contact": contact,
            "confidence": np.asarray(ints["contact_conf_q15"], dtype=np.float64) / 32768.0,
            "force": force, "x": np.where(shown, x0, np.nan), "y": np.where(shown, y0, np.nan),
            "torque_x": y0 * force, "torque_y": -x0 * force,
            "status": np.asarray(ints["status"], dtype=np.uint32)}
