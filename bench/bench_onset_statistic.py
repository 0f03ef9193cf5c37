"""Which statistic the CUSUM should sum, and what the trainer's threshold costs: the quickest
onset any CUSUM on the contact net's margin, or on the force net's output, reaches within a
false-event rate on recordings, beside the model's own setting.

Usage::

    python -m fbgforce.bench.bench_onset_statistic --model DIR --data const_temp.csv rests.csv [--per-min 0.5] [--json]

The model's float pipeline (:func:`fbgforce.model.floatref.predict`: the filter, the
at-rest tracker, the nets) runs on each recording, tared on its own contact-free samples.
For each statistic (``margin``: the contact net's logit difference; ``force``: the force
net's output before gating, N) and each drift ``k`` of a grid (the statistic's quantiles at
rest, plus 0 to 2 of its standard deviations at rest), the threshold ``h`` is read off the same
recordings: the least at which the CUSUM's excursions over the rest samples
(:func:`fbgforce.evaluation.metrics.use_masks`) raise at most ``per_min`` false events a
minute. Each press's onset is then the first sample from its labelled onset on at which
``S >= h``, the CUSUM run from :data:`BEFORE_SAMPLES` before it (restarted after any alarm
there) to the label's end. The row with the least median onset is the statistic's frontier:
what an oracle threshold reaches, not what a calibration can choose. ``own_drift`` is the
same at the model's own drift and clip, ``own`` the model's setting as trained (its false
events counted the same way). docs/tradeoff.md ("The margin or the force?") quotes it on the
foreign family.
"""
from __future__ import annotations

import argparse
import json
import sys
from typing import Any, Sequence

import numpy as np

#: Samples of the statistic before a press's labelled onset that the CUSUM starts from.
BEFORE_SAMPLES = 300
#: Quantiles of the statistic at rest that give the drifts tried.
DRIFT_QUANTILES = (0.5, 0.9, 0.99, 0.999, 0.9999)
#: Standard deviations of the statistic at rest added to each quantile.
DRIFT_SDS = (0.0, 0.5, 1.0, 2.0)
#: The statistics: the contact net's margin and the force net's output before gating.
STATISTICS = {"margin": "margin", "force": "force_raw_N"}


def rest_peaks(recordings: Sequence[dict[str, Any]], stat: str, k: float, lo: float,
               hi: float) -> tuple[np.ndarray, float]:
    """The CUSUM's excursion peaks over every run of rest samples, and the rest's minutes."""
    from fbgforce.model.decision import cusum_peaks
    from fbgforce.recordings.stagelog import runs

    peaks, minutes = [np.empty(0)], 0.0
    for r in recordings:
        for a, b in zip(*runs(r["rest"])):
            peaks.append(cusum_peaks(r[stat][a:b], k, lo, hi))
            minutes += (b - a) / r["rate_hz"] / 60.0
    return np.concatenate(peaks), minutes


def quiet_threshold(peaks: np.ndarray, minutes: float, per_min: float) -> float:
    """The least ``h`` above 0 at which at most ``per_min * minutes`` of the ``peaks`` reach
    it (an ``h`` of 0 would call every sample contact)."""
    allowed = int(np.floor(per_min * minutes))
    top = np.sort(peaks)[::-1]
    return float(np.nextafter(top[allowed] if top.size > allowed else 0.0, np.inf))


def onsets_ms(recordings: Sequence[dict[str, Any]], stat: str, k: float, lo: float, hi: float,
              h: float) -> np.ndarray:
    """Each press's onset delay at ``(k, lo, hi, h)``, ms (inf where ``S`` never reaches ``h``
    before the label ends)."""
    from fbgforce.model.decision import cusum_path
    from fbgforce.recordings.stagelog import runs

    out = []
    for r in recordings:
        s = r[stat]
        for on, end in zip(*runs(r["contact"])):
            start = max(0, on - BEFORE_SAMPLES)
            early = np.flatnonzero(cusum_path(s[start:on], k, lo, hi) >= h)
            if early.size:           # an alarm at rest before the press: S starts again
                start += int(early[-1]) + 1
            hit = np.flatnonzero(cusum_path(s[start:end], k, lo, hi)[on - start:] >= h)
            out.append(1000.0 * hit[0] / r["rate_hz"] if hit.size else np.inf)
    return np.asarray(out, dtype=np.float64)


