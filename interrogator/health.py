"""The stream's health, once a second: what a controller needs to trust the estimates without
parsing a log (docs/serial.md, "Health"; docs/protocol.md, "Status record").

:class:`Health` counts what the stream sees (samples, the reader's lost frames and reconnects,
the runtime's status flags) and :meth:`Health.snapshot` judges it by the rules of
:func:`judge`: OK, WARN or ERROR with the reasons. ``fbgforce stream`` takes a snapshot every
:data:`PERIOD_S`, hands it to its outputs (``/diagnostics``, the UDP and LCM status records) and
puts the last one in its summary (``health``).
"""
from __future__ import annotations

import time
from typing import Any

import numpy as np

from fbgforce import contract

#: Seconds between two snapshots (the outputs' status records, ``/diagnostics``).
PERIOD_S = 1.0
OK, WARN, ERROR, STALE = 0, 1, 2, 3
LEVEL_NAMES = ("OK", "WARN", "ERROR", "STALE")
#: No sample for this long: WARN (a 1 kHz device delivers a batch every few ms).
SILENT_WARN_S = 0.25
#: No sample for this long: ERROR (the estimates are no longer current).
SILENT_ERROR_S = 1.0
#: Share of the last second's samples with SENSOR_FAULT above which the level is ERROR.
FAULT_ERROR_SHARE = 0.5
#: Share of the tracker's bound above which its offset alone makes a WARN.
TRACKER_WARN_SHARE = 0.8
#: Status flags counted per second, in the order of ``fbgforce.contract.STATUS``.
FLAG_NAMES = tuple(c.name for c in contract.STATUS)
FLAG_VALUES = np.array([c.value for c in contract.STATUS], dtype=np.uint32)


class Health:
    """Counters of a running stream and the snapshot of the last :data:`PERIOD_S`.

    Parameters
    ----------
    model_digest
        The model's digest (:func:`fbgforce.model.freshness.model_digest`), reported as it is.
    tracker_bound_pm
        The at-rest tracker's bound on its correction of a grating's baseline, pm (0: no
        tracker).
    """

    def __init__(self, model_digest: str, tracker_bound_pm: float,
                 now: float | None = None) -> None:
        self.model_digest = model_digest
        self.tracker_bound_pm = float(tracker_bound_pm)
        self.received = 0
        self.estimated = 0
        self.last_sample: float | None = None
        self.started = time.monotonic() if now is None else now
        self._flags = np.zeros(len(FLAG_NAMES), dtype=np.int64)
        self._estimated_in_period = 0
        self._received_in_period = 0
        self._period_start = self.started
        self._lost_at_start = 0
        self._reconnects_at_start = 0
        self.published = 0

    def samples(self, n: int, now: float) -> None:
        """``n`` samples arrived at ``now`` (monotonic seconds)."""
        if n:
            self.received += n
            self._received_in_period += n
            self.last_sample = now

    def estimates(self, status: np.ndarray) -> None:
        """The runtime's status flags of a batch of estimates."""
        status = np.asarray(status, dtype=np.uint32)
        if len(status):
            self.estimated += len(status)
            self._estimated_in_period += len(status)
            self._flags += np.count_nonzero(status[:, None] & FLAG_VALUES[None, :], axis=0)

    def due(self, now: float) -> bool:
        """Whether a snapshot is due at ``now``."""
        return now - self._period_start >= PERIOD_S

    def snapshot(self, now: float, reader_stats: dict[str, int], tracker_offset_pm: float,
                 commands: dict[str, int] | None = None, *, advance: bool = True
                 ) -> dict[str, Any]:
        """The health over the period since the last snapshot (``advance``: start the next).

        Keys: ``level`` (0 OK, 1 WARN, 2 ERROR), ``level_name``, ``message`` (the reasons, or
        ``"OK"``), ``rate_hz`` (samples received per second over the period), ``received``,
        ``lost`` (the reader's lost frames since the start), ``reconnects``, ``silent_s``
        (since the last sample; since the start before the first), ``flags_last_s`` (status
        flag name -> estimates carrying it in the period), ``estimates_last_s``,
        ``lost_last_s``, ``reconnects_last_s``, ``tracker_offset_pm`` (the largest
        correction the at-rest tracker has made to a strain grating's baseline since the
        tare), ``tracker_bound_pm``, ``model_digest`` and ``commands`` (tares and resets
        applied and failed).
        """
        span = max(now - self._period_start, 1e-9)
        lost = int(reader_stats.get("lost_frames", 0))
        reconnects = int(reader_stats.get("reconnects", 0))
        flags = {name: int(c) for name, c in zip(FLAG_NAMES, self._flags.tolist())}
        silent = now - (self.last_sample if self.last_sample is not None else self.started)
        snap: dict[str, Any] = {
            "rate_hz": round(self._received_in_period / span, 1),
            "received": self.received,
            "lost": lost,
            "reconnects": reconnects,
            "silent_s": round(silent, 3),
            "estimates_last_s": self._estimated_in_period,
            "lost_last_s": lost - self._lost_at_start,
            "reconnects_last_s": reconnects - self._reconnects_at_start,
            "flags_last_s": flags,
            "tracker_offset_pm": round(float(tracker_offset_pm), 3),
            "tracker_bound_pm": self.tracker_bound_pm,
            "model_digest": self.model_digest,
            "commands": dict(commands or {}),
        }
        level, reasons = judge(snap, first_sample=self.last_sample is not None)
        snap = {"level": level, "level_name": LEVEL_NAMES[level],
                "message": "; ".join(reasons) if reasons else "OK", **snap}
        if advance:
            self._period_start = now
            self._flags[:] = 0
            self._estimated_in_period = self._received_in_period = 0
            self._lost_at_start, self._reconnects_at_start = lost, reconnects
        return snap


