"""ROS 2 goals (docs/ros2.md): live topics at 1 kHz and a 10-minute rosbag2 round trip.

    python -m fbgforce.bench.bench_ros2 [--model MODEL_DIR] [--seconds 60] [--rate 1000]
                                        [--repeat 3] [--modes off,listen,on,inline]
                                        [--cpu N] [--record-minutes 10] [--json FILE]

1. **Live**: a virtual Hyperion plays the ``calibration`` scene on loopback TCP at ``--rate``
   in a child process; this process runs ``fbgforce stream``'s loop (fixed-point C runtime)
   for ``--seconds`` in each mode, the modes alternating ``--repeat`` times so that the
   spread between rounds shows the machine's noise:

   - ``off``: no output, no subscriber;
   - ``listen``: no output, the subscriber below running (what the subscriber's own work
     costs the estimator's step on the same machine);
   - ``on``: ``--publish ros2:///...`` as ``fbgforce stream`` does it, the outputs in the
     publishing process (:class:`~fbgforce.interrogator.publish.PublisherProcess`);
   - ``inline``: the same ROS 2 output called in the estimator's thread
     (:class:`~fbgforce.interrogator.publish.Outputs`), for comparison.

   With ROS 2, a ROS 2-typed subscriber in another child process takes ``NAMESPACE/contact``
   (reliable, keep all it gets). Printed per run: samples, published, received, lost
   (published − received), reordered (a publication counter not above the previous one),
   ``publish_latency_us`` (p50, p99, max: a sample's arrival to the return of its last write)
   and the estimator's step time: the median over the one-sample steps of wall time (``step
   us``), of the thread's CPU time (``step cpu``, which preemption by other processes does
   not inflate) and of the wall time inside ``Runtime.run_raw`` (``runtime``: the C call with
   its cffi buffers; the rest of the step is the Python around it). Per sample, from
   ``/proc`` (all threads of a process): the CPU time of the stream's process, of the
   publishing process and of the subscriber (``cpu us``: stream/publisher/subscriber), and
   the stream's involuntary context switches (``preempt``: per 1000 samples) and the
   publishing process's voluntary ones (``wakes``: its wake-ups per sample). Then per mode
   the medians over the rounds (median, min–max) and, per round, each mode's difference from
   the baselines ``off`` and ``listen`` of the same round and its ratio to ``off``, beside
   the run-to-run noise of the step without publishing: the differences between successive
   ``off`` runs (``--modes off,on,off`` gives two per round).

   ``--cpu N`` runs the stream (the estimator) on CPU N alone and the publishing process,
   the subscriber and the emulator on the other CPUs, as ``fbgforce stream --cpu N`` on a
   host that keeps a core for the estimator.
2. **Record**: ``--record-minutes`` of 1 kHz samples (the calibration scene, repeated) are
   written by the writer ``record --out LOG.mcap`` uses and read back by ``load_dataset``
   (rosbags); printed: messages, file size, write and read time, samples differing.

Cyclone DDS is kept on the loopback interface unless ``CYCLONEDDS_URI`` is set. Without
``--model`` a small model is trained and exported first (about 20 s).
"""
from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import os
import socket
import sys
import tempfile
import time
from collections import Counter
from pathlib import Path
from typing import Any

import numpy as np

from fbgforce.bench.bench_publish import small_model
from fbgforce.errors import InputError
from fbgforce.interrogator.publish import pin_process, separate_cpus

LOOPBACK = ('<CycloneDDS><Domain><General><Interfaces><NetworkInterface name="lo"/>'
            '</Interfaces></General></Domain></CycloneDDS>')