def _row(recordings: Sequence[dict[str, Any]], stat: str, k: float, lo: float, hi: float,
         per_min: float, h: float | None = None) -> dict[str, Any]:
    """One setting's scores; ``h`` None: :func:`quiet_threshold` at ``per_min``."""
    peaks, minutes = rest_peaks(recordings, stat, k, lo, hi)
    if h is None:
        h = quiet_threshold(peaks, minutes, per_min)
    on = onsets_ms(recordings, stat, k, lo, hi, h)
    found = on[np.isfinite(on)]
    return {"statistic": stat, "k": float(k), "h": float(h), "lo": float(lo), "hi": float(hi),
            "false_events_per_min": float(np.sum(peaks >= h) / minutes) if minutes else None,
            "onset_median_ms": float(np.median(on)) if on.size else None,
            "onset_p90_ms": float(np.percentile(found, 90)) if found.size else None,
            "found": float(found.size / on.size) if on.size else None}


def load(model_dir: str, data: Sequence[str]) -> tuple[Any, list[dict[str, Any]]]:
    """The model, and each recording's statistics, rest and contact masks and rate."""
    from fbgforce.evaluation import metrics as fmetrics
    from fbgforce.model import modeldir
    from fbgforce.model.floatref import predict
    from fbgforce.recordings import dataset, tare as ftare

    model = modeldir.load(model_dir)
    recordings = []
    for path in data:
        ds = dataset.load(path)
        base, _ = ftare.tare(ds.wl_nm, ds.contact, ds.t_s, path=path)
        out = predict(model, ds.wl_nm, base)
        contact = np.asarray(ds.contact, dtype=bool)
        rest = fmetrics.use_masks(np.zeros(contact.size, bool), contact, ds.force_N,
                                  ds.t_s)["rest"]
        recordings.append({"contact": contact, "rest": rest,
                           "rate_hz": ftare.sample_rate_hz(ds.t_s),
                           **{stat: np.asarray(out[key], dtype=np.float64)
                              for stat, key in STATISTICS.items()}})
    return model, recordings


def measure(model_dir: str, data: Sequence[str], per_min: float = 0.5) -> dict[str, Any]:
    """Each statistic's quickest row over the drift grid (``frontier``), the margin at the
    model's own drift (``own_drift``) and the model's own setting (``own``)."""
    model, recordings = load(model_dir, data)
    frontier = {}
    for stat in STATISTICS:
        rest = np.concatenate([r[stat][r["rest"]] for r in recordings])
        drifts = [float(np.quantile(rest, q)) + sd * float(rest.std())
                  for q in DRIFT_QUANTILES for sd in DRIFT_SDS]
        rows = [_row(recordings, stat, k, -np.inf, np.inf, per_min) for k in drifts]
        frontier[stat] = min(rows, key=lambda r: (r["onset_median_ms"], r["h"]))
    iu = model.in_use
    own = (iu.contact_cusum_k, iu.contact_cusum_lo, iu.contact_cusum_hi)
    return {"model": str(model_dir), "data": list(map(str, data)), "per_min": per_min,
            "frontier": frontier,
            "own_drift": _row(recordings, "margin", *own, per_min) if iu.contact_cusum_h else None,
            "own": _row(recordings, "margin", *own, per_min, h=iu.contact_cusum_h)
            if iu.contact_cusum_h else None}


def _line(label: str, row: dict[str, Any] | None) -> str:
    if row is None:
        return f"{label:34s} (the model's decision is no CUSUM)"
    return (f"{label:34s} k {row['k']:7.3f}  h {row['h']:8.3g}  {row['false_events_per_min']:.2f}"
            f" /min  onset {row['onset_median_ms']:.1f} ms (p90 {row['onset_p90_ms']:.1f})"
            f"  found {100.0 * row['found']:.1f} %")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m fbgforce.bench.bench_onset_statistic",
                                 description=__doc__.splitlines()[0])
    ap.add_argument("--model", required=True, metavar="DIR", help="a trained model directory")
    ap.add_argument("--data", required=True, nargs="+", metavar="FILE",
                    help="labelled recordings with presses and rests (CSV/npz)")
    ap.add_argument("--per-min", type=float, default=0.5, metavar="N",
                    help="false contact events per minute at rest the thresholds allow (0.5, "
                         "what the trainer aims at)")
    ap.add_argument("--json", action="store_true", help="print one JSON object")
    args = ap.parse_args(argv)

    from fbgforce.cliargs import fail
    from fbgforce.errors import InputError

    if not args.per_min > 0:
        return fail("bench_onset_statistic: --per-min must be above 0", args.json)
    try:
        out = measure(args.model, args.data, args.per_min)
    except (InputError, OSError, ValueError) as exc:
        return fail(f"bench_onset_statistic: {exc}", args.json)
    if args.json:
        print(json.dumps(out))
        return 0
    print(_line("the model's own setting", out["own"]))
    print(_line(f"its drift, h at {args.per_min:g} /min", out["own_drift"]))
    for stat, row in out["frontier"].items():
        print(_line(f"quickest CUSUM on the {stat}", row))
    return 0


if __name__ == "__main__":
    sys.exit(main())
