"""What a calibration log covers, and what a model trained on it will not know
(``fbgforce coverage``, and the same lines in ``fbgforce train``; docs/lab-import.md
"Coverage").

Per press (a run of equal ``press_id`` with contact): its peak force, where it pressed (the
median contact location), how fast it loaded (10 % to 90 % of its peak over the time taken),
how long it held (the longest stretch within the trainer's hold band of its peak) and how far
it turned back within itself (its deepest dip below the loads before and after it). Over the
log: the temperature grating's span and the time without contact. And what the log's own
noise allows any contact decision on its presses (:mod:`fbgforce.evaluation.onset_bound`): a
model's onset is to be read against that, not against a number from another pad.
"""
from __future__ import annotations

from typing import Any, Sequence

import numpy as np

from fbgforce.evaluation import onset_bound
from fbgforce.evaluation.metrics import HOLD_SMOOTH_S
from fbgforce.recordings.dataset import Dataset
from fbgforce.geometry import BASE_WL_NM, PAD_SIZE_MM, THERMAL_COEFF_PER_K
from fbgforce.trainer.data import HOLD_BAND, HOLD_MIN_S
from fbgforce.trainer.hysteresis import speed_follows_peak
from fbgforce.trainer.preprocess import TEMP_MIN_SPAN_PM
from fbgforce.trainer.synthetic import IDLE_MINUTES

#: Force ranges reported, N (the last open).
FORCE_BINS_N = (0.0, 2.0, 10.0, 30.0, 50.0, 70.0)
#: The location map's cells over the pad (x, y).
MAP_CELLS = (3, 4)
#: A model knows what it saw: below these it is told what is missing.
WANT_FORCE_MAX_N = 60.0
WANT_LIGHT_N = 2.0
WANT_FAST_N_PER_S = 200.0
WANT_SLOW_N_PER_S = 20.0
WANT_HOLD_S = 1.5
WANT_TEMPERATURE_K = 2.0
WANT_LONG_REST_S = 5.0
#: A press turns back within itself when its force dips below the loads on either side of the
#: dip by this share of its peak (and :data:`WANT_TURN_N`): a grip whose force wanders does,
#: and runs the pad's hysteresis through loops no press that rises once and falls once shows.
WANT_TURN_FRACTION = 0.1
WANT_TURN_N = 0.5
#: The temperature grating's nominal sensitivity, pm/K (to quote its span in kelvin).
T_SENSITIVITY_PM_PER_K = BASE_WL_NM[-1] * THERMAL_COEFF_PER_K * 1000.0


def _dip_N(force: np.ndarray, rate: float) -> float:
    """The deepest dip of ``force`` (one press, in time order, sampled at ``rate`` Hz) below
    the lower of its highest loads before and after it, the load averaged over the hold
    test's :data:`~fbgforce.evaluation.metrics.HOLD_SMOOTH_S` first: load-cell noise is no
    turn."""
    k = max(1, min(int(round(HOLD_SMOOTH_S * rate)), force.size))
    f = np.convolve(force, np.ones(k) / k, mode="valid")
    before = np.maximum.accumulate(f)
    after = np.maximum.accumulate(f[::-1])[::-1]
    return float(np.max(np.minimum(before, after) - f)) if f.size else 0.0


def _press_table(ds: Dataset) -> np.ndarray:
    """(presses, 6): peak N, x mm, y mm, loading N/s, hold s, deepest dip N (:func:`_dip_N`),
    for presses with contact."""
    rows = []
    rate = 1.0 / float(np.median(np.diff(ds.t_s))) if len(ds) > 1 else 1000.0
    order = np.argsort(ds.press_id, kind="stable")
    ids, starts = np.unique(ds.press_id[order], return_index=True)
    bounds = np.append(starts, order.size)
    for k in range(ids.size):
        idx = order[bounds[k]:bounds[k + 1]]
        c = idx[ds.contact[idx]]
        if c.size == 0:
            continue
        f = ds.force_N[c]
        peak = float(f.max())
        i_peak = int(np.argmax(f))
        rise = f[:i_peak + 1]
        t = ds.t_s[c][:i_peak + 1]
        t10 = t[np.argmax(rise >= 0.1 * peak)]
        t90 = t[np.argmax(rise >= 0.9 * peak)]
        speed = 0.8 * peak / max(float(t90 - t10), 1.0 / rate)
        near = np.abs(f - peak) <= max(HOLD_BAND[0], HOLD_BAND[1] * peak)
        d = np.diff(np.concatenate([[0], near.astype(np.int8), [0]]))
        hold = float((np.flatnonzero(d == -1) - np.flatnonzero(d == 1)).max()) / rate
        rows.append((peak, float(np.median(ds.x_mm[c])), float(np.median(ds.y_mm[c])), speed,
                     hold, _dip_N(f, rate)))
    return np.array(rows, dtype=np.float64).reshape(-1, 6)