def _subscribe(domain: int, topic: str, ready: Any, stop: Any, result: Any,
               cpus: set[int] | None) -> None:
    """Child process: take every Contact on ``topic``; count received and out-of-order. At
    normal priority even when the bench runs under ``chrt``: the consumer is not part of the
    estimator's real-time loop."""
    if hasattr(os, "sched_setscheduler"):
        os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
    if cpus is not None:
        pin_process(cpus)
    from cyclonedds.core import Policy, Qos
    from cyclonedds.domain import DomainParticipant
    from cyclonedds.sub import DataReader
    from cyclonedds.topic import Topic
    from cyclonedds.util import duration

    from fbgforce.interrogator.ros2 import dds_topic_name
    from fbgforce.interrogator.ros2_dds import Contact

    dp = DomainParticipant(domain)
    qos = Qos(Policy.Reliability.Reliable(duration(seconds=1)),
              Policy.History.KeepLast(1_000_000), Policy.Durability.TransientLocal)
    reader = DataReader(dp, Topic(dp, dds_topic_name(topic), Contact), qos=qos)
    ready.set()
    received = reordered = 0
    last = -1
    while not stop.is_set():
        for m in reader.take(N=10_000):
            if not isinstance(m, Contact):
                continue
            received += 1
            if m.seq <= last:
                reordered += 1
            last = m.seq
        time.sleep(0.002)
    result[:] = [received, reordered]


def _emulate(args: list[str], cpus: set[int] | None) -> None:
    from fbgforce.cli import main

    if cpus is not None:
        pin_process(cpus)
    sys.stdout = open(os.devnull, "w")
    main(["emulate", *args])


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _timed_estimator(model: Path) -> tuple[Any, list[tuple[int, int, int, int]]]:
    """A LiveEstimator whose every push records (samples, wall ns, thread CPU ns, wall ns in
    ``Runtime.run_raw``: the C runtime's call with its cffi buffers; the rest of the step is
    the Python around it)."""
    from fbgforce.interrogator.stream import LiveEstimator

    steps: list[tuple[int, int, int, int]] = []
    in_runtime = [0]

    class Timed(LiveEstimator):
        def __init__(self, model_dir: Path) -> None:
            super().__init__(model_dir)
            run_raw = self._rt.run_raw

            def timed_run_raw(wl: Any) -> Any:
                t0 = time.perf_counter_ns()
                out = run_raw(wl)
                in_runtime[0] += time.perf_counter_ns() - t0
                return out

            self._rt.run_raw = timed_run_raw

        def push(self, wl_fm: Any) -> Any:
            in_runtime[0] = 0
            w0, c0 = time.perf_counter_ns(), time.thread_time_ns()
            out = super().push(wl_fm)
            if len(out["contact"]):
                steps.append((len(out["contact"]), time.perf_counter_ns() - w0,
                              time.thread_time_ns() - c0, in_runtime[0]))
            return out

    return Timed(model), steps


MODES = ("off", "listen", "on", "inline")


def process_usage(pid: int) -> np.ndarray | None:
    """CPU time (ns), voluntary and involuntary context switches of process ``pid``, summed
    over its threads (``/proc/PID/task``); ``None`` where there is no such process."""
    total = np.zeros(3, dtype=np.int64)
    tick_ns = 1_000_000_000 // os.sysconf("SC_CLK_TCK")
    try:
        tasks = os.listdir(f"/proc/{pid}/task")
    except FileNotFoundError:
        return None
    for task in tasks:
        try:
            stat = Path(f"/proc/{pid}/task/{task}/stat").read_text().rsplit(")", 1)[1].split()
            status = Path(f"/proc/{pid}/task/{task}/status").read_text().splitlines()
        except FileNotFoundError:  # a thread that ended meanwhile
            continue
        switches = dict(line.split(":") for line in status if "ctxt_switches" in line)
        total += (tick_ns * (int(stat[11]) + int(stat[12])),
                  int(switches["voluntary_ctxt_switches"]),
                  int(switches["nonvoluntary_ctxt_switches"]))
    return total


class _Accounted:
    """A publication whose :meth:`finish` first takes the processes' usage (the publishing
    process is gone after it)."""

    def __init__(self, publication: Any, take: Any) -> None:
        self.publication, self.take = publication, take

    def publish(self, records: np.ndarray) -> None:
        self.publication.publish(records)

    def status(self, snapshot: Any) -> None:
        self.publication.status(snapshot)

    def finish(self) -> dict[str, Any]:
        self.take()
        return self.publication.finish()