def judge(snap: dict[str, Any], *, first_sample: bool = True) -> tuple[int, list[str]]:
    """The level of a snapshot and its reasons, by these rules (docs/serial.md, "Health"):

    ERROR
        no sample for :data:`SILENT_ERROR_S` or more (before the first sample too); a sensor
        fault on more than :data:`FAULT_ERROR_SHARE` of the period's estimates.
    WARN
        no sample for :data:`SILENT_WARN_S` or more; samples lost or a reconnect in the
        period; any estimate of the period with SENSOR_FAULT, BASELINE_LIMIT (re-tare),
        OUT_OF_RANGE or NOT_TARED; the tracker's offset at :data:`TRACKER_WARN_SHARE` of its
        bound or more; a tare or reset that failed in the period.
    OK
        none of these.
    """
    errors: list[str] = []
    warnings: list[str] = []
    silent = snap["silent_s"]
    if silent >= SILENT_ERROR_S:
        errors.append(f"no sample for {silent:.1f} s" if first_sample else
                      f"no sample yet ({silent:.1f} s)")
    elif silent >= SILENT_WARN_S:
        warnings.append(f"no sample for {silent:.2f} s")
    flags = snap["flags_last_s"]
    n = snap["estimates_last_s"]
    fault = flags.get("SENSOR_FAULT", 0)
    if n and fault > FAULT_ERROR_SHARE * n:
        errors.append(f"sensor fault on {fault} of {n} samples")
    elif fault:
        warnings.append(f"sensor fault on {fault} of {n} samples")
    if snap["lost_last_s"]:
        warnings.append(f"{snap['lost_last_s']} samples lost")
    if snap["reconnects_last_s"]:
        warnings.append(f"link reconnected ({snap['reconnects_last_s']})")
    if flags.get("BASELINE_LIMIT", 0):
        warnings.append("tracker at its bound: re-tare")
    if flags.get("OUT_OF_RANGE", 0):
        warnings.append(f"inputs outside the calibrated range on {flags['OUT_OF_RANGE']} samples")
    if flags.get("NOT_TARED", 0):
        warnings.append("not tared")
    bound = snap["tracker_bound_pm"]
    if bound > 0 and snap["tracker_offset_pm"] >= TRACKER_WARN_SHARE * bound \
            and not flags.get("BASELINE_LIMIT", 0):
        warnings.append(f"tracker offset {snap['tracker_offset_pm']:.0f} of {bound:.0f} pm")
    if snap["commands"].get("failed_last_s", 0):
        warnings.append(f"{snap['commands']['failed_last_s']} command(s) failed")
    if errors:
        return ERROR, errors + warnings
    if warnings:
        return WARN, warnings
    return OK, []