def _location_map(x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, float, float]:
    """Presses per cell of :data:`MAP_CELLS` over the pad (rows y, columns x) from their
    median locations ``x``, ``y``, and the pad's size: the nominal one, or larger where the
    presses reached beyond it."""
    w = max(PAD_SIZE_MM[0], float(np.nanmax(x)) if x.size else 0.0)
    h = max(PAD_SIZE_MM[1], float(np.nanmax(y)) if y.size else 0.0)
    nx, ny = MAP_CELLS
    counts = np.zeros((ny, nx), dtype=int)
    if x.size:
        cx = np.clip((x / w * nx).astype(int), 0, nx - 1)
        cy = np.clip((y / h * ny).astype(int), 0, ny - 1)
        np.add.at(counts, (cy, cx), 1)
    return counts, w, h


def _temperature_and_rests(datasets: Sequence[Dataset]) -> tuple[float, float, float]:
    """The temperature grating's largest span over the recordings (pm, of 1 s means, clear of
    the noise), their time without contact and its longest stretch (s)."""
    span_pm, rest_total, rest_longest = 0.0, 0.0, 0.0
    for ds in datasets:
        dt = float(np.median(np.diff(ds.t_s))) if len(ds) > 1 else 1e-3
        per_s = max(1, int(round(1.0 / dt)))
        m = (len(ds) // per_s) * per_s
        if m:
            wl_t = ds.wl_nm[:m, 4].reshape(-1, per_s).mean(axis=1)   # 1 s means: no noise
            span_pm = max(span_pm, float(np.ptp(wl_t)) * 1e3)
        free = ~ds.contact
        rest_total += float(free.sum()) * dt
        d = np.diff(np.concatenate([[0], free.astype(np.int8), [0]]))
        runs = np.flatnonzero(d == -1) - np.flatnonzero(d == 1)
        rest_longest = max(rest_longest, float(runs.max()) * dt if runs.size else 0.0)
    return span_pm, rest_total, rest_longest


def _missing_presses(peak: np.ndarray, speed: np.ndarray, hold: np.ndarray,
                     counts: np.ndarray) -> list[str]:
    """What the presses (their peaks, loading speeds, holds and location map) leave a model
    short of, in words (the first lines of ``missing``)."""
    missing = []
    if peak.size == 0:
        missing.append("any press: the log has no contact")
        return missing
    if peak.max() < WANT_FORCE_MAX_N:
        missing.append(f"forces above {peak.max():.0f} N (it will extrapolate there)")
    if peak.min() > WANT_LIGHT_N:
        missing.append(f"light touches (no press peaks below {WANT_LIGHT_N:g} N)")
    empty = int((counts == 0).sum())
    if empty:
        missing.append(f"{empty} of {counts.size} pad cells (no press there: see the map)")
    if speed.max() < WANT_FAST_N_PER_S:
        missing.append(f"fast taps (no loading faster than {WANT_FAST_N_PER_S:g} N/s)")
    if speed.min() > WANT_SLOW_N_PER_S:
        missing.append(f"slow ramps (no loading slower than {WANT_SLOW_N_PER_S:g} N/s)")
    if hold.max() < WANT_HOLD_S:
        missing.append(f"holds of {WANT_HOLD_S:g} s or longer (a held grip will read low)")
    return missing


def coverage(datasets: Sequence[Dataset]) -> dict[str, Any]:
    """What the recordings cover (module docstring); ``missing`` lists, in words, what a model
    trained on them has not seen. The keys are those of ``fbgforce coverage --json``."""
    tables = [_press_table(ds) for ds in datasets]
    table = np.concatenate(tables) if tables else np.zeros((0, 6))
    peak, x, y, speed, hold, dip = table.T if table.size else (np.zeros(0),) * 6
    turning = (dip >= WANT_TURN_FRACTION * peak) & (dip >= WANT_TURN_N)
    deepest = float(np.max(dip / np.maximum(peak, 1e-9))) if peak.size else 0.0
    counts, w, h = _location_map(x, y)
    ny, nx = counts.shape
    edges = FORCE_BINS_N
    by_range = {(f"{lo:g}-{hi:g}" if i < len(edges) - 1 else f">{lo:g}"):
                int(((peak > lo) & ((peak <= hi) if i < len(edges) - 1 else True)).sum())
                for i, (lo, hi) in enumerate(zip(edges, edges[1:] + (np.inf,)))}
    span_pm, rest_total, rest_longest = _temperature_and_rests(datasets)
    span_K = span_pm / T_SENSITIVITY_PM_PER_K
    missing = _missing_presses(peak, speed, hold, counts)
    if span_K < WANT_TEMPERATURE_K:
        missing.append(f"temperature changes beyond {span_K:.2g} K (the temperature grating "
                       f"moved {span_pm:.0f} pm)")
    if rest_longest < WANT_LONG_REST_S:
        missing.append(f"long rests (none over {WANT_LONG_REST_S:g} s: creep recovery, the "
                       "zero drifting at rest)")
    # Physical hypotheses the trainer may correct for only where the log can test them
    # (docs/trainer.md, "Evidence before correction").
    unknown = []
    longest_hold = float(hold.max()) if hold.size else 0.0
    if longest_hold < WANT_HOLD_S:
        unknown.append(f"how the pad behaves under a held load: no hold of {WANT_HOLD_S:g} s "
                       f"(longest {longest_hold:.2f} s), so held grips are extrapolated and a "
                       "creep is read from the releases alone")
    if not turning.any():
        unknown.append(f"how the pad answers a load that turns back within a press: none dips "
                       f"by {100 * WANT_TURN_FRACTION:g} % of its peak and rises again "
                       f"(deepest {100 * deepest:.1f} %), so a grip whose force wanders runs "
                       "the pad's friction and damping through loops the calibration never "
                       "showed")
    # Fewer than three presses establish nothing anyway.
    follows = speed_follows_peak(peak, speed) if peak.size >= 3 else None
    if follows is not None:
        unknown.append(f"whether the pad's hysteresis is a friction or a damper: the presses' "
                       f"loading speeds follow their peaks (correlation {follows:.3f}), so a "
                       "gap between rise and fall in proportion to the load is one in "
                       "proportion to its speed, and no holds for friction are made")
    if rest_longest < WANT_LONG_REST_S:
        unknown.append(f"a creep slower than its rests (longest {rest_longest:.1f} s): a slow "
                       "recovery after a release looks like the zero wandering")
    if rest_longest < 60.0 * IDLE_MINUTES:
        unknown.append(f"how the contact decision holds on a pad left alone for minutes: no "
                       f"rest of {IDLE_MINUTES:g} minutes (longest {rest_longest:.1f} s), so "
                       "the idle pads its threshold is read on are the rest noise drawn "
                       "again, without the pad's slow wander")
    if span_K < WANT_TEMPERATURE_K:
        unknown.append(f"the temperature grating's lag behind the strain gratings (the "
                       f"temperature spans {span_K:.2g} K)")
    if span_pm < TEMP_MIN_SPAN_PM:
        unknown.append(f"how each strain grating's thermal response differs from the "
                       f"temperature grating's (it moved {span_pm:.0f} pm, under "
                       f"{TEMP_MIN_SPAN_PM:g}: the reference is subtracted as it is)")
    stats = (lambda a: {"min": float(a.min()), "median": float(np.median(a)),
                        "max": float(a.max())} if a.size else None)
    return {
        "presses": int(peak.size),
        "force_N": stats(peak), "force_ranges": by_range,
        "location_map": {"cells_x": nx, "cells_y": ny, "pad_mm": [w, h],
                         "counts": counts.tolist()},
        "loading_N_per_s": stats(speed),
        "holds": {"presses_holding_s": int((hold >= HOLD_MIN_S).sum()),
                  f"presses_holding_{WANT_HOLD_S:g}_s": int((hold >= WANT_HOLD_S).sum()),
                  "longest_s": float(hold.max()) if hold.size else 0.0},
        "turns": {"presses_turning": int(turning.sum()), "deepest_fraction": deepest},
        "temperature": {"span_pm": span_pm, "span_K": span_K},
        "rest": {"total_s": rest_total, "longest_s": rest_longest},
        "missing": missing,
        "cannot_establish": unknown,
        "noise_allows": onset_bound.bound(datasets),
    }


def coverage_lines(cov: dict[str, Any]) -> list[str]:
    """The report as text lines (what ``fbgforce coverage`` prints and ``train`` repeats)."""
    lines = [f"coverage: {cov['presses']} presses"]
    if cov["force_N"]:
        f, s = cov["force_N"], cov["loading_N_per_s"]
        lines.append(f"  force: peaks {f['min']:.2f}-{f['max']:.1f} N; presses by peak: "
                     + ", ".join(f"{k} N {v}" for k, v in cov["force_ranges"].items()))
        lines.append(f"  loading speed: {s['min']:.3g}-{s['max']:.3g} N/s "
                     f"(median {s['median']:.3g})")
        hd = cov["holds"]
        lines.append(f"  holds: {hd['presses_holding_s']} presses hold >= {HOLD_MIN_S:g} s, "
                     f"{hd[f'presses_holding_{WANT_HOLD_S:g}_s']} >= {WANT_HOLD_S:g} s, longest "
                     f"{hd['longest_s']:.2f} s")
    lm = cov["location_map"]
    lines.append(f"  press locations ({lm['cells_x']} x {lm['cells_y']} cells over "
                 f"{lm['pad_mm'][0]:g} x {lm['pad_mm'][1]:g} mm, top row first):")
    for row in lm["counts"]:
        lines.append("    " + " ".join(f"{v:4d}" for v in row))
    t, r = cov["temperature"], cov["rest"]
    lines.append(f"  temperature: span {t['span_K']:.2f} K ({t['span_pm']:.0f} pm on the "
                 f"temperature grating)")
    lines.append(f"  rest: {r['total_s']:.1f} s without contact, longest {r['longest_s']:.1f} s")
    if cov["missing"]:
        lines.append("  a model trained on it will not know: " + "; ".join(cov["missing"]))
    else:
        lines.append("  nothing missing by these checks")
    if cov.get("cannot_establish"):
        lines.append("  it cannot establish: " + "; ".join(cov["cannot_establish"]))
    lines += _noise_allows_lines(cov.get("noise_allows"))
    return lines


def _noise_allows_lines(b: dict[str, Any] | None) -> list[str]:
    """What the log's noise allows any contact decision (:func:`onset_bound.bound`), in words."""
    if b is None:
        return ["  the noise allows: not measured (no rest to measure the noise on)"]
    head = (f"  the noise allows: {b['noise_pm']:.1f} pm per grating")
    if not b["presses"]:
        return [head + f"; no press with a rest before it and 5 samples above "
                f"{onset_bound.SENSITIVITY_MIN_N:g} N to bound the onset on"]
    o = b["onset_bound_ms"]
    noise = ("" if b["force_noise_N"] is None
             else f", a force noise of {b['force_noise_N']:.3f} N a sample at best")
    noise += onset_bound.lag_text(b)
    return [head + f"{noise}; no contact decision within {b['per_min']:g} false event a minute "
            f"at rest finds its {b['presses']} presses sooner than "
            f"{onset_bound.delay_text(o['median'])} after the label (median; p90 "
            f"{onset_bound.delay_text(o['p90'])}), nor more than "
            f"{100 * b['detected_above_1N']:.2f} % of their samples above "
            f"{onset_bound.SENSITIVITY_MIN_N:g} N"]
