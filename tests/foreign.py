"""Foreign calibration logs: an INDEPENDENT generator of files in the dataset contract.

The trainer will be scored on logs from sources we never see (other grippers on real x-y-z
stages, other simulators). This test helper makes such logs with physics that deliberately
differ from ``fbgforce.sim`` and ``fbgforce.geometry`` (neither is imported here):

- a 30 × 40 mm pad (not 21 × 27) on four supports in a skewed quadrilateral, the load shared
  among them like a FLEXIBLE plate (inverse-square-distance shares, not the rigid-plate
  force/torque balance), so the strain-to-location map is nonlinear;
- per-channel sensitivities ±30 %, a quadratic beam response (±8 % at full load) and linear
  cross-talk between channels (up to 5 %), optional viscoelastic creep, optional
  rate-independent pad friction (a Dahl model, stepped in the beams' travel so that the pad
  sticks at a reversal, then slips smoothly: not the simulator's play operators), optional
  rate-dependent hysteresis (a damper beside the beams: no creep);
- base wavelengths anywhere in 1510–1590 nm; sample rates 500 / 1000 / 2000 Hz; white noise
  2–15 pm quantised to 0.1 pm;
- temperature: a slow ramp plus a wander seen by every grating with its own coefficient, or
  exactly none (then the coefficients cannot be identified from the data), or a fast ramp of
  tens of kelvin at a set rate (K/min) starting with the first press; the temperature grating
  can see the temperature through its own first-order lag (seconds: it sits elsewhere in the
  fingertip), so a fast ramp leaves the reference behind the strain gratings;
- a slow wander of every grating on its own (a few pm over tens of seconds: interrogator and
  fibre mounts), independent of temperature;
- presses: trapezoidal force profiles up to 50 or 100 N, held for up to seconds, rests of any
  length (from very short ones to tens of seconds), a recording that starts inside the end of
  a press;
- labels: contact = load-cell force above a threshold of 0.1–1 N, load-cell noise making small
  negative forces at rest, press ids large and non-contiguous in arbitrary order;
- files: columns in a shuffled order, ``#`` comments before the header and among the data,
  extra columns (numeric and text), optionally CRLF line ends; one device may be logged in
  several files.

Use :func:`device` for a device (seeded), :func:`log` for one recording of it, and
:func:`write_csv` to write a messy-but-valid CSV that ``fbgforce.recordings.dataset.load`` must accept,
:func:`write_lab_logs` for the raw interrogator and stage logs a lab would have of it (for
``fbgforce import``: peaks in pm, another stage clock).
:data:`VARIANTS` are the named cases the generalisation tests and docs/trainer.md use.
:data:`IN_USE_VARIANTS` are recordings of ONE fingertip (:data:`IN_USE_FINGERTIP`, device
seed 200) in the conditions it is used in: a calibration log, presses at constant temperature,
thermal ramps, long rests, held grips and light presses; each carries a ``role`` for the
in-use benchmark (bench/bench_in_use.py, docs/robustness.md "Use in the field").
:data:`FAMILY` are fingertips that differ from that one in exactly one piece of the physics the
in-use stages assume (creep absent or at other time constants, friction or a rate-dependent
damper alone, interrogator noise, the reference grating's lag, thermal mismatch);
:func:`write_family` records each in :data:`FAMILY_VARIANTS` (``--family``).

As a script it writes the logs the generalisation and in-use benchmarks score
(bench/bench_generalisation.py and bench/bench_in_use.py read them; neither imports this file)::

    python tests/foreign.py --out DIR [--presses 60] [VARIANT ...]
    python tests/foreign.py --out DIR --family [--presses 100] [MEMBER ...]   # defaults shown

For each variant (default all of :data:`VARIANTS`; the in-use ones by name): a device (the
variant's ``device_seed``, else seed 100 + its index in :data:`VARIANTS`), two logs of it (seeds
1 and 2) as ``DIR/<variant>_A.csv`` and ``DIR/<variant>_B.csv``, and ``DIR/foreign.json`` naming
them with the device's true temperature coefficients and the variant's role and temperature
ramp (:data:`MANIFEST`). A variant with ``presses_max`` writes at most that many presses per
log (long rests and holds would otherwise make files of hundreds of MB).
"""
from __future__ import annotations

import argparse
import json
import sys
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from fbgforce.recordings.dataset import Dataset