def run_live(model: Path, seconds: float, rate: float, mode: str,
             cpus: set[int] | None = None) -> dict[str, Any]:
    """One live run in ``mode`` (:data:`MODES`); the row printed for it. ``cpus``: where
    the emulator, the subscriber and the publishing process run (``--cpu``)."""
    from fbgforce.interrogator.hyperion import HyperionReader
    from fbgforce.interrogator.publish import Outputs, PublisherProcess
    from fbgforce.interrogator.ros2_dds import Ros2Publisher
    from fbgforce.interrogator.stream import run_stream

    ctx = mp.get_context("spawn")
    cmd_port, stream_port = _free_port(), _free_port()
    emu = ctx.Process(target=_emulate, args=([
        "--scene", "calibration", "--seed", "0", "--rate", str(rate), "--duration",
        str(seconds + 1.0), "--linger", "0.5", "--protocol", "hyperion", "--command-port",
        str(cmd_port), "--stream-port", str(stream_port)], cpus))
    sub = None
    domain = 1 + os.getpid() % 200
    namespace = f"/fbgforce_bench_{os.getpid()}_{mode}"
    url = f"ros2://{namespace}?domain={domain}"
    if mode != "off":
        ready, stop, result = ctx.Event(), ctx.Event(), ctx.Array("q", 2)
        sub = ctx.Process(target=_subscribe, args=(domain, namespace + "/contact", ready, stop,
                                                   result, cpus))
        sub.start()
        ready.wait(30)
    publication: Any = (None if mode in ("off", "listen") else
                        PublisherProcess([url], cpus=cpus) if mode == "on" else
                        Outputs([Ros2Publisher(url)]))
    pids = {"stream": os.getpid(), "subscriber": None if sub is None else sub.pid,
            "publisher": publication._child.pid if mode == "on" else None}
    usage: dict[str, list[Any]] = {k: [] for k, pid in pids.items() if pid is not None}

    def take_usage() -> None:
        for k in usage:
            usage[k].append(process_usage(pids[k]))  # type: ignore[arg-type]

    emu.start()
    reader = HyperionReader(f"hyperion://127.0.0.1:{cmd_port}?stream={stream_port}")
    estimator, steps = _timed_estimator(model)
    take_usage()
    try:
        summary = run_stream(reader, estimator, duration=seconds, start_timeout=60,
                             idle_timeout=2, status=False,
                             publication=None if publication is None else
                             _Accounted(publication, take_usage))
    finally:
        reader.close()
        emu.join(30)
    if publication is None:
        take_usage()
    single = np.array([(w, c, r) for k, w, c, r in steps if k == 1], dtype=np.float64) / 1000.0
    lat = summary.get("publish_latency_us", dict.fromkeys(("p50", "p99", "max"), "-"))
    row: dict[str, Any] = {
        "mode": mode, "samples": summary["samples"], "rate_hz": summary["rate_hz"],
        "lost_frames": summary["lost_frames"], "p50_us": lat["p50"], "p99_us": lat["p99"],
        "max_us": lat["max"], "compute_us_per_sample": summary["compute_us_per_sample"],
        "step_wall_us_median": round(float(np.median(single[:, 0])), 1),
        "step_cpu_us_median": round(float(np.median(single[:, 1])), 1),
        "runtime_us_median": round(float(np.median(single[:, 2])), 1),
        "single_sample_steps": len(single),
        "batch_sizes": dict(sorted(Counter(k for k, *_ in steps).most_common(4)))}
    per_sample = 1.0 / max(summary["received"], 1)
    for k, (start, end) in ((k, v) for k, v in usage.items() if len(v) == 2):
        if start is not None and end is not None:
            cpu_ns, voluntary, involuntary = (end - start).tolist()
            row[f"{k}_cpu_us_per_sample"] = round(cpu_ns / 1000.0 * per_sample, 1)
            row[f"{k}_voluntary_switches_per_sample"] = round(voluntary * per_sample, 3)
            row[f"{k}_involuntary_switches_per_sample"] = round(involuntary * per_sample, 3)
    if sub is not None:
        time.sleep(1.0)  # let the subscriber drain
        stop.set()
        sub.join(30)
    if publication is not None:
        pub = summary["published"][0]
        received, reordered = list(result)
        row.update(published=pub["sent"], send_errors=pub["send_errors"], received=received,
                   lost=pub["sent"] - received, reordered=reordered,
                   publish_dropped=summary["publish_dropped"])
        publication.close()
    return row


