"""Taring a recording: its unloaded wavelengths from the contact-free samples it flags.

One rule, used by training, evaluation, export calibration and verification alike, so that
every engine is compared on the same baseline. It lives here, below the trainer, because the
exporter and the benches need it too and must not depend on the trainer (data flows one way).
"""
from __future__ import annotations

from typing import Any

import numpy as np

from fbgforce.errors import InputError

#: Contact-free samples this soon after a contact ends are left out of taring and of the
#: temperature fit: a viscoelastic pad relaxes for a while after unloading (hysteresis).
GUARD_S = 0.1
#: Fewest contact-free samples at the start of a recording for a start-only tare.
MIN_START_SAMPLES = 20

#: A clock whose float64 spacing exceeds this fraction of its median step has its step
#: averaged over the regular steps (:func:`sample_rate_hz`).
STEP_ROUNDING_LIMIT = 1e-6


def sample_rate_hz(t_s: np.ndarray) -> float:
    """Sample rate from the median time step (robust to gaps and dropped samples).

    float64 holds a time near 1.8e9 s (a Unix-epoch clock) to 0.24 µs, so each single step
    of a 1 kHz log is off by up to 240 ppm and their median is one of them. Where that
    rounding exceeds :data:`STEP_ROUNDING_LIMIT` of the step, the step is the mean of the
    regular ones (within half a step of the median), which averages the rounding away; a
    clock counting from zero stays below the limit for 10^6 s at 1 kHz and keeps the median.
    """
    t = np.asarray(t_s, dtype=np.float64)
    if t.size < 2:
        return 1000.0
    steps = np.diff(t)
    dt = float(np.median(steps))
    if not dt > 0:
        return 1000.0
    if np.spacing(float(np.max(np.abs(t)))) > STEP_ROUNDING_LIMIT * dt:
        dt = float(np.mean(steps[np.abs(steps - dt) < 0.5 * dt]))
    return 1.0 / dt


def rest_guard_s(contact: np.ndarray, t_s: np.ndarray | None = None) -> float:
    """Guard after each release: :data:`GUARD_S`, or half the median rest if rests are shorter.

    A logger with rests of only 30-80 ms would otherwise leave no contact-free sample at all for
    the temperature fit; the later half of each rest is the most relaxed data it offers.
    """
    c = np.asarray(contact).astype(bool)
    if c.size < 2:
        return GUARD_S
    t = np.arange(c.size, dtype=np.float64) / 1000.0 if t_s is None else np.asarray(t_s, float)
    edges = np.flatnonzero(np.diff(c.astype(np.int8)))
    # Rests strictly between a release and the next contact (not the lead-in or the tail).
    starts = edges[c[edges]] + 1            # first free sample after a release
    ends = edges[~c[edges]]                 # last free sample before a contact
    nxt = np.searchsorted(ends, starts)
    ok = nxt < ends.size
    rests = t[ends[nxt[ok]]] - t[starts[ok]]
    if rests.size == 0:
        return GUARD_S
    return float(min(GUARD_S, 0.5 * np.median(rests)))


def contact_free_mask(contact: np.ndarray, t_s: np.ndarray | None = None,
                      guard_s: float | None = None) -> np.ndarray:
    """Contact-free samples, leaving out ``guard_s`` seconds after every contact ends and half
    of that before every contact starts.

    ``guard_s=None``: :func:`rest_guard_s` (0.1 s unless the recording's rests are shorter).
    """
    c = np.asarray(contact).astype(bool)
    free = ~c
    if guard_s is None:
        guard_s = rest_guard_s(c, t_s)
    if not c.any() or guard_s <= 0:
        return free
    t = np.arange(c.size, dtype=np.float64) / 1000.0 if t_s is None else np.asarray(t_s, float)
    # Time of the most recent contact sample at or before each sample (-inf before the first).
    last_contact_t = np.where(c, t, -np.inf)
    np.maximum.accumulate(last_contact_t, out=last_contact_t)
    # ... and of the next one at or after it (+inf after the last): a log labelled at a
    # threshold of up to 1 N carries sub-threshold load on the samples just before each onset.
    next_contact_t = np.where(c, t, np.inf)[::-1]
    np.minimum.accumulate(next_contact_t, out=next_contact_t)
    next_contact_t = next_contact_t[::-1]
    return free & (t - last_contact_t > guard_s) & (next_contact_t - t > 0.5 * guard_s)


def tare(wl_nm: np.ndarray, contact: np.ndarray, t_s: np.ndarray | None = None, *,
         path: str | None = None) -> tuple[np.ndarray, dict[str, Any]]:
    """Unloaded wavelengths (5,) of one recording: robust median of contact-free samples.

    Uses the contact-free samples before the first contact when there are at least
    :data:`MIN_START_SAMPLES` of them (what the runtime sees when it tares at start-up, and
    free of any temperature drift later in the file); otherwise every contact-free sample the
    file flags (``contact == 0``), minus a guard after each contact (:func:`rest_guard_s`).

    Returns
    -------
    baseline_nm, info
        ``info`` says which samples were used (``"start"`` or ``"flagged"``) and how many.

    Raises
    ------
    InputError
        If the recording has no contact-free samples at all.
    """
    wl = np.asarray(wl_nm, dtype=np.float64)
    c = np.asarray(contact).astype(bool)
    if wl.shape[0] == 0:
        raise InputError("empty recording: nothing to tare", path=path)
    first = int(np.argmax(c)) if c.any() else c.size
    if first >= MIN_START_SAMPLES:
        sel = np.zeros(c.size, dtype=bool)
        sel[:first] = True
        how = "start"
    else:
        sel = contact_free_mask(c, t_s)
        if not sel.any():
            sel = ~c
        how = "flagged"
    if not sel.any():
        raise InputError("no contact-free samples (contact == 0) to tare against: record some "
                         "unloaded samples, ideally at the start", path=path, column="contact")
    return np.median(wl[sel], axis=0), {"tare_samples": int(sel.sum()), "tare_from": how}
