"""``fbgforce record --out LOG.mcap``: a calibration log as a rosbag2 MCAP file.

Written with ``mcap`` and its ROS 2 support (``mcap-ros2-support``, extra ``[ros2]``): profile
``ros2``, schemas as ``.msg`` text (encoding ``ros2msg``), messages in CDR, and on every
channel the metadata rosbag2's MCAP storage writes and reads: ``offered_qos_profiles`` (which
the MCAP ``ros2`` profile requires; :data:`fbgforce.interrogator.ros2.OFFERED_QOS_PROFILES`)
and ``topic_type_hash`` (REP-2011), so ``ros2 bag info``, ``ros2 bag play`` and Foxglove open
it. One message per sample on each topic of
:data:`TOPICS`, all stamped with the sample's time (docs/ros2.md):

- ``/fbgforce/peaks`` (``fbgforce_msgs/msg/Peaks``): the interrogator's wavelengths, m;
- ``/fbgforce/stage`` (``fbgforce_msgs/msg/Stage``): the stage and load cell line joined to it;
- with a model, ``/fbgforce/contact`` and ``/fbgforce/wrench``: the estimates, as
  ``stream --publish ros2://`` publishes them.

:func:`fbgforce.recordings.dataset.load_bag` reads such a file back into the dataset contract.
"""
from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import numpy as np

from fbgforce.recordings.bag import FBGFORCE_TOPICS as TOPICS
from fbgforce.errors import InputError
from fbgforce.interrogator import ros2 as R

#: Message type of each topic.
TOPIC_TYPES = {"peaks": R.PEAKS_TYPE, "stage": R.STAGE_TYPE, "contact": R.CONTACT_TYPE,
               "wrench": R.WRENCH_TYPE}


def writer_class(path: Path) -> Any:
    """mcap-ros2-support's writer, or an error naming the extra (checked before recording)."""
    try:
        from mcap_ros2.writer import Writer  # optional extra [ros2]
    except ImportError:
        raise InputError("an .mcap log needs mcap-ros2-support: pip install 'fbgforce[ros2]'",
                         path=str(path), column="--out") from None
    return Writer


def write_log(path: str | Path, *, stamp_ns: np.ndarray, sample_seq: np.ndarray,
              wl_fm: np.ndarray, stage: dict[str, np.ndarray],
              estimates: dict[str, np.ndarray] | None = None,
              frame_id: str = R.DEFAULT_FRAME_ID) -> dict[str, int]:
    """Write one message per sample and topic; returns the message count per topic.

    Parameters
    ----------
    stamp_ns
        (n,) sample times, ns (``header.stamp``, and the log time of every message).
    sample_seq
        (n,) the interrogator's sample counters.
    wl_fm
        (n, 5) wavelengths, fm (the peaks are written in m: fm · 1e-15).
    stage
        ``contact`` (bool), ``force_N``, ``x_mm``, ``y_mm``, ``press_id`` per sample.
    estimates
        The runtime's integer estimates per sample
        (:func:`fbgforce.interrogator.publish.estimate_integers`), or None.
    """
    path = Path(path)
    n = len(stamp_ns)
    topics = list(TOPIC_TYPES) if estimates is not None else ["peaks", "stage"]
    with open(path, "wb") as fh:
        writer = writer_class(path)(fh)
        try:
            schemas = {name: writer.register_msgdef(TOPIC_TYPES[name],
                                                    R.full_msgdef(TOPIC_TYPES[name]))
                       for name in topics}
            for name in topics:
                _register_channel(writer, TOPICS[name], schemas[name])
            _write_messages(writer, schemas, stamp_ns, sample_seq, wl_fm, stage, estimates,
                            frame_id)
        finally:
            writer.finish()
    return {TOPICS[name]: n for name in topics}


def _register_channel(writer: Any, topic: str, schema: Any) -> None:
    """Register ``topic``'s channel with rosbag2's channel metadata. mcap-ros2-support's
    ``write_message`` registers a channel without metadata the first time it meets a topic;
    registered here first, on the writer's MCAP writer, the channel is the one it then uses."""
    metadata = {"offered_qos_profiles": R.OFFERED_QOS_PROFILES,
                "topic_type_hash": R.type_hash(schema.name) or ""}
    writer._channel_ids[topic] = writer._writer.register_channel(
        topic=topic, message_encoding="cdr", schema_id=schema.id, metadata=metadata)


def _write_messages(writer: Any, schemas: dict[str, Any], stamp_ns: np.ndarray,
                    sample_seq: np.ndarray, wl_fm: np.ndarray, stage: dict[str, np.ndarray],
                    estimates: dict[str, np.ndarray] | None, frame_id: str) -> None:
    n = len(stamp_ns)
    si = None if estimates is None else R.estimates_si(estimates)
    wl_m = np.asarray(wl_fm, dtype=np.float64) * 1e-15
    for i in range(n):
        t = int(stamp_ns[i])
        sec, nanosec = R.split_stamp(t)
        header = {"stamp": {"sec": sec, "nanosec": nanosec}, "frame_id": frame_id}
        seq = int(sample_seq[i]) & 0xFFFFFFFF
        writer.write_message(TOPICS["peaks"], schemas["peaks"], {
            "header": header, "sample_seq": seq, "wavelength": wl_m[i].tolist()},
            log_time=t, sequence=i)
        writer.write_message(TOPICS["stage"], schemas["stage"], {
            "header": header, "sample_seq": seq, "contact": bool(stage["contact"][i]),
            "force": float(stage["force_N"][i]), "x": float(stage["x_mm"][i]) / 1000.0,
            "y": float(stage["y_mm"][i]) / 1000.0, "press_id": int(stage["press_id"][i])},
            log_time=t, sequence=i)
        if si is not None:
            force = float(si["force"][i])
            writer.write_message(TOPICS["contact"], schemas["contact"], {
                "header": header, "seq": i & 0xFFFFFFFF, "sample_seq": seq,
                "contact": bool(si["contact"][i]),
                "contact_confidence": float(si["confidence"][i]), "force": force,
                "x": float(si["x"][i]), "y": float(si["y"][i]),
                "status": int(si["status"][i])}, log_time=t, sequence=i)
            writer.write_message(TOPICS["wrench"], schemas["wrench"], {
                "header": header, "wrench": {
                    "force": {"x": 0.0, "y": 0.0, "z": force},
                    "torque": {"x": float(si["torque_x"][i]), "y": float(si["torque_y"][i]),
                               "z": 0.0}}}, log_time=t, sequence=i)
    writer.add_metadata("fbgforce", {"command": "fbgforce record", "samples": str(n),
                                     "written_unix_ns": str(time.time_ns())})


def stamps_for(t_s: np.ndarray, first_t_us: int, host_ns: int) -> np.ndarray:
    """``header.stamp`` of recorded samples, ns: the first sample's device time
    (``first_t_us``; the host's, ``host_ns``, when the protocol has none: -1) plus the
    dataset's ``t_s``, so the log's times and the dataset's agree to the nanosecond."""
    first = int(first_t_us) * 1000 if first_t_us >= 0 else host_ns
    return first + np.round(np.asarray(t_s, dtype=np.float64) * 1e9).astype(np.int64)