BASELINES = ("off", "listen")
STEP_KEYS = ("step_wall_us_median", "step_cpu_us_median", "runtime_us_median")


def _spread(values: Any, digits: int = 1) -> list[float]:
    """Median, min and max, rounded."""
    v = np.asarray(values, dtype=np.float64)
    return [round(float(np.median(v)), digits), round(float(v.min()), digits),
            round(float(v.max()), digits)]


def off_noise(live: list[dict[str, Any]]) -> dict[str, Any]:
    """The run-to-run noise of the step without publishing: the differences between
    successive ``off`` runs' step medians (``step_wall_us_differences``) and the largest of
    them in size (``largest_us``; ``None`` with fewer than two ``off`` runs)."""
    noise = np.diff([r["step_wall_us_median"] for r in live if r["mode"] == "off"])
    return {"step_wall_us_differences": [round(float(d), 1) for d in noise],
            "largest_us": round(float(np.abs(noise).max()), 1) if len(noise) else None}


def step_summary(live: list[dict[str, Any]], modes: list[str]) -> dict[str, Any]:
    """Per mode, the rounds' step medians (median, min, max), its per-round difference from
    each baseline mode run before it (``minus_off``, ``minus_listen``: median, min, max) and
    its per-round ratio to ``off`` (``step_wall_ratio_to_off``), wall and thread CPU; and
    ``within_noise``: whether the median difference from ``off`` is no larger than the
    largest run-to-run difference of ``off`` itself (:func:`off_noise`)."""
    out: dict[str, Any] = {}
    largest = off_noise(live)["largest_us"]

    def base_row(base: str, rnd: int) -> dict[str, Any] | None:
        return next((r for r in live if r["mode"] == base and r["round"] == rnd), None)

    for mode in dict.fromkeys(modes):
        rows = [r for r in live if r["mode"] == mode]
        entry: dict[str, Any] = {}
        # A baseline compares with the modes after it: listen with off, the rest with both.
        later = BASELINES[:BASELINES.index(mode)] if mode in BASELINES else BASELINES
        for key in STEP_KEYS:
            entry[key] = _spread([r[key] for r in rows])
            for base in (b for b in later if b in modes):
                pairs = [(r, base_row(base, r["round"])) for r in rows]
                entry[key.replace("median", f"minus_{base}")] = _spread(
                    [r[key] - b[key] for r, b in pairs if b is not None])
        if mode != "off" and "off" in modes:
            pairs = [(r, base_row("off", r["round"])) for r in rows]
            entry["step_wall_ratio_to_off"] = _spread(
                [r["step_wall_us_median"] / b["step_wall_us_median"] for r, b in pairs
                 if b is not None], 3)
            if largest is not None:
                entry["within_noise"] = abs(entry["step_wall_us_minus_off"][0]) <= largest
        out[mode] = entry
    return out