@dataclass(frozen=True)
class Spec:
    """What a foreign log looks like; every field has a physical or logging meaning."""

    name: str
    pad_mm: tuple[float, float] = (30.0, 40.0)
    rate_hz: float = 1000.0
    noise_pm: float = 5.0
    force_max_N: float = 50.0            # the presses' peaks are drawn from
    force_min_N: float = 0.5             # [force_min_N, force_max_N]
    full_scale_N: float | None = None    # the load the beams are built for (their quadratic
                                         # term's scale); None: force_max_N. A protocol of
                                         # lighter presses on the same pad keeps the pad's.
    hold_modulation: float = 0.0         # a hold's force wanders by +- this fraction of its
                                         # level, one slow sine (a hand's grip is not a stage)
    contact_threshold_N: float = 0.5
    load_cell_noise_N: float = 0.03
    drift: bool = True                   # temperature ramp + wander (False: exactly constant)
    drift_K: float = 1.5                 # ramp over the log, K
    ramp_K_per_min: float = 0.0          # > 0: from the first press the temperature rises at
                                         # this rate to drift_K and stays (no wander)
    temp_lag_s: float = 0.0              # first-order lag of the temperature grating, s
    temp_coeff_spread: float = 0.1       # strain gratings' thermal coefficients: 1 +- this
                                         # times the reference grating's
    wander_pm: float = 0.0               # slow wander of each grating on its own (peak), pm
    creep: float = 0.0                   # viscoelastic fraction (0 = none)
    creep_s: float = 0.05                # time constant of the viscoelastic part, s
    friction: float = 0.0                # pad friction: loading/unloading gap at equal load,
                                         # as a fraction of that load (0 = none)
    friction_sharpness: float = 4.0      # how fast a reversal slips (higher: sharper corner)
    viscous_s: float = 0.0               # rate-dependent (Kelvin-Voigt) hysteresis: the beams
                                         # carry F - viscous_s * dF/dt, s (0 = none); it acts
                                         # only while the load moves, so it leaves no creep
    rest_s: tuple[float, float] = (0.15, 0.4)
    ramp_s: tuple[float, float] = (0.15, 0.35)
    hold_s: tuple[float, float] = (0.0, 0.2)
    start_in_contact: int = 0            # samples of a press's tail before the first rest
    presses_max: int | None = None       # most presses a log of this variant holds
    last_hold_s: float = 0.0             # > 0: the last press holds this long instead
    device_seed: int | None = None       # the fingertip (None: one per variant, see write_logs)
    role: str = ""                       # what the log measures in bench/bench_in_use.py
    crlf: bool = False
    extras: bool = True


@dataclass
class Device:
    """One foreign fingertip: geometry, gratings and their responses (from a seed)."""

    spec: Spec
    supports_mm: np.ndarray              # (4, 2)
    soft_mm: float                       # plate flexibility length in the share law
    gain_pm_per_N: np.ndarray            # (4,) per beam
    quad: np.ndarray                     # (4,) relative quadratic term at full beam load
    crosstalk: np.ndarray                # (4, 4) I + small off-diagonals
    base_nm: np.ndarray                  # (5,)
    temp_pm_per_K: float                 # reference grating
    temp_coeff: np.ndarray               # (4,) strain gratings relative to the reference


def device(spec: Spec, seed: int) -> Device:
    """A device drawn from ``seed``: skewed supports, sensitivities ±30 %, wavelengths anywhere
    in 1510–1590 nm (at least 4 nm apart so peaks never cross), thermal coefficients within
    ``spec.temp_coeff_spread`` of the reference grating's."""
    rng = np.random.default_rng(seed)
    w, h = spec.pad_mm
    corners = np.array([[0.2 * w, 0.15 * h], [0.8 * w, 0.2 * h], [0.15 * w, 0.85 * h],
                        [0.85 * w, 0.8 * h]])
    supports = corners + rng.normal(0.0, 0.04 * min(w, h), corners.shape)
    while True:
        base = np.sort(rng.uniform(1510.0, 1590.0, 5))
        if np.min(np.diff(base)) > 4.0:
            break
    rng.shuffle(base)  # the reference grating need not be the longest wavelength
    off = rng.uniform(-0.05, 0.05, (4, 4))
    np.fill_diagonal(off, 0.0)
    return Device(spec=spec, supports_mm=supports, soft_mm=rng.uniform(6.0, 10.0),
                  gain_pm_per_N=40.0 * rng.uniform(0.7, 1.3, 4), quad=rng.uniform(-0.08, 0.08, 4),
                  crosstalk=np.eye(4) + off, base_nm=base,
                  temp_pm_per_K=rng.uniform(9.0, 11.0),
                  temp_coeff=rng.uniform(1.0 - spec.temp_coeff_spread,
                                         1.0 + spec.temp_coeff_spread, 4))


