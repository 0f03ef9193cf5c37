"""Host timing of the inference engines: single-sample steps and batches, measured alike.

What is timed is always the WHOLE shipped pipeline per sample, raw wavelengths in, estimates
out (tare, temperature compensation, FIR, standardisation, three nets, gating), because that is
what a 1 kHz controller pays. Two call patterns:

- ``single``: one sample per call through the engine's streaming API (a controller's
  interrupt). For numpy and onnxruntime this is :class:`fbgforce.model.floatref.FloatPipeline` fed one
  sample at a time (:func:`float_pipeline`, what :func:`fbgforce.model.floatref.predict` computes); for
  the C runtime, ``Runtime.step``. Includes the Python call overhead, which dominates for every engine here.
- ``batch``: one call over ``n`` samples of a continuous recording (offline evaluation, log
  replay), reported per sample.

Engines are measured in interleaved rounds (A B C A B C ...) so that a slow spell of the shared
machine hits all of them alike, and the figure is the median over every timed call (single) or
every timed batch (batch). Single calls are timed on the wall clock (they are µs long, so the
median discards the few that another process interrupts); batches, which last milliseconds,
in the calling thread's CPU time, so a busy shared machine does not inflate them.
"""
from __future__ import annotations

import statistics
import time
from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np

from fbgforce.model import artifact, floatref


def float_pipeline(model: artifact.HierarchicalModel, baseline_nm: np.ndarray, nets: str = "numpy",
                   model_dir: Any = None) -> floatref.FloatPipeline:
    """The streaming float pipeline the single-sample timings step, one sample per
    :meth:`~fbgforce.model.floatref.FloatPipeline.push`: :class:`fbgforce.model.floatref.FloatPipeline`, the one
    float pipeline every engine and command runs (what :func:`fbgforce.model.floatref.predict` computes).

    Parameters
    ----------
    model
        The float model (causal or no filter; the centred filter needs future samples:
        :class:`~fbgforce.errors.InputError`).
    baseline_nm
        (5,) tare wavelengths.
    nets
        ``"numpy"`` (float64, :func:`fbgforce.model.floatref.numpy_nets`) or ``"onnx"`` (float32
        onnxruntime, :func:`fbgforce.export.onnx_export.onnx_nets`).
    model_dir
        Where an exported ``model.onnx`` may be (for ``nets="onnx"``).
    """
    if nets == "numpy":
        return floatref.FloatPipeline(model, baseline_nm)
    if nets == "onnx":
        from fbgforce.export.onnx_export import onnx_nets

        return floatref.FloatPipeline(model, baseline_nm, nets=onnx_nets(model, model_dir))
    raise ValueError(f"nets must be 'numpy' or 'onnx', not {nets!r}")


@dataclass
class Timer:
    """One engine's timed callables.

    ``single`` is called once per sample with the sample index (it steps a stream);
    ``batch`` is called with ``(start, stop)`` sample indices of the recording.
    """

    name: str
    single: Callable[[int], Any] | None = None
    batch: Callable[[int, int], Any] | None = None
    single_ns: list[int] = field(default_factory=list)
    batch_ns_per_sample: list[float] = field(default_factory=list)