def run_record(minutes: float, tmp: Path) -> dict[str, Any]:
    from fbgforce import sim
    from fbgforce.recordings import dataset
    from fbgforce.interrogator.mcaplog import stamps_for, write_log
    from fbgforce.interrogator.protocol import nm_to_fm

    scene = sim.simulate("calibration", seed=0)
    n = int(round(minutes * 60 * 1000))
    idx = np.arange(n) % len(scene)
    t_s = np.arange(n) / 1000.0
    wl_fm = nm_to_fm(scene.wl_nm[idx])
    press = scene.press_id[idx] + (np.arange(n) // len(scene)) * (scene.press_id.max() + 1)
    stage = {"contact": scene.contact[idx], "force_N": scene.force_N[idx],
             "x_mm": scene.x_mm[idx], "y_mm": scene.y_mm[idx], "press_id": press}
    out = tmp / "ten_minutes.mcap"
    t0 = time.perf_counter()
    counts = write_log(out, stamp_ns=stamps_for(t_s, 1_700_000_000_000_000, 0),
                       sample_seq=np.arange(n), wl_fm=wl_fm, stage=stage)
    t1 = time.perf_counter()
    ds = dataset.load(out)
    t2 = time.perf_counter()
    ok = (np.rint(ds.wl_nm * 1e6).astype(np.int64) == wl_fm).all(axis=1)
    ok &= np.abs(ds.t_s - t_s) < 1e-9
    ok &= (ds.contact == stage["contact"]) & (ds.force_N == stage["force_N"])
    ok &= ds.press_id == press
    for key in ("x_mm", "y_mm"):
        both = np.isnan(getattr(ds, key)) & np.isnan(stage[key])
        ok &= both | (np.abs(getattr(ds, key) - stage[key]) < 1e-9)
    return {"samples": n, "messages": sum(counts.values()), "read_back": len(ds),
            "differing": int((~ok).sum()) + abs(n - len(ds)),
            "mbytes": round(out.stat().st_size / 1e6, 1), "write_s": round(t1 - t0, 1),
            "read_s": round(t2 - t1, 1)}


def main(argv: list[str] | None = None) -> int:
    ap = _parser()
    args = ap.parse_args(argv)
    modes = [m for m in args.modes.split(",") if m]
    if not modes or set(modes) - set(MODES):
        ap.error(f"--modes: a comma-separated list of {', '.join(MODES)}")
    os.environ.setdefault("CYCLONEDDS_URI", LOOPBACK)
    others = None
    if args.cpu is not None:
        try:
            others = separate_cpus(args.cpu, publishing=True)
        except InputError as exc:
            ap.error(str(exc))
    results: dict[str, Any] = {"load_average_start": os.getloadavg()[0], "cpu": args.cpu,
                               "other_cpus": None if others is None else sorted(others)}
    with tempfile.TemporaryDirectory() as tmp:
        model = args.model or small_model(Path(tmp))
        live = _live_rounds(model, args, modes, others)
        results["live"] = live
        if live:
            results["step"] = step_summary(live, modes)
            results["step_noise"] = off_noise(live)
            _print_step_summary(results["step"], results["step_noise"])
        if args.record_minutes > 0:
            rec = run_record(args.record_minutes, Path(tmp))
            results["record"] = rec
            print(f"record: {rec['samples']} samples, {rec['messages']} messages, "
                  f"{rec['mbytes']} MB, written in {rec['write_s']} s, read back "
                  f"{rec['read_back']} in {rec['read_s']} s, {rec['differing']} differing",
                  flush=True)
    results["load_average_end"] = os.getloadavg()[0]
    print(f"load average (1 min): {results['load_average_start']:.1f} at start, "
          f"{results['load_average_end']:.1f} at end")
    if args.json:
        Path(args.json).write_text(json.dumps(results, indent=1))
    return 0


def _parser() -> argparse.ArgumentParser:
    """The bench's options (module docstring)."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--model", type=Path, help="exported model directory (default: train one)")
    ap.add_argument("--seconds", type=float, default=60.0)
    ap.add_argument("--rate", type=float, default=1000.0)
    ap.add_argument("--record-minutes", type=float, default=10.0)
    ap.add_argument("--repeat", type=int, default=3, help="rounds of live runs, one per mode")
    ap.add_argument("--modes", default=",".join(MODES),
                    help=f"live modes in each round, comma-separated ({', '.join(MODES)})")
    ap.add_argument("--cpu", type=int, metavar="N",
                    help="run the stream on CPU N alone, everything else on the other CPUs")
    ap.add_argument("--json", metavar="FILE", help="also write the results as JSON")
    return ap


def _live_rounds(model: Path, args: argparse.Namespace, modes: list[str],
                 others: set[int] | None) -> list[dict[str, Any]]:
    """The live runs: ``--repeat`` rounds, each running every mode once in the order given
    (so the rounds' spread shows the machine's noise), each run printed as it ends."""
    print(f"{'round':>5} {'mode':<6} {'samples':>8} {'published':>9} {'received':>9} "
          f"{'lost':>5} {'reord':>5} {'p50 us':>7} {'p99 us':>8} {'max us':>8} "
          f"{'step us':>7} {'step cpu':>8} {'runtime':>7} {'cpu us':>15} {'preempt':>7} "
          f"{'wakes':>5} {'load':>5}")
    live = []
    for i in range(args.repeat):
        for mode in modes:
            r = run_live(model, args.seconds, args.rate, mode, others)
            r["round"] = i + 1
            r["load_average"] = os.getloadavg()[0]
            live.append(r)
            _print_live_row(r)
    return live


def _print_live_row(r: dict[str, Any]) -> None:
    """One live run's line of the table, a dash where the mode has no such figure."""
    dash = "-"
    cpu = "/".join(f"{r[f'{k}_cpu_us_per_sample']:.0f}"
                   if f"{k}_cpu_us_per_sample" in r else dash
                   for k in ("stream", "publisher", "subscriber"))
    preempt = 1000 * r.get("stream_involuntary_switches_per_sample", 0)
    print(f"{r['round']:>5} {r['mode']:<6} {r['samples']:>8} "
          f"{r.get('published', dash):>9} {r.get('received', dash):>9} "
          f"{r.get('lost', dash):>5} {r.get('reordered', dash):>5} "
          f"{r['p50_us']:>7} {r['p99_us']:>8} {r['max_us']:>8} "
          f"{r['step_wall_us_median']:>7} {r['step_cpu_us_median']:>8} "
          f"{r['runtime_us_median']:>7} {cpu:>15} {preempt:>7.0f} "
          f"{r.get('publisher_voluntary_switches_per_sample', dash):>5} "
          f"{r['load_average']:>5.1f}", flush=True)


def _print_step_summary(step: dict[str, Any], noise: dict[str, Any]) -> None:
    """Per mode, the step time over the rounds and its difference from the baselines; then,
    when there are two ``off`` runs to tell the noise by, whether each mode's difference
    from ``off`` lies within it."""
    print("step time, median over rounds [min, max] (us): wall | thread CPU | "
          "in the runtime's call")
    for mode, e in step.items():
        line = (f"  {mode:<6} {e['step_wall_us_median']} | {e['step_cpu_us_median']} | "
                f"{e['runtime_us_median']}")
        for base in BASELINES:
            if f"step_wall_us_minus_{base}" in e:
                line += (f"   minus {base}, per round: "
                         f"{e[f'step_wall_us_minus_{base}']} | "
                         f"{e[f'step_cpu_us_minus_{base}']} | "
                         f"{e[f'runtime_us_minus_{base}']}")
        print(line)
    if noise["largest_us"] is not None:
        print(f"step without publishing, run to run (successive off runs): "
              f"{noise['step_wall_us_differences']} us")
        for mode, e in step.items():
            if "step_wall_ratio_to_off" in e:
                print(f"  {mode:<6} minus off {e['step_wall_us_minus_off']} us, "
                      f"ratio {e['step_wall_ratio_to_off']}: "
                      f"{'within' if e['within_noise'] else 'beyond'} the noise "
                      f"(largest {noise['largest_us']} us)")


if __name__ == "__main__":
    sys.exit(main())