def shares(dev: Device, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Fraction of the load on each support (n, 4): inverse-square distance, summing to 1."""
    d2 = (x[:, None] - dev.supports_mm[:, 0]) ** 2 + (y[:, None] - dev.supports_mm[:, 1]) ** 2
    wgt = 1.0 / (d2 + dev.soft_mm ** 2)
    return wgt / wgt.sum(axis=1, keepdims=True)


def pad_friction(beam: np.ndarray, gap: float, sharpness: float) -> np.ndarray:
    """Beam loads (n, 4) after a frictional pad: a Dahl model, passive.

    A friction force ``z`` per beam opposes the pad's motion and saturates at ``mu |F|`` with
    ``mu = gap / 2`` (Coulomb: proportional to the load, so the loop closes at zero), approached
    exponentially in the beam's own travel, as Dahl's law has it in the displacement:
    ``z <- b + (z - b) exp(-sharpness |db| / (mu |F|))`` with ``b = mu |F| sign(dF)``. The beam
    receives ``F - z`` and so moves the way the load does, by ``dF / (1 + a)`` with ``a =
    sharpness |b - z| / (mu |F|)`` to first order: right after a reversal (``a = 2 sharpness``)
    the pad nearly sticks and the beam's load hardly moves, then slips onto the other branch.
    Depends on the sequence of loads only, not on time.
    """
    mu = gap / 2.0
    out = np.empty_like(beam)
    for j in range(beam.shape[1]):
        col = beam[:, j].tolist()
        res = [0.0] * len(col)
        z, prev = 0.0, 0.0
        for i, f in enumerate(col):
            d = f - prev
            bound = mu * abs(f)
            if bound == 0.0:
                z = 0.0
            elif d != 0.0:
                target = bound if d > 0 else -bound
                travel = abs(d) / (1.0 + sharpness * abs(target - z) / bound)
                z = target + (z - target) * np.exp(-sharpness * travel / bound)
            res[i] = f - z
            prev = f
        out[:, j] = res
    return out


def strain_pm(dev: Device, force: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Noise-free strain-grating shifts (n, 4), pm: shares, (a rate-dependent damper, pad
    friction,) quadratic beams, cross-talk."""
    beam = force[:, None] * shares(dev, x, y)
    if dev.spec.viscous_s > 0:
        # A damper in parallel with the beams takes up part of the load while it moves:
        # loading reads low and unloading high, by more the faster the press.
        beam = beam - dev.spec.viscous_s * dev.spec.rate_hz * np.gradient(beam, axis=0)
    if dev.spec.friction > 0:
        beam = pad_friction(beam, dev.spec.friction, dev.spec.friction_sharpness)
    # A beam rarely carries more than half the load the pad is built for.
    full = (dev.spec.full_scale_N or dev.spec.force_max_N) / 2.0
    s = dev.gain_pm_per_N * beam * (1.0 + dev.quad * beam / full)
    return s @ dev.crosstalk.T


def lag(x: np.ndarray, tau_samples: float) -> np.ndarray:
    """First-order lag of ``x`` ((n,) or (n, k), each column on its own) with a time constant
    of ``tau_samples``, starting from zero: ``y[i] = y[i-1] + a (x[i] - y[i-1])``."""
    a = 1.0 - np.exp(-1.0 / tau_samples)
    cols = x.reshape(x.shape[0], -1)
    out = np.empty(cols.shape)
    for j in range(cols.shape[1]):
        acc = 0.0
        res = [0.0] * cols.shape[0]
        for i, v in enumerate(cols[:, j].tolist()):
            acc += a * (v - acc)
            res[i] = acc
        out[:, j] = res
    return out.reshape(x.shape)


def temperature_K(spec: Spec, rng: np.random.Generator, t: np.ndarray, ramp_from: int
                  ) -> np.ndarray:
    """Temperature change (n,) K at the sample times ``t``, zero at the first sample.

    A fast ramp (``ramp_K_per_min`` > 0) starts at sample ``ramp_from`` (the first press: the
    start-up tare sees a constant temperature) and rises to ``drift_K``, then stays; otherwise
    ``drift_K`` over the whole log plus a 0.3 K wander, or exactly constant.
    """
    if not spec.drift:
        return np.zeros(t.size)
    el = t - t[0]
    if spec.ramp_K_per_min > 0:
        return np.clip((el - el[min(ramp_from, el.size - 1)]) * spec.ramp_K_per_min / 60.0,
                       0.0, spec.drift_K)
    dur = t.size / spec.rate_hz
    phase = rng.uniform(0, 2 * np.pi)
    temp = spec.drift_K * el / dur + 0.3 * np.sin(2 * np.pi * el / max(dur / 1.5, 1.0) + phase)
    return temp - temp[0]


def wander_pm(spec: Spec, rng: np.random.Generator, t: np.ndarray) -> np.ndarray:
    """Slow wander (n, 5) pm of each grating on its own: three sinusoids per grating with
    periods of 30-300 s and random phases, together at most ``spec.wander_pm``."""
    period = rng.uniform(30.0, 300.0, (3, 5))
    phase = rng.uniform(0.0, 2 * np.pi, (3, 5))
    el = (t - t[0])[:, None]
    return (spec.wander_pm / 3.0) * sum(np.sin(2 * np.pi * el / period[k] + phase[k])
                                        for k in range(3))


#: Periods (s) of a held grip's wander (:attr:`Spec.hold_modulation`).
HOLD_MODULATION_PERIOD_S = (4.0, 8.0)


def _profile(rng: np.random.Generator, spec: Spec, peak: float, last: bool = False) -> np.ndarray:
    r = spec.rate_hz
    up = int(rng.uniform(*spec.ramp_s) * r)
    hold = int(rng.uniform(*spec.hold_s) * r)
    if last and spec.last_hold_s > 0:
        hold = int(spec.last_hold_s * r)
    down = int(rng.uniform(*spec.ramp_s) * r)
    # Indentation at constant speed into a rubber pad: force grows faster than linearly.
    rise = np.linspace(0.0, 1.0, up, endpoint=False) ** 1.4
    fall = np.linspace(1.0, 0.0, down) ** 1.4
    level = np.ones(hold)
    if spec.hold_modulation > 0 and hold:
        # Slow enough that a 0.2 s window still reads the grip as held
        # (fbgforce.evaluation.metrics, HOLD_BAND_FRACTION).
        period = rng.uniform(*HOLD_MODULATION_PERIOD_S) * r
        phase = rng.uniform(0.0, 2 * np.pi)
        level = 1.0 + spec.hold_modulation * np.sin(2 * np.pi * np.arange(hold) / period + phase)
        rise, fall = rise * level[0], fall * level[-1]
    return peak * np.concatenate([rise, level, fall])


def log(dev: Device, seed: int, n_press: int = 40) -> Dataset:
    """One recording of ``dev`` with ``n_press`` presses (seeded)."""
    spec = dev.spec
    rng = np.random.default_rng(seed)
    w, h = spec.pad_mm
    forces, xs, ys, pids = [], [], [], []
    # Press ids: large, non-contiguous, in no particular order.
    ids = rng.choice(np.arange(10 ** 6, 10 ** 6 + 50 * (n_press + 1)), n_press + 1, replace=False)
    ids = ids * 7919 + 10 ** 10
    if spec.start_in_contact:
        k = spec.start_in_contact
        forces.append(np.linspace(rng.uniform(2.0, 6.0), 0.0, k + 1)[:k])
        xs.append(np.full(k, rng.uniform(2.0, w - 2.0)))
        ys.append(np.full(k, rng.uniform(2.0, h - 2.0)))
        pids.append(np.full(k, ids[-1]))
    ramp_from = 0
    for p in range(n_press):
        rest = np.zeros(int(rng.uniform(*spec.rest_s) * spec.rate_hz))
        if p == 0:
            ramp_from = spec.start_in_contact + rest.size
        f = _profile(rng, spec, rng.uniform(spec.force_min_N, spec.force_max_N),
                     last=p == n_press - 1)
        forces.append(np.concatenate([rest, f]))
        n = rest.size + f.size
        xs.append(np.full(n, rng.uniform(1.0, w - 1.0)))
        ys.append(np.full(n, rng.uniform(1.0, h - 1.0)))
        pids.append(np.full(n, ids[p]))
    # A final rest so the last press is complete.
    tail = int(0.2 * spec.rate_hz)
    forces.append(np.zeros(tail))
    xs.append(np.full(tail, xs[-1][-1]))
    ys.append(np.full(tail, ys[-1][-1]))
    pids.append(np.full(tail, ids[n_press - 1]))
    f = np.concatenate(forces)
    x, y = np.concatenate(xs), np.concatenate(ys)
    n = f.size
    t = np.arange(n) / spec.rate_hz + rng.uniform(0.0, 100.0)
    s = strain_pm(dev, f, x, y)
    if spec.creep > 0:
        # Viscoelastic pad: part of the response follows the load with a lag (creep_s).
        s = (1.0 - spec.creep) * s + spec.creep * lag(s, spec.creep_s * spec.rate_hz)
    temp_K = temperature_K(spec, rng, t, ramp_from)
    # The temperature grating sits elsewhere in the fingertip and may lag the beams' gratings.
    temp_ref_K = lag(temp_K, spec.temp_lag_s * spec.rate_hz) if spec.temp_lag_s > 0 else temp_K
    shift_t = dev.temp_pm_per_K * temp_K
    wl = np.empty((n, 5))
    wl[:, :4] = dev.base_nm[:4] + (s + np.outer(shift_t, dev.temp_coeff)) / 1000.0
    wl[:, 4] = dev.base_nm[4] + dev.temp_pm_per_K * temp_ref_K / 1000.0
    if spec.wander_pm > 0:
        wl += wander_pm(spec, rng, t) / 1000.0
    wl += rng.normal(0.0, spec.noise_pm / 1000.0, wl.shape)
    wl = np.round(wl, 4)  # the interrogator reports 0.1 pm
    contact = f > spec.contact_threshold_N
    cell = f + rng.normal(0.0, spec.load_cell_noise_N, n)
    extra: dict[str, np.ndarray] = {}
    if spec.extras:
        extra = {"stage_z_mm": -0.01 * f + rng.normal(0, 1e-3, n),
                 "room_C": 22.0 + temp_K,
                 "operator": np.where(np.arange(n) % 2 == 0, "ana", "bo")}
    return Dataset(t_s=t, wl_nm=wl, contact=contact, x_mm=np.where(contact, x, np.nan),
                   y_mm=np.where(contact, y, np.nan), force_N=cell, press_id=np.concatenate(pids),
                   extra=extra, source=f"foreign:{spec.name} seed={seed}")


def write_csv(ds: Dataset, path: str | Path, seed: int = 0, crlf: bool = False) -> Path:
    """A valid but unusual CSV: shuffled columns, comments before the header and among the
    rows, a blank line, extra columns last or first, optional CRLF (dataset contract §4)."""
    rng = np.random.default_rng(seed)
    cols = ds.columns()
    names = list(cols)
    order = [names[i] for i in rng.permutation(len(names))]
    fmt = {"t_s": "{:.6f}", "contact": "{:d}", "press_id": "{:d}", "force_N": "{:.4f}",
           "x_mm": "{:.3f}", "y_mm": "{:.3f}"}
    text_cols = []
    for name in order:
        arr = cols[name]
        if arr.dtype.kind in "US":
            text_cols.append([str(v) for v in arr])
            continue
        if arr.dtype == bool:
            arr = arr.astype(np.int64)
        f = fmt.get(name, "{:.4f}" if name.startswith("wl") else "{:.6g}")
        text_cols.append(["" if (isinstance(v, float) and np.isnan(v)) else f.format(v)
                          for v in arr.tolist()])
    rows = [",".join(r) for r in zip(*text_cols)]
    mid = len(rows) // 2
    lines = ["# exported by stage-logger 3.1 (foreign format test)",
             "# interrogator: 4+1 gratings, peaks in nm", ",".join(order),
             *rows[:mid], "# stage paused for re-homing", "", *rows[mid:]]
    nl = "\r\n" if crlf else "\n"
    p = Path(path)
    p.write_text(nl.join(lines) + nl, encoding="utf-8")
    return p


def write_lab_logs(ds: Dataset, directory: str | Path, *, rate_hz: float = 500.0,
                   offset_s: float = 0.1, drift_ppm: float = 80.0, jitter_s: float = 1e-4,
                   seed: int = 0) -> dict[str, str]:
    """The raw files a lab with this fingertip would have, for ``fbgforce import``: an
    interrogator export (peaks in pm, its own column names in a shuffled order, a status text
    column, comment lines) and a tab-separated stage log (load in mN, position in µm) on a
    clock of its own.

    The stage clock reads ``t + offset_s + drift_ppm * 1e-6 * (t - t[0])`` at interrogator time
    ``t`` (the log's ``t_s``); it samples every ``1 / rate_hz`` on its own clock with Gaussian
    jitter (clipped to 0.4 periods), from half a second before the interrogator's first sample
    to half a second after its last; the load is the log's load cell, the position the press's
    place, held through the rests. Writes ``import.toml`` beside them (the ``--map`` that
    imports them) and returns the same flags by key (``fbg``, ``fbg-columns``, ...)."""
    out = Path(directory)
    out.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    fbg_names = ["Ch 1 [pm]", "Ch 2 [pm]", "Ch 3 [pm]", "Ch 4 [pm]", "Ref [pm]"]
    order = rng.permutation(6)
    header = (["Timestamp [s]"] + fbg_names)
    cols = [[f"{v:.6f}" for v in ds.t_s.tolist()]] + [
        [f"{v * 1e3:.1f}" for v in ds.wl_nm[:, i].tolist()] for i in range(5)]
    fbg_path = out / "interrogator.csv"
    lines = ["# interrogator export, peaks in pm", "status," + ",".join(header[i] for i in order)]
    lines += ["ok," + ",".join(r) for r in zip(*(cols[i] for i in order))]
    fbg_path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    # The place of each sample's press, held through its rest and after it.
    x, y = ds.x_mm.copy(), ds.y_mm.copy()
    for arr in (x, y):
        ok = np.isfinite(arr)
        idx = np.where(ok, np.arange(arr.size), 0)
        np.maximum.accumulate(idx, out=idx)
        arr[:] = np.where(ok[idx], arr[idx], arr[ok][0])
    drift = drift_ppm * 1e-6
    t0 = float(ds.t_s[0])
    s0 = t0 - 0.5 + offset_s - 0.5 * drift
    s1 = float(ds.t_s[-1]) + 0.5 + offset_s + drift * (float(ds.t_s[-1]) + 0.5 - t0)
    k = np.arange(int(np.floor((s1 - s0) * rate_hz)) + 1)
    jitter = np.clip(rng.normal(0.0, jitter_s, k.size), -0.4 / rate_hz, 0.4 / rate_hz)
    t_stage = s0 + k / rate_hz + jitter
    t_true = t0 + (t_stage - offset_s - t0) / (1.0 + drift)
    force = np.interp(t_true, ds.t_s, ds.force_N, left=0.0, right=0.0)
    j = np.clip(np.searchsorted(ds.t_s, t_true), 0, len(ds) - 1)
    stage_path = out / "stage.tsv"
    rows = [f"{a:.6f}\t{f * 1e3:.2f}\t{px * 1e3:.1f}\t{py * 1e3:.1f}"
            for a, f, px, py in zip(t_stage.tolist(), force.tolist(), x[j].tolist(),
                                    y[j].tolist())]
    stage_path.write_text("clock_s\tFz_mN\tX_um\tY_um\n" + "\n".join(rows) + "\n",
                          encoding="utf-8")
    flags = {"fbg": str(fbg_path), "fbg-unit": "pm",
             "fbg-columns": "t=Timestamp [s],wl1=Ch 1 [pm],wl2=Ch 2 [pm],wl3=Ch 3 [pm],"
                            "wl4=Ch 4 [pm],wlT=Ref [pm]",
             "stage": str(stage_path), "stage-columns": "t=clock_s,force=Fz_mN,x=X_um,y=Y_um",
             "force-unit": "mN", "position-unit": "um"}
    # The same as a --map file beside the logs (its paths relative to it).
    (out / "import.toml").write_text("".join(
        f'{k} = "{Path(v).name if k in ("fbg", "stage") else v}"\n' for k, v in flags.items()),
        encoding="utf-8")
    return flags


#: Named variants: each differs from our simulator's calibration scene in several ways at once.
VARIANTS: dict[str, Spec] = {
    # 1 kHz, moderate noise, drift, 0.5 N contact threshold, 50 N.
    "pad30x40": Spec("pad30x40"),
    # 500 Hz, no temperature change at all (coefficients unidentifiable), 0.2 N threshold.
    "rate500_nodrift": Spec("rate500_nodrift", rate_hz=500.0, noise_pm=8.0, drift=False,
                            contact_threshold_N=0.2),
    # 2 kHz, quiet interrogator, drift, 100 N, 0.1 N threshold, creep.
    "rate2k_100N": Spec("rate2k_100N", rate_hz=2000.0, noise_pm=2.0, force_max_N=100.0,
                        contact_threshold_N=0.1, creep=0.03),
    # Noisy interrogator (15 pm), 1 N threshold, 100 N, CRLF file.
    "noisy15pm": Spec("noisy15pm", noise_pm=15.0, force_max_N=100.0, force_min_N=1.5,
                      contact_threshold_N=1.0, crlf=True),
    # Starts inside a press, rests of 30-80 ms only, strong drift.
    "short_rests": Spec("short_rests", rest_s=(0.03, 0.08), start_in_contact=12, drift_K=3.0,
                        contact_threshold_N=0.3),
    # Strongly hysteretic pad: friction loop 12 % of the load (6 % of full scale between the
    # branches at mid-range) plus 8 % creep; a memoryless estimator can only average them.
    "hysteretic_pad": Spec("hysteretic_pad", friction=0.12, creep=0.08, hold_s=(0.0, 0.4)),
}

#: The fingertip every in-use variant records (device seed 200): 0.3 N contact threshold,
#: thermal coefficients within 4 % of the reference grating's, a temperature grating lagging by
#: 4 s, a wander of 3 pm, a pad that creeps (5 % with a 1 s time constant) and rubs (friction
#: loop 5 % of the load). The variants differ only in protocol: temperature, rests, holds.
IN_USE_FINGERTIP = Spec("in_use", contact_threshold_N=0.3, temp_coeff_spread=0.04,
                        temp_lag_s=4.0, wander_pm=3.0, creep=0.05, creep_s=1.0, friction=0.05,
                        full_scale_N=50.0, device_seed=200)
# 70 presses of 1-4 s rests last about 205 s: a 40 K ramp at 13 K/min (185 s) fits.
_SPARSE = replace(IN_USE_FINGERTIP, drift=False, rest_s=(1.0, 4.0), hold_s=(0.0, 0.15),
                  presses_max=70)

#: Named in-use variants of :data:`IN_USE_FINGERTIP`; ``role`` says what each measures
#: (docs/robustness.md, "Use in the field"). The constant-temperature and ramp logs of one
#: seed hold the same presses, so their force errors compare like for like.
IN_USE_VARIANTS: dict[str, Spec] = {
    # What a user calibrates with: about 1 K of temperature change over the log, presses that
    # hold for 0.15 s or less, no long holds.
    "calib_1K": replace(IN_USE_FINGERTIP, name="calib_1K", role="calibration", drift_K=0.7,
                        hold_s=(0.0, 0.15)),
    # The paper's protocol through a few kelvin (presses of at most 0.2 s): the reference
    # grating then spans about the 30 pm from which the trainer fits temperature coefficients.
    "calib_3K": replace(IN_USE_FINGERTIP, name="calib_3K", role="calibration", drift_K=3.0,
                        hold_s=(0.0, 0.2)),
    # Sparse presses (1-4 s rests) at constant temperature: the reference for the ramps.
    "const_temp": replace(_SPARSE, name="const_temp", role="constant"),
    # The same presses through temperature ramps starting with the first press.
    "ramp20K": replace(_SPARSE, name="ramp20K", role="ramp", drift=True, drift_K=20.0,
                       ramp_K_per_min=10.0),
    "ramp40K": replace(_SPARSE, name="ramp40K", role="ramp", drift=True, drift_K=40.0,
                       ramp_K_per_min=13.0),
    "ramp40K_fast": replace(_SPARSE, name="ramp40K_fast", role="ramp", drift=True,
                            drift_K=40.0, ramp_K_per_min=20.0),
    # Rests of 10-30 s at constant temperature: false contact events at rest.
    "long_rests": replace(IN_USE_FINGERTIP, name="long_rests", role="rest", drift=False,
                          rest_s=(10.0, 30.0), hold_s=(0.0, 0.15), presses_max=10),
    # Sparse presses through a 40 K ramp at 20 K/min, the last one held for 2 minutes: the
    # ramp goes on for about a minute of the grip and then stops under it.
    "ramp_hold": replace(_SPARSE, name="ramp_hold", role="ramp_hold", drift=True, drift_K=40.0,
                         ramp_K_per_min=20.0, last_hold_s=120.0, presses_max=20),
    # Grips held 1.5-6 s at 3-40 N, wandering +-15 % as a hand's grip does, at constant
    # temperature (creep and friction act): the held grips the in-use goals name, within the
    # calibration's 50 N (at its very top every net reads low, docs/robustness.md).
    "held_grips": replace(IN_USE_FINGERTIP, name="held_grips", role="hold", drift=False,
                          rest_s=(0.3, 1.0), hold_s=(1.5, 6.0), force_min_N=3.0,
                          force_max_N=40.0, hold_modulation=0.15, presses_max=40),
    # Light presses of 0.2-3 N at constant temperature, 0.5-2 s apart: the contact decision
    # where the margin is thin.
    "light_presses": replace(_SPARSE, name="light_presses", role="light", force_min_N=0.2,
                             force_max_N=3.0, rest_s=(0.5, 2.0), presses_max=60),
}

#: The in-use family: fingertips that differ from :data:`IN_USE_FINGERTIP` (the member
#: ``in_use``) in exactly one piece of the physics the in-use stages assume, each recorded in
#: the conditions of :data:`FAMILY_VARIANTS`. Every in-use default is chosen by the family's
#: worst member (docs/robustness.md, "The family of fingertips").
FAMILY: dict[str, dict[str, float]] = {
    "in_use": {},                                       # creep 5 % at 1 s, friction 5 %
    "no_creep": {"creep": 0.0},                         # friction alone
    "creep_50ms": {"creep_s": 0.05},
    "creep_5s": {"creep_s": 5.0},
    "viscous": {"creep": 0.0, "friction": 0.0, "viscous_s": 0.004},   # rate-dependent only
    "noise_2pm": {"noise_pm": 2.0},
    "noise_10pm": {"noise_pm": 10.0},
    "ref_no_lag": {"temp_lag_s": 0.0},                  # the reference grating keeps up
    "thermal_8pct": {"temp_coeff_spread": 0.08},        # strain gratings' coefficients +-8 %
}
#: The recordings of each family member: what it is calibrated with and what it is scored on.
FAMILY_VARIANTS = ("calib_1K", "calib_3K", "const_temp", "ramp40K", "long_rests",
                   "held_grips", "light_presses")

#: Every variant the script can write, by name.
ALL_VARIANTS: dict[str, Spec] = {**VARIANTS, **IN_USE_VARIANTS}

#: The file ``main`` writes next to the logs: ``{"presses": n, "variants": {name: {"train":
#: "<name>_A.csv", "other": "<name>_B.csv", "device_seed": s, "temp_coeff_true": [4 floats],
#: "presses": n}}}`` (file names relative to the manifest); in-use variants add ``role`` and,
#: for ramps, ``ramp_K`` and ``ramp_K_per_min``.
MANIFEST = "foreign.json"
#: Presses per log of the variants by default, and of the family (docs/robustness.md's tables
#: were measured on that many: its calibration test split holds 10 presses).
VARIANT_PRESSES = 60
FAMILY_PRESSES = 100
#: The file :func:`write_family` writes: ``{"presses": n, "members": {member: {"manifest":
#: "<member>/foreign.json", "physics": {Spec field: value}}}}``.
FAMILY_MANIFEST = "family.json"


def device_seed(name: str) -> int:
    """The device seed of a variant: its ``device_seed``, else 100 + its index in
    :data:`VARIANTS`."""
    spec = ALL_VARIANTS[name]
    return spec.device_seed if spec.device_seed is not None else 100 + list(VARIANTS).index(name)


def write_logs(out: str | Path, names: list[str] | None = None, presses: int = VARIANT_PRESSES,
               physics: dict[str, float] | None = None) -> Path:
    """Two logs per variant of one device each, and the manifest; returns the manifest's path.
    ``physics``: fields of :class:`Spec` that replace every variant's (a :data:`FAMILY`
    member's)."""
    root = Path(out)
    root.mkdir(parents=True, exist_ok=True)
    entries = {}
    for name in names or list(VARIANTS):
        spec = replace(ALL_VARIANTS[name], **(physics or {}))
        seed = device_seed(name)
        dev = device(spec, seed)
        n_press = min(presses, spec.presses_max or presses)
        for tag, log_seed in (("A", 1), ("B", 2)):
            write_csv(log(dev, log_seed, n_press), root / f"{name}_{tag}.csv", seed=log_seed,
                      crlf=spec.crlf)
        entry = {"train": f"{name}_A.csv", "other": f"{name}_B.csv", "device_seed": seed,
                 "temp_coeff_true": dev.temp_coeff.tolist(), "presses": n_press}
        if spec.role:
            entry["role"] = spec.role
        if spec.ramp_K_per_min > 0:
            entry.update(ramp_K=spec.drift_K, ramp_K_per_min=spec.ramp_K_per_min)
        entries[name] = entry
    path = root / MANIFEST
    extra = {"physics": physics} if physics is not None else {}
    path.write_text(json.dumps({"presses": presses, **extra, "variants": entries}, indent=1)
                    + "\n")
    return path


def write_family(out: str | Path, members: list[str] | None = None,
                 presses: int = FAMILY_PRESSES) -> Path:
    """The logs of :data:`FAMILY_VARIANTS` for each member of :data:`FAMILY` (default all),
    each in ``out/<member>/`` with its manifest, and ``out/family.json`` naming the members
    and their physics; returns that file's path."""
    root = Path(out)
    chosen = members or list(FAMILY)
    for member in chosen:
        print(f"foreign.py: family member {member}", file=sys.stderr)
        write_logs(root / member, list(FAMILY_VARIANTS), presses, FAMILY[member])
    path = root / FAMILY_MANIFEST
    path.write_text(json.dumps({"presses": presses, "members": {
        m: {"manifest": f"{m}/{MANIFEST}", "physics": FAMILY[m]} for m in chosen}}, indent=1)
        + "\n")
    return path


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description="Write foreign calibration logs (two per variant) "
                                 "and foreign.json, for bench/bench_generalisation.py and "
                                 "bench/bench_in_use.py.")
    ap.add_argument("variants", nargs="*", metavar="VARIANT",
                    help=f"variant names (default: all of {', '.join(VARIANTS)}; in use: "
                         f"{', '.join(IN_USE_VARIANTS)})")
    ap.add_argument("--out", required=True, metavar="DIR", help="directory for the logs")
    ap.add_argument("--presses", type=int, default=None,
                    help=f"presses per log (default {VARIANT_PRESSES}; with --family "
                         f"{FAMILY_PRESSES}, what docs/robustness.md measured on)")
    ap.add_argument("--lab-logs", action="store_true",
                    help="write instead, per variant, the raw logs of its first log for "
                         "fbgforce import (DIR/VARIANT/: interrogator.csv, stage.tsv, "
                         "import.toml, clock.json with the true stage clock); the load cell "
                         "with 5 mN of noise (the import labels contact above 50 mN)")
    ap.add_argument("--stage-rate-hz", type=float, default=500.0)
    ap.add_argument("--stage-offset-s", type=float, default=0.1)
    ap.add_argument("--stage-drift-ppm", type=float, default=80.0)
    ap.add_argument("--family", action="store_true",
                    help="write instead the in-use family: for each member (default all of "
                         f"{', '.join(FAMILY)}; name some as VARIANT) the logs "
                         f"{', '.join(FAMILY_VARIANTS)} in DIR/MEMBER/, and DIR/family.json "
                         "(for bench_in_use --family)")
    ap.add_argument("--seed", type=int, default=1,
                    help="with --lab-logs: the seed of the log (its presses and noise; "
                         "default 1, the first log of each variant)")
    args = ap.parse_args(argv)
    if args.presses is None:
        args.presses = FAMILY_PRESSES if args.family else VARIANT_PRESSES
    if args.presses < 2:
        print("foreign.py: --presses must be at least 2", file=sys.stderr)
        return 2
    if args.family:
        unknown = [v for v in args.variants if v not in FAMILY]
        if unknown:
            print(f"foreign.py: unknown family member(s) {', '.join(unknown)}; choose from "
                  f"{', '.join(FAMILY)}", file=sys.stderr)
            return 2
        print(write_family(args.out, args.variants or None, args.presses))
        return 0
    unknown = [v for v in args.variants if v not in ALL_VARIANTS]
    if unknown:
        print(f"foreign.py: unknown variant(s) {', '.join(unknown)}; choose from "
              f"{', '.join(ALL_VARIANTS)}", file=sys.stderr)
        return 2
    if args.lab_logs:
        for name in args.variants or list(VARIANTS):
            spec = replace(ALL_VARIANTS[name], load_cell_noise_N=0.005)
            n_press = min(args.presses, spec.presses_max or args.presses)
            ds = log(device(spec, device_seed(name)), args.seed, n_press)
            where = Path(args.out) / name
            write_lab_logs(ds, where, rate_hz=args.stage_rate_hz, offset_s=args.stage_offset_s,
                           drift_ppm=args.stage_drift_ppm, jitter_s=0.1 / args.stage_rate_hz)
            (where / "clock.json").write_text(json.dumps(
                {"offset_s": args.stage_offset_s, "drift_ppm": args.stage_drift_ppm,
                 "duration_s": float(ds.t_s[-1] - ds.t_s[0]), "presses": n_press}) + "\n")
            print(where)
        return 0
    print(write_logs(args.out, args.variants or None, args.presses))
    return 0


if __name__ == "__main__":
    sys.exit(main())
