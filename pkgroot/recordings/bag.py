"""rosbag2 logs (MCAP or SQLite 3) read into the columns of the dataset contract
(docs/ros2.md); :func:`fbgforce.recordings.dataset.load_bag` makes a dataset of them.

Read with ``rosbags`` (extra ``[ros2]``), which decodes any ROS 2 message from the definitions
stored in the bag. Which message field feeds which dataset column is a *field map*: column ->
``"/TOPIC:FIELD"``, where FIELD is a dotted path with optional indices (``wrench.force.z``,
``data[3]``) and may end in ``*SCALE`` (``x*1000``: m to mm). :data:`FBGFORCE_FIELDS` maps
the topics ``fbgforce record --out LOG.mcap`` writes; a bag recorded by another driver is
read by giving its own map, e.g.::

    fields = {"wl1_nm": "/hyperion/peaks:data[0]", ..., "wlT_nm": "/hyperion/peaks:data[4]",
              "force_N": "/ft/wrench:wrench.force.z", "contact": "/stage/contact:data",
              "x_mm": "/stage/point:point.x*1000", "y_mm": "/stage/point:point.y*1000"}

Rows: one per message of the wavelength topic (the topic of ``wl1_nm``), timed by its
``header.stamp`` (the bag's log time if it has no header); ``t_s`` counts from the first row.
Every other topic is joined by time: a row takes the latest message of that topic stamped at
or before it (the messages of ``record``'s topics share the sample's stamp, so they join
exactly). Wavelengths are rounded to 1 fm, the runtime's unit (as a CSV stores them);
``x_mm``/``y_mm`` are NaN where ``contact`` is 0; ``press_id`` is 0 when not mapped.
"""
from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from fbgforce.errors import InputError

#: Topics written by ``fbgforce record --out LOG.mcap`` (and ``--model``'s estimates).
FBGFORCE_TOPICS = {"peaks": "/fbgforce/peaks", "stage": "/fbgforce/stage",
                   "contact": "/fbgforce/contact", "wrench": "/fbgforce/wrench"}
_WL = ("wl1_nm", "wl2_nm", "wl3_nm", "wl4_nm", "wlT_nm")
#: The field map of fbgforce's own logs.
FBGFORCE_FIELDS = {
    **{col: f"{FBGFORCE_TOPICS['peaks']}:wavelength[{k}]*1e9" for k, col in enumerate(_WL)},
    "contact": f"{FBGFORCE_TOPICS['stage']}:contact",
    "x_mm": f"{FBGFORCE_TOPICS['stage']}:x*1000",
    "y_mm": f"{FBGFORCE_TOPICS['stage']}:y*1000",
    "force_N": f"{FBGFORCE_TOPICS['stage']}:force",
    "press_id": f"{FBGFORCE_TOPICS['stage']}:press_id",
}
#: Columns a field map must give; ``press_id`` may be left out.
MAPPED_COLUMNS = _WL + ("contact", "x_mm", "y_mm", "force_N")
_SPEC = re.compile(r"(/[^:\s]*):([A-Za-z_][A-Za-z0-9_]*(?:\[\d+\])?"
                   r"(?:\.[A-Za-z_][A-Za-z0-9_]*(?:\[\d+\])?)*)(?:\*([^\s]+))?\Z")


@dataclass(frozen=True)
class Field:
    """One column's source: a topic, a path into its message, a scale."""

    column: str
    topic: str
    path: tuple[str | int, ...]
    scale: float

    @classmethod
    def parse(cls, column: str, text: str) -> "Field":
        m = _SPEC.match(text.strip())
        scale = 1.0
        if m is not None and m.group(3) is not None:
            try:
                scale = float(m.group(3))
            except ValueError:
                m = None
        if m is None:
            raise InputError(f"{text!r} is not /TOPIC:FIELD[.FIELD|[INDEX]]...[*SCALE]",
                             column=column)
        path: list[str | int] = []
        for part in m.group(2).split("."):
            name, _, index = part.partition("[")
            path.append(name)
            if index:
                path.append(int(index[:-1]))
        return cls(column, m.group(1), tuple(path), scale)

    def text(self) -> str:
        out = ""
        for p in self.path:
            out += f"[{p}]" if isinstance(p, int) else (f".{p}" if out else p)
        return f"{self.topic}:{out}"

    def get(self, msg: Any) -> Any:
        value = msg
        for p in self.path:
            value = value[p] if isinstance(p, int) else getattr(value, p)
        return value


