"""How early any contact decision could find the presses of a recording: the information
bound on onset delay, from the interrogator's noise and the pad's sensitivity.

Usage::

    python -m fbgforce.bench.bench_onset_bound --data const_temp.csv rests.csv [--per-min 1] [--json]

A detector that raises at most ``per_min`` false contact events a minute at rest has an
average run length at rest of ``gamma = 60 * rate / per_min`` samples, and cannot, on
average, find a change before the log-likelihood ratio of what it has seen since the change
reaches ``log(gamma)`` (Lorden 1971 for a fixed change, Lai 1998 for one that grows, as a
press does; asymptotically in ``gamma``). For a press of force ``f(t)`` on a pad whose shifts
move by ``f * s`` (``s``, pm/N per grating, the press's own location) under white noise of
covariance ``C`` (pm^2), each sample adds ``f(t)^2 * s' C^-1 s / 2`` to that ratio. The bound
is the delay after the contact label's onset at which the sum from the press's first loaded
sample reaches ``log(gamma)`` (0 where it does so before the label):
the quickest median onset of a detector that knew the press's location
and force profile in advance. Any decision that must learn them from the signal, the contact
net's included, comes later.

``C`` is half the covariance of the rests' first differences (white noise doubles in a
difference; the zero's wander and the temperature's drift vanish from it; the rests those of
the tare, :func:`fbgforce.recordings.tare.contact_free_mask`), ``s`` each press's
least-squares shift per newton over its samples above 1 N, from the rest before it.
docs/tradeoff.md ("How quick the decision can be") quotes the bound beside the frontier of
``fbgforce tradeoff --decision`` on the foreign family.
"""
from __future__ import annotations

import argparse
import json
import math
import sys
from typing import Any, Sequence

import numpy as np

#: Unloaded samples before a press that give its zero for the sensitivity fit.
ZERO_SAMPLES = 50
#: Force below which the load cell's own noise is all there is (its squares would add
#: evidence the press never gave), N.
FORCE_FLOOR_N = 0.05
#: Force above which a press's samples give its sensitivity, N.
SENSITIVITY_MIN_N = 1.0


def rest_noise_covariance(wl_pm: np.ndarray, contact: np.ndarray,
                          t_s: np.ndarray | None = None) -> np.ndarray | None:
    """Half the covariance of consecutive rest samples' differences, pm^2 (None with fewer
    than 100 pairs); the rest samples are the tare's
    (:func:`fbgforce.recordings.tare.contact_free_mask`)."""
    from fbgforce.recordings.tare import contact_free_mask

    rest = contact_free_mask(contact, t_s)
    pair = rest[1:] & rest[:-1]
    if pair.sum() < 100:
        return None
    d = np.diff(wl_pm, axis=0)[pair]
    return np.cov(d, rowvar=False) / 2.0


def press_bounds(wl_pm: np.ndarray, force_N: np.ndarray, contact: np.ndarray,
                 noise_cov: np.ndarray, rate_hz: float, per_min: float = 1.0
                 ) -> list[dict[str, float]]:
    """The bound for every press of one recording with a rest before it.

    Parameters
    ----------
    wl_pm
        (n, m) the gratings' shifts, pm (any common offset).
    force_N, contact
        (n,) the load cell and the contact label.
    noise_cov
        (m, m) the noise covariance per sample, pm^2 (:func:`rest_noise_covariance`).
    rate_hz
        Sample rate.
    per_min
        False events per minute at rest the detector may raise.

    Returns
    -------
    list of dict
        Per press: ``onset_bound_ms`` (inf where the press never gives enough evidence) and
        ``force_noise_N`` (the per-sample noise of a force read by the matched filter at the
        press's location, ``1 / sqrt(s' C^-1 s)``).
    """
    from fbgforce.recordings.stagelog import runs

    contact = np.asarray(contact, bool)
    f = np.where(np.asarray(force_N, float) > FORCE_FLOOR_N, np.asarray(force_N, float), 0.0)
    threshold = math.log(60.0 * rate_hz / per_min)
    inv = np.linalg.pinv(noise_cov)
    starts, stops = runs(contact)
    out = []
    rests_from = [0, *stops[:-1].tolist()]
    for t_on, t_off, rest_from in zip(starts.tolist(), stops.tolist(), rests_from):
        # From the last unloaded sample of the rest: the tail of the release before counts
        # for nothing.
        unloaded = np.flatnonzero(f[rest_from:t_on] == 0.0)
        loaded = np.arange(t_on, t_off)[f[t_on:t_off] > SENSITIVITY_MIN_N]
        if not unloaded.size or unloaded[-1] + 1 < ZERO_SAMPLES or loaded.size < 5:
            continue
        start = rest_from + int(unloaded[-1])
        zero = wl_pm[start + 1 - ZERO_SAMPLES:start + 1].mean(axis=0)
        s = (f[loaded] @ (wl_pm[loaded] - zero)) / float(f[loaded] @ f[loaded])
        q = float(s @ inv @ s)
        evidence = 0.5 * q * np.cumsum(f[start:t_off] ** 2)
        reached = np.flatnonzero(evidence >= threshold)
        delay = (start + int(reached[0]) - int(t_on)) if reached.size else math.inf
        out.append({"onset_bound_ms": max(delay, 0) * 1000.0 / rate_hz,
                    "force_noise_N": 1.0 / math.sqrt(q) if q > 0 else math.inf})
    return out