def measure(timers: list[Timer], n_samples: int, *, single_calls: int = 2000,
            batch_size: int = 2000, batch_reps: int = 50, rounds: int = 5,
            warmup: int = 50, batch_target_ms: float = 2.0, min_batch: int = 64
            ) -> dict[str, dict[str, float | None]]:
    """Time every engine in interleaved rounds; return medians in ns per sample.

    Parameters
    ----------
    timers
        The engines; a missing callable is reported as ``None``.
    n_samples
        Length of the recording the callables index into (calls wrap around it).
    single_calls
        Single-sample calls timed per engine in total (split over the rounds).
    batch_size, batch_reps
        Largest number of samples per batch call, and batch calls per engine in total (split
        over the rounds).
    rounds
        Interleaving rounds.
    batch_target_ms, min_batch
        Each engine's batch length is chosen (between ``min_batch`` and ``batch_size``) so
        that one call takes about ``batch_target_ms`` of CPU time: long enough that per-call
        overhead is small against the work, short enough that caches stay warm.

    Returns
    -------
    dict
        ``{name: {"single_ns": median, "single_p99_ns", "batch_ns": median per sample,
        "single_min_ns", "batch_min_ns", "single_calls", "batch_calls", "batch_size"}}``.
    """
    batch_size = max(1, min(batch_size, n_samples))
    per_round_single = max(1, single_calls // rounds)
    per_round_batch = max(1, -(-batch_reps // rounds))
    sizes = _warm_up_and_size_batches(timers, n_samples, warmup, batch_size, min_batch,
                                      batch_target_ms)
    pos_single = {t.name: warmup for t in timers}
    pos_batch = {t.name: 0 for t in timers}
    for _ in range(rounds):
        for t in timers:
            if t.single is not None:
                pos_single[t.name] = _time_single_calls(t, pos_single[t.name], per_round_single,
                                                        n_samples)
            if t.batch is not None:
                pos_batch[t.name] = _time_batches(t, pos_batch[t.name], sizes[t.name],
                                                  per_round_batch, n_samples)
    return {t.name: _summary(t, sizes.get(t.name)) for t in timers}


def _warm_up_and_size_batches(timers: list[Timer], n_samples: int, warmup: int, batch_size: int,
                              min_batch: int, batch_target_ms: float) -> dict[str, int]:
    """Warms every engine up and decides each one's batch length: the number of samples one
    call works through in about ``batch_target_ms`` of CPU time, between ``min_batch`` and
    ``batch_size``, from the fastest of three probe calls."""
    cpu_clock = time.thread_time_ns
    sizes: dict[str, int] = {}
    for t in timers:
        if t.single is not None:
            for i in range(warmup):
                t.single(i % n_samples)
        if t.batch is not None:
            probe = min(batch_size, max(1, min_batch))
            t.batch(0, probe)
            est = []
            for _ in range(3):
                t0 = cpu_clock()
                t.batch(0, probe)
                est.append((cpu_clock() - t0) / probe)
            per_sample = max(min(est), 1.0)
            sizes[t.name] = int(min(batch_size, max(min(min_batch, batch_size),
                                                    batch_target_ms * 1e6 / per_sample)))
    return sizes


def _time_single_calls(t: Timer, k: int, calls: int, n_samples: int) -> int:
    """One round of ``t``'s single-sample calls on the wall clock, from sample ``k`` on
    (wrapping around the recording); returns where the next round continues."""
    clock = time.perf_counter_ns
    fn = t.single
    out = t.single_ns
    for _ in range(calls):
        t0 = clock()
        fn(k % n_samples)
        out.append(clock() - t0)
        k += 1
    return k


def _time_batches(t: Timer, start: int, size: int, calls: int, n_samples: int) -> int:
    """One round of ``t``'s batch calls in CPU time, consecutive batches of ``size`` samples
    from ``start`` on, back to the first sample when a batch would run past the recording's
    end; returns where the next round continues."""
    # Batches are timed in this thread's CPU time: every engine runs on the calling thread
    # (onnxruntime and OpenBLAS set to one thread), so this is the compute time, without the
    # time slices a busy shared machine gives to other processes in the middle of a call.
    cpu_clock = time.thread_time_ns
    for _ in range(calls):
        if start + size > n_samples:
            start = 0
        t0 = cpu_clock()
        t.batch(start, start + size)
        t.batch_ns_per_sample.append((cpu_clock() - t0) / size)
        start += size
    return start


def _summary(t: Timer, batch_size: int | None) -> dict[str, float | None]:
    """The figures one engine reports: medians as the headline, the 99th percentile of the
    single calls and the fastest repetitions beside them."""
    single = sorted(t.single_ns)
    return {
        "single_ns": float(statistics.median(single)) if single else None,
        "single_p99_ns": float(single[min(len(single) - 1, int(0.99 * len(single)))])
        if single else None,
        "batch_ns": float(statistics.median(t.batch_ns_per_sample))
        if t.batch_ns_per_sample else None,
        # The fastest repetition: the figure least disturbed by other processes on a
        # shared machine (the median is the headline; both are reported).
        "single_min_ns": float(single[0]) if single else None,
        "batch_min_ns": float(min(t.batch_ns_per_sample)) if t.batch_ns_per_sample else None,
        "single_calls": len(single),
        "batch_calls": len(t.batch_ns_per_sample),
        "batch_size": batch_size,
    }


def limit_blas_threads(n: int = 1) -> int | None:
    """Set the number of threads of the BLAS numpy uses (OpenBLAS builds), in this process.

    onnxruntime and the C runtime run on one thread here; numpy's OpenBLAS would otherwise use
    every core for each matrix product, which on a shared 2-core machine mostly waits for busy
    cores (measured: 6.5 vs 1.6 µs per sample for a 2000-sample batch under load). Returns the
    previous count, or None when no OpenBLAS is loaded (then nothing changes).
    """
    import ctypes

    try:
        with open("/proc/self/maps") as f:
            paths = {line.split()[-1] for line in f if "openblas" in line.lower()}
    except OSError:
        return None
    for path in sorted(paths):
        try:
            lib = ctypes.CDLL(path)
        except OSError:
            continue
        for prefix in ("scipy_openblas", "openblas"):
            for suffix in ("64_", ""):
                setter = getattr(lib, f"{prefix}_set_num_threads{suffix}", None)
                getter = getattr(lib, f"{prefix}_get_num_threads{suffix}", None)
                if setter is not None and getter is not None:
                    before = int(getter())
                    setter(int(n))
                    return before
    return None


def platform_info() -> dict[str, Any]:
    """The machine and library versions a timing was taken with (for the JSON outputs)."""
    import os
    import platform

    info: dict[str, Any] = {"python": platform.python_version(), "numpy": np.__version__,
                            "machine": platform.machine(), "cpus": os.cpu_count()}
    try:
        with open("/proc/cpuinfo") as f:
            names = [line.split(":", 1)[1].strip() for line in f if line.startswith("model name")]
        if names:
            info["cpu"] = names[0]
    except OSError:
        pass
    try:
        import onnxruntime

        info["onnxruntime"] = onnxruntime.__version__
    except ImportError:
        pass
    return info