def parse_fields(fields: Mapping[str, str]) -> dict[str, Field]:
    """A field map (column -> spec) checked: every :data:`MAPPED_COLUMNS` given, nothing else
    but ``press_id``."""
    unknown = sorted(set(fields) - set(MAPPED_COLUMNS) - {"press_id"})
    if unknown:
        raise InputError(f"not a dataset column: {', '.join(unknown)} (map "
                         f"{', '.join(MAPPED_COLUMNS)} and optionally press_id)",
                         column="fields")
    missing = [c for c in MAPPED_COLUMNS if c not in fields]
    if missing:
        raise InputError(f"the field map lacks {', '.join(missing)}", column="fields")
    return {col: Field.parse(col, text) for col, text in fields.items()}


def _stamp_ns(msg: Any, log_time_ns: int) -> int:
    header = getattr(msg, "header", None)
    stamp = getattr(header, "stamp", None)
    if stamp is None:
        return int(log_time_ns)
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def _anyreader(path: Path) -> Any:
    try:
        from rosbags.highlevel import AnyReader  # optional extra [ros2]
        from rosbags.typesys import Stores, get_typestore
    except ImportError:
        raise InputError("reading a rosbag2 log needs rosbags: pip install 'fbgforce[ros2]'",
                         path=str(path)) from None
    return AnyReader([path], default_typestore=get_typestore(Stores.LATEST))


def read_bag_columns(path: str | Path, fields: Mapping[str, str] | None = None
                     ) -> dict[str, np.ndarray]:
    """The mapped columns of a rosbag2 log (a ``.mcap`` file or a bag directory) as arrays.

    Returns ``t_s`` and each mapped column (float64, scaled; one row per message of the
    wavelength topic, in stamp order), ``stamp_ns`` (int64) and ``complete`` (bool: every
    joined topic had a message at or before the row; the columns of a topic that had none
    yet are NaN there).

    Raises
    ------
    fbgforce.errors.InputError
        Not a bag, a mapped topic missing from it, or a field missing from a message (the
        message's 0-based index on its topic is named).
    """
    path = Path(path)
    spec = parse_fields(FBGFORCE_FIELDS if fields is None else fields)
    by_topic: dict[str, list[Field]] = {}
    for f in spec.values():
        by_topic.setdefault(f.topic, []).append(f)
    stamps: dict[str, list[int]] = {t: [] for t in by_topic}
    values: dict[str, list[list[float]]] = {t: [] for t in by_topic}
    try:
        with _anyreader(path) as reader:
            have = {c.topic for c in reader.connections}
            for topic in by_topic:
                if topic not in have:
                    raise InputError(f"no topic {topic} in the bag (it has "
                                     f"{', '.join(sorted(have)) or 'none'})", path=str(path),
                                     column=by_topic[topic][0].column)
            conns = [c for c in reader.connections if c.topic in by_topic]
            for conn, log_time, raw in reader.messages(connections=conns):
                msg = reader.deserialize(raw, conn.msgtype)
                row = []
                for f in by_topic[conn.topic]:
                    try:
                        row.append(float(f.get(msg)) * f.scale)
                    except (AttributeError, IndexError, TypeError, ValueError) as exc:
                        raise InputError(f"message {len(values[conn.topic])} on {conn.topic}"
                                         f" ({conn.msgtype}): {f.text()} not readable: {exc}",
                                         path=str(path), column=f.column) from None
                stamps[conn.topic].append(_stamp_ns(msg, log_time))
                values[conn.topic].append(row)
    except InputError:
        raise
    except Exception as exc:  # rosbags' reader errors have no common base worth naming
        raise InputError(f"not a readable rosbag2 log: {exc}", path=str(path)) from None
    base = spec["wl1_nm"].topic
    if not stamps[base]:
        raise InputError(f"no message on {base}", path=str(path), column="wl1_nm")
    order = np.argsort(np.asarray(stamps[base], dtype=np.int64), kind="stable")
    t_ns = np.asarray(stamps[base], dtype=np.int64)[order]
    out: dict[str, np.ndarray] = {"t_s": (t_ns - t_ns[0]) / 1e9, "stamp_ns": t_ns}
    complete = np.ones(len(t_ns), dtype=bool)
    for topic, cols in by_topic.items():
        table = np.asarray(values[topic], dtype=np.float64).reshape(-1, len(cols))
        if topic == base:
            rows = table[order]
        else:
            own = np.asarray(stamps[topic], dtype=np.int64)
            sort = np.argsort(own, kind="stable")
            idx = np.searchsorted(own[sort], t_ns, side="right") - 1
            found = idx >= 0
            complete &= found
            rows = np.full((len(t_ns), len(cols)), np.nan)
            rows[found] = table[sort][idx[found]]
        for k, f in enumerate(cols):
            out[f.column] = rows[:, k]
    out["complete"] = complete
    return out