def measure(data: Sequence[str], per_min: float = 1.0) -> dict[str, Any]:
    """:func:`press_bounds` over the recordings of ``data`` (the noise from each one's own
    rests, or from all of them where one has too few), with the median and 90th percentile."""
    from fbgforce.errors import InputError
    from fbgforce.recordings import dataset, tare as ftare

    recs = [dataset.load(p) for p in data]
    shifts = [1000.0 * np.asarray(ds.wl_nm, float) for ds in recs]
    covs = [rest_noise_covariance(w, ds.contact, ds.t_s) for w, ds in zip(shifts, recs)]
    known = [c for c in covs if c is not None]
    if not known:
        raise InputError("no 100 samples of rest clear of contact to measure the noise on",
                         path=", ".join(map(str, data)))
    pooled = np.mean(known, axis=0)
    presses = []
    for w, ds, cov in zip(shifts, recs, covs):
        presses += press_bounds(w, ds.force_N, ds.contact, pooled if cov is None else cov,
                                ftare.sample_rate_hz(ds.t_s), per_min)
    bound = np.array([p["onset_bound_ms"] for p in presses])
    noise = np.array([p["force_noise_N"] for p in presses])
    grating = float(np.sqrt(np.median(np.diag(pooled))))
    return {"data": list(map(str, data)), "per_min": per_min, "presses": len(presses),
            "noise_pm": grating,
            "onset_bound_ms": {"median": float(np.median(bound)) if bound.size else None,
                               "p90": float(np.percentile(bound, 90)) if bound.size else None},
            "force_noise_N": {"median": float(np.median(noise)) if noise.size else None}}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m fbgforce.bench.bench_onset_bound",
                                 description=__doc__.splitlines()[0])
    ap.add_argument("--data", required=True, nargs="+", metavar="FILE",
                    help="labelled recordings with presses and rests (CSV/npz)")
    ap.add_argument("--per-min", type=float, default=1.0, metavar="N",
                    help="false contact events per minute at rest the detector may raise (1)")
    ap.add_argument("--json", action="store_true", help="print one JSON object")
    args = ap.parse_args(argv)

    from fbgforce.cliargs import fail
    from fbgforce.errors import InputError

    if not args.per_min > 0:
        return fail("bench_onset_bound: --per-min must be above 0", args.json)
    try:
        out = measure(args.data, args.per_min)
    except (InputError, OSError, ValueError) as exc:
        return fail(f"bench_onset_bound: {exc}", args.json)
    if args.json:
        print(json.dumps(out))
    elif not out["presses"]:
        print(f"no press with {ZERO_SAMPLES} unloaded samples before it and 5 above "
              f"{SENSITIVITY_MIN_N:g} N")
    else:
        b = out["onset_bound_ms"]
        print(f"{out['presses']} presses, noise {out['noise_pm']:.1f} pm per grating, force "
              f"noise of the matched filter {out['force_noise_N']['median']:.3f} N per sample: "
              f"no decision within {args.per_min:g} false event"
              f"{'' if args.per_min == 1 else 's'} a minute finds them sooner "
              f"than {b['median']:.1f} ms median ({b['p90']:.1f} ms p90) after the label")
    return 0


if __name__ == "__main__":
    sys.exit(main())
