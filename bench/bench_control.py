"""Tare, reset and health while streaming: the goals of docs/serial.md, "Tare, reset and health
while streaming", measured end to end (loopback only).

    python -m fbgforce.bench.bench_control [--model MODEL_DIR] [--commands 10000]
                                           [--garbage 100000] [--rounds 3] [--seconds 8]
                                           [--json FILE]

1. **Preload**: a virtual Hyperion plays, at 1 kHz, the smoke scene's unloaded fingertip (its
   noise, seed 5), then a +60 pm step on every strain grating (a re-mounted pad), then the
   scene's press nearest to 11 N (the step kept), then rest. ``fbgforce stream --control
   udp:// --publish ros2:///bench`` runs on it; the bench sends a tare over UDP 1.5 s after
   the step, a reset after the press, and stops the instrument (SIGSTOP) for 3 s at the end.
   Printed: the rest force before the step (the model's own, p99 of |F|), the force the step
   reads before the tare (median, and the share of samples in contact), the tare's answer and the time from its request to its answer, the rest force
   after the tare (99th percentile of |F| from the window's end to the press), the press's
   force RMSE against the scene's load cell (beside the same press without the step run
   offline, tared at the start: what the model reads at best; and with the step but no tare,
   offline: what the tare saves; the at-rest tracker's offset when the tare was asked for),
   the reset's answer, delay and rest p99 after it,
   and from ``/diagnostics`` (a DDS reader in this process): the period of the records
   (median, min, max), the time from the instrument's silence to the first WARN or ERROR
   record and from its return to the first OK one.
2. **Commands**: a stream with ``--tare-samples 1`` on a 5 kHz playback; a client sends
   ``--commands`` tares one after the other, each sent again every 20 ms until its final
   answer, and drops 5 % of its sends and 5 % of the answers it receives on purpose (so
   repeats and lost answers happen); meanwhile another socket sends ``--garbage`` random
   datagrams (random lengths 0..200 bytes, and commands with one bit flipped) to the control
   port. Printed: commands answered DONE, tares the stream applied (its summary), commands
   lost (never answered) and applied twice (applied − answered), repeats the stream answered
   again, garbage datagrams the stream counted as bad, the stream's exit code; and the control
   decoder on ``--garbage`` random datagrams in this process (exceptions).
3. **Step time**: ``--rounds`` rounds of ``--seconds`` each alternating a stream without and
   with ``--control`` (health runs in both: it is part of the loop) on a 1 kHz playback;
   printed per run the estimator's compute time per sample (``compute_us_per_sample``) and
   the stream process's CPU time per sample, then the difference between the modes beside
   the run-to-run noise (the spread of each mode's runs), as bench_ros2 judges it.

Without ``--model`` a small model is trained on the smoke scene (seed 0) and exported first
(about 20 s).
"""
from __future__ import annotations

import argparse
import contextlib
import dataclasses
import json
import os
import resource
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any, Callable

import numpy as np

LOOPBACK = ('<CycloneDDS><Domain><General><Interfaces><NetworkInterface name="lo"/>'
            '</Interfaces></General></Domain></CycloneDDS>')
STEP_PM = 60.0
#: The smoke scene's (seed 5) press nearest to 11 N, and a rest before it.
PRESS = (3332, 3897)
PRESS_REST = (3120, 3320)


def _free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _emulator(data: Path, rate: float, *extra: str) -> tuple[subprocess.Popen, str]:
    proc = subprocess.Popen([sys.executable, "-m", "fbgforce.cli", "emulate", "--data", str(data),
                             "--rate", str(rate), "--protocol", "hyperion", "--command-port", "0",
                             "--stream-port", "0", "--linger", "0.5", *extra],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    assert proc.stdout is not None
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline:
        line = proc.stdout.readline()
        if line.startswith("interrogator:"):
            return proc, line.split(":", 1)[1].strip()
    proc.kill()
    raise RuntimeError(f"the emulator did not start: {proc.communicate()[1][-2000:]}")


def _end(proc: subprocess.Popen) -> None:
    if proc.poll() is None:
        os.kill(proc.pid, signal.SIGCONT)
        proc.kill()
    proc.communicate()


def preload_playback(tmp: Path, seconds_rest: float = 5.0) -> tuple[Path, dict[str, Any]]:
    """The preload scenario as a dataset file, and where its parts are (sample indices)."""
    from fbgforce import sim
    from fbgforce.recordings import dataset

    scene = sim.simulate("smoke", seed=5)
    rest = scene.wl_nm[:200]
    rng = np.random.default_rng(5)
    n_rest = int(seconds_rest * 1000)

    def noise(n: int) -> np.ndarray:
        return rest.mean(axis=0) + rng.normal(0.0, rest.std(axis=0), (n, 5))

    press = scene.wl_nm[PRESS[0]:PRESS[1]] - scene.wl_nm[PRESS_REST[0]:PRESS_REST[1]].mean(axis=0)
    wl = np.concatenate([noise(n_rest), press + rest.mean(axis=0), noise(2 * n_rest)])
    force = np.concatenate([np.zeros(n_rest), scene.force_N[PRESS[0]:PRESS[1]],
                            np.zeros(2 * n_rest)])
    step = 1000
    wl[step:, :4] += STEP_PM / 1000.0
    n = len(wl)
    base = scene.subset(np.arange(n))
    ds = dataclasses.replace(base, wl_nm=wl, force_N=force, contact=force > 0,
                             x_mm=np.where(force > 0, 10.0, np.nan),
                             y_mm=np.where(force > 0, 13.0, np.nan))
    path = tmp / "preload.csv"
    dataset.save(ds, path)
    clean = wl.copy()
    clean[step:, :4] -= STEP_PM / 1000.0
    return path, {"n": n, "step": step, "press": (n_rest, n_rest + PRESS[1] - PRESS[0]),
                  "force": force, "clean_wl_nm": clean}


def _diagnostics_reader(domain: int, got: list, stop: threading.Event) -> None:
    from cyclonedds.core import Policy, Qos
    from cyclonedds.domain import DomainParticipant
    from cyclonedds.sub import DataReader
    from cyclonedds.topic import Topic
    from cyclonedds.util import duration

    from fbgforce.interrogator.ros2_dds import DiagnosticArray

    dp = DomainParticipant(domain)
    rd = DataReader(dp, Topic(dp, "rt/diagnostics", DiagnosticArray), qos=Qos(
        Policy.Reliability.Reliable(duration(seconds=1)), Policy.History.KeepLast(100)))
    while not stop.is_set():
        for m in rd.take(N=100):
            if isinstance(m, DiagnosticArray):
                s = m.status[0]
                got.append((time.monotonic(), int(s.level), s.message,
                            {kv.key: kv.value for kv in s.values}))
        time.sleep(0.005)


def run_preload(model: Path, tmp: Path) -> dict[str, Any]:
    """The preload run (module docstring, 1.)."""
    from fbgforce.cli import main as cli_main
    from fbgforce.interrogator import stream as S

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "examples" / "udp_receiver"))
    import control as client_mod  # type: ignore[import-not-found]

    data, where = preload_playback(tmp)
    domain = 1 + os.getpid() % 200
    os.environ.setdefault("CYCLONEDDS_URI", LOOPBACK)
    diags: list = []
    stop = threading.Event()
    reader = threading.Thread(target=_diagnostics_reader, args=(domain, diags, stop), daemon=True)
    reader.start()
    port = _free_udp_port()
    sink = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sink.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1 << 22)
    sink.bind(("127.0.0.1", 0))
    sink.settimeout(10)
    out_csv = tmp / "preload_estimates.csv"
    em, source = _emulator(data, 1000.0)
    res: dict[str, Any] = {}
    errors: list[BaseException] = []
    ctl = threading.Thread(target=_preload_controller,
                           args=(client_mod, port, sink, where, em, res, errors), daemon=True)
    ctl.start()
    try:
        code = _stream_preload(cli_main, source, model, where["n"], port, sink, domain, out_csv)
        ctl.join(30)
        time.sleep(1.5)
    finally:
        stop.set()
        sink.close()
        _end(em)
    if errors:
        raise errors[0]
    return _preload_result(code, S.load_estimates(out_csv), where, res, diags, client_mod, model)


def _wait_for_sample(sink: socket.socket, sample: int) -> None:
    """Returns once the stream has published sample ``sample`` (or a later one) to ``sink``."""
    from fbgforce.interrogator.publish import decode_datagram

    while True:
        rec = decode_datagram(sink.recv(256))
        if rec is not None and int(rec["sample_seq"]) >= sample:
            return


def _preload_controller(client_mod: Any, port: int, sink: socket.socket, where: dict[str, Any],
                        em: subprocess.Popen, res: dict[str, Any],
                        errors: list[BaseException]) -> None:
    """The operator of the preload run, paced by the published samples: a tare 1.5 s after
    the step, a reset after the press, then the instrument stopped for 3 s near the end.
    Each command's answer, delay and send time go to ``res``, with when the silence began and
    ended; an exception goes to ``errors`` for the main thread to raise."""
    try:
        client = client_mod.Client("127.0.0.1", port)
        _wait_for_sample(sink, where["step"] + 1500)
        t0 = time.monotonic()
        ack = client.send("tare")
        res["tare"] = (ack, time.monotonic() - t0, t0)
        _wait_for_sample(sink, where["press"][1] + 800)
        t0 = time.monotonic()
        ack = client.send("reset")
        res["reset"] = (ack, time.monotonic() - t0, t0)
        _wait_for_sample(sink, where["n"] - 4500)
        res["silence"] = time.monotonic()
        os.kill(em.pid, signal.SIGSTOP)
        time.sleep(3.0)
        res["back"] = time.monotonic()
        os.kill(em.pid, signal.SIGCONT)
    except BaseException as exc:
        errors.append(exc)


def _stream_preload(cli_main: Callable[[list[str]], int], source: str, model: Path,
                    samples: int, port: int, sink: socket.socket, domain: int,
                    out_csv: Path) -> int:
    """``fbgforce stream`` on the preload playback, in this process and quiet: commands on
    UDP ``port``, estimates to ``sink`` and ``out_csv``, diagnostics on DDS ``domain``;
    returns its exit code."""
    with open(os.devnull, "w") as quiet, contextlib.redirect_stdout(quiet):
        return cli_main(["stream", "--source", source, "--model", str(model), "--samples",
                         str(samples), "--idle-timeout", "10", "--control",
                         f"udp://127.0.0.1:{port}", "--publish",
                         f"udp://127.0.0.1:{sink.getsockname()[1]}", "--publish",
                         f"ros2:///bench?domain={domain}", "--out", str(out_csv),
                         "--start-timeout", "30", "--quiet", "--json"])


def _offline_press(model: Path, where: dict[str, Any]) -> tuple[float, np.ndarray, float]:
    """What the model reads offline: the press RMSE without the step (tared on the first 200
    samples: the best it reads), and the forces and press RMSE with the step and no tare
    after it (the first tare only: what the tare saves)."""
    from fbgforce.pybind import Runtime

    p0, p1 = where["press"]
    rt = Runtime(model)
    rt.tare(where["clean_wl_nm"][:200])
    clean = rt.run(where["clean_wl_nm"])["force_N"][p0:p1]
    rmse_clean = float(np.sqrt(np.mean((clean - where["force"][p0:p1]) ** 2)))
    stepped = where["clean_wl_nm"].copy()
    stepped[where["step"]:, :4] += STEP_PM / 1000.0
    rt = Runtime(model)
    rt.tare(stepped[:200])
    untared = rt.run(stepped)["force_N"]
    rmse_untared = float(np.sqrt(np.mean((untared[p0:p1] - where["force"][p0:p1]) ** 2)))
    return rmse_clean, untared, rmse_untared


def _diagnostics_figures(diags: list, res: dict[str, Any]) -> dict[str, Any]:
    """What ``/diagnostics`` said: how many records, their period, whether they carry the
    lost-samples key, how soon the instrument's silence turned them WARN or ERROR and its
    return turned them OK again, and the worst level during the silence."""
    times = np.array([d[0] for d in diags])
    levels = [d[1] for d in diags]
    first_bad = next((t for t, lv, _, _ in diags if t >= res["silence"] and lv >= 1), None)
    first_ok = next((t for t, lv, _, _ in diags if t >= res["back"] and lv == 0), None)
    return {
        "diagnostics": len(diags),
        "diag_period_s": [float(np.median(np.diff(times))), float(np.diff(times).min()),
                          float(np.diff(times).max())] if len(times) > 2 else None,
        "diag_lost_key": bool(diags) and "samples_lost" in diags[-1][3],
        "silence_to_warn_s": None if first_bad is None else round(first_bad - res["silence"], 3),
        "silence_level": max(levels[i] for i, t in enumerate(times) if res["silence"] <= t
                             <= res["back"]) if diags else None,
        "back_to_ok_s": None if first_ok is None else round(first_ok - res["back"], 3),
    }


def _preload_result(code: int, est: dict[str, np.ndarray], where: dict[str, Any],
                    res: dict[str, Any], diags: list, client_mod: Any, model: Path
                    ) -> dict[str, Any]:
    """The preload figures (module docstring, part 1) from the stream's estimates, the
    commands' answers, the offline references and the diagnostics; the windows each rest
    figure is taken over keep clear of the tare's and the reset's own windows."""
    seq = est["seq"]
    force = est["force_N"]
    tare_ack, tare_s, tare_t = res["tare"]
    reset_ack, reset_s, reset_t = res["reset"]
    step, (p0, p1) = where["step"], where["press"]
    # The tare is sent when sample step + 1500 is out and answered some 250 samples later:
    # rest from 600 samples after that on is after its window for sure.
    tare_rest = force[(seq > step + 2100) & (seq < p0)]
    before = force[(seq > step + 100) & (seq < step + 1400)]
    contact_before = est["contact"][(seq > step + 100) & (seq < step + 1400)]
    in_press = (seq >= p0) & (seq < p1)
    truth = where["force"][seq[in_press]]
    rmse = float(np.sqrt(np.mean((force[in_press] - truth) ** 2)))
    rmse_clean, untared, rmse_untared = _offline_press(model, where)
    # What the at-rest tracker had taken of the step when the tare was asked for.
    offset = [float(d[3]["tracker_offset_pm"]) for d in diags if d[0] <= tare_t]
    reset_rest = force[(seq > p1 + 1400) & (seq < where["n"] - 4600)]
    # The model's own rest before the step (after the stream's first tare): what a tare can
    # give back at best.
    own_rest = force[(seq > 300) & (seq < step)]
    return {
        "exit_code": code,
        "step_force_median_N": float(np.median(before)),
        "step_contact_share": float(np.mean(contact_before)),
        "tare": {"result": client_mod.RESULTS[tare_ack.result], "message": tare_ack.message,
                 "answered_s": round(tare_s, 3)},
        "rest_before_step_p99_N": float(np.percentile(np.abs(own_rest), 99)),
        "rest_after_tare_p99_N": float(np.percentile(np.abs(tare_rest), 99)),
        "rest_after_tare_n": int(len(tare_rest)),
        "press_peak_N": float(truth.max()), "press_rmse_N": rmse,
        "press_rmse_no_step_offline_N": rmse_clean,
        "press_rmse_step_untared_offline_N": rmse_untared,
        "untared_rest_after_step_p99_N": float(np.percentile(np.abs(
            untared[step + 2100:p0]), 99)),
        "tracker_offset_at_tare_pm": offset[-1] if offset else None,
        "reset": {"result": client_mod.RESULTS[reset_ack.result],
                  "message": reset_ack.message, "answered_s": round(reset_s, 3)},
        "rest_after_reset_p99_N": float(np.percentile(np.abs(reset_rest), 99)),
        "rest_after_reset_n": int(len(reset_rest)),
        **_diagnostics_figures(diags, res),
        "reset_request_t": reset_t,
    }


def _lossy_client(port: int, n: int, drop: float, seed: int) -> dict[str, int]:
    """Sends ``n`` tares one after the other, each again every 20 ms until its final answer,
    dropping ``drop`` of its sends and of the answers it receives."""
    from fbgforce.interrogator import control as C

    rng = np.random.default_rng(seed)
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    session = int(rng.integers(0, 2**32))
    counts = {"sent": 0, "dropped_sends": 0, "dropped_answers": 0, "done": 0, "other": 0,
              "lost": 0, "answers_seen": 0}
    for seq in range(1, n + 1):
        data = C.encode_command(session, seq, C.TARE)
        deadline = time.monotonic() + 10
        final = None
        while final is None and time.monotonic() < deadline:
            if rng.random() < drop:
                counts["dropped_sends"] += 1
            else:
                sock.sendto(data, ("127.0.0.1", port))
                counts["sent"] += 1
            end = time.monotonic() + 0.02
            while final is None:
                left = end - time.monotonic()
                if left <= 0:
                    break
                sock.settimeout(left)
                try:
                    ack = C.decode_ack(sock.recv(512))
                except socket.timeout:
                    break
                if ack is None or int(ack["seq"]) != seq:
                    continue
                counts["answers_seen"] += 1
                if rng.random() < drop:
                    counts["dropped_answers"] += 1
                    continue
                if int(ack["result"]) != C.PENDING:
                    final = int(ack["result"])
        if final is None:
            counts["lost"] += 1
        elif final == C.DONE:
            counts["done"] += 1
        else:
            counts["other"] += 1
    sock.close()
    return counts


def _garbage(port: int, n: int, seed: int, counts: dict[str, int]) -> None:
    from fbgforce.interrogator import control as C

    rng = np.random.default_rng(seed)
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    for i in range(n):
        if i % 2:
            g = rng.bytes(int(rng.integers(0, 201)))
        else:
            b = bytearray(C.encode_command(int(rng.integers(0, 2**32)), i, C.TARE))
            b[int(rng.integers(0, len(b)))] ^= 1 << int(rng.integers(0, 8))
            g = bytes(b)
        sock.sendto(g, ("127.0.0.1", port))
        counts["sent"] += 1
        if i % 50 == 49:
            time.sleep(0.002)  # about what the control socket's buffer holds between turns
    sock.close()


def run_commands(model: Path, tmp: Path, n: int, garbage: int) -> dict[str, Any]:
    """Part 2 (module docstring)."""
    from fbgforce import sim
    from fbgforce.recordings import dataset

    data = tmp / "smoke.csv"
    if not data.exists():
        dataset.save(sim.simulate("smoke", seed=5), data)
    return _run_commands_stream(model, data, _free_udp_port(), n, garbage)


def _run_commands_stream(model: Path, data: Path, port: int, n: int, garbage: int
                         ) -> dict[str, Any]:
    from fbgforce.interrogator import control as C
    from fbgforce.interrogator.hyperion import HyperionReader
    from fbgforce.interrogator.stream import LiveEstimator, run_stream

    em, source = _emulator(data, 5000.0, "--loop")
    server = C.ControlServer(f"udp://127.0.0.1:{port}")
    est = LiveEstimator(model, tare_samples=1)
    reader = HyperionReader(source)
    client: dict[str, Any] = {}
    junk = {"sent": 0}
    result: dict[str, Any] = {}
    stop = threading.Event()

    class _Until:
        """Ends the stream once the client and the garbage are done (a reader that reads on
        until then)."""

        def __init__(self, inner: Any) -> None:
            self.inner = inner

        def read(self, wait: float = 0.02) -> list:
            if stop.is_set():
                raise KeyboardInterrupt
            return self.inner.read(wait)

        def stats(self) -> dict[str, int]:
            return self.inner.stats()

        def close(self) -> None:
            self.inner.close()

    def stream() -> None:
        result.update(run_stream(_Until(reader), est, status=False, start_timeout=30,
                                 commands=[server]))

    worker = threading.Thread(target=stream, daemon=True)
    worker.start()
    time.sleep(1.0)
    t0 = time.monotonic()
    gthread = threading.Thread(target=_garbage, args=(port, garbage, 2, junk), daemon=True)
    gthread.start()
    client.update(_lossy_client(port, n, 0.05, 1))
    elapsed = time.monotonic() - t0
    gthread.join(600)
    time.sleep(0.5)
    stop.set()
    worker.join(60)
    reader.close()
    server.close()
    _end(em)
    rng = np.random.default_rng(9)
    crashes = 0
    for i in range(garbage):
        try:
            C.decode_command(rng.bytes(int(rng.integers(0, 201))))
            C.decode_ack(rng.bytes(int(rng.integers(0, 201))))
        except Exception:
            crashes += 1
    stats = server.stats()
    applied = result["commands"]["tare"]
    return {"commands": n, "done": client["done"], "lost": client["lost"],
            "refused_or_failed": client["other"],
            "applied_by_stream": applied, "applied_twice": applied - client["done"],
            "client_sends": client["sent"], "dropped_sends": client["dropped_sends"],
            "dropped_answers": client["dropped_answers"], "repeats_answered": stats["repeats"],
            "garbage_sent": junk["sent"], "garbage_counted_bad": stats["bad"],
            "stream_survived": bool(result), "seconds": round(elapsed, 1),
            "decoder_random_datagrams": 2 * garbage, "decoder_exceptions": crashes}


def run_step_time(model: Path, tmp: Path, rounds: int, seconds: float) -> dict[str, Any]:
    """Part 3 (module docstring)."""
    from fbgforce import sim
    from fbgforce.recordings import dataset
    from fbgforce.interrogator import control as C
    from fbgforce.interrogator.hyperion import HyperionReader
    from fbgforce.interrogator.stream import LiveEstimator, run_stream

    data = tmp / "smoke.csv"
    if not data.exists():
        dataset.save(sim.simulate("smoke", seed=5), data)
    runs: dict[str, list[tuple[float, float]]] = {"plain": [], "control": []}
    for _ in range(rounds):
        for mode in ("plain", "control"):
            em, source = _emulator(data, 1000.0, "--loop")
            server = C.ControlServer("udp://127.0.0.1:0") if mode == "control" else None
            reader = HyperionReader(source)
            est = LiveEstimator(model)
            cpu0 = resource.getrusage(resource.RUSAGE_SELF)
            try:
                s = run_stream(reader, est, duration=seconds, start_timeout=30, status=False,
                               commands=[server] if server is not None else [])
            finally:
                reader.close()
                if server is not None:
                    server.close()
                _end(em)
            cpu1 = resource.getrusage(resource.RUSAGE_SELF)
            cpu = (cpu1.ru_utime + cpu1.ru_stime - cpu0.ru_utime - cpu0.ru_stime)
            runs[mode].append((s["compute_us_per_sample"], 1e6 * cpu / max(s["received"], 1)))
            print(f"  {mode:<8} compute {runs[mode][-1][0]:6.1f} us/sample   process CPU "
                  f"{runs[mode][-1][1]:6.1f} us/sample   ({s['received']} samples)", flush=True)
    med = {m: np.median(np.array(v), axis=0).tolist() for m, v in runs.items()}
    spread = {m: (np.ptp(np.array(v), axis=0).tolist() if len(v) > 1 else [0.0, 0.0])
              for m, v in runs.items()}
    return {"runs": runs, "median": med, "spread": spread,
            "difference": [med["control"][i] - med["plain"][i] for i in range(2)]}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--model", type=Path, help="exported model directory (default: train one)")
    ap.add_argument("--commands", type=int, default=10_000)
    ap.add_argument("--garbage", type=int, default=100_000)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--seconds", type=float, default=8.0)
    ap.add_argument("--parts", default="preload,commands,step",
                    help="which parts to run (comma-separated: preload, commands, step)")
    ap.add_argument("--json", metavar="FILE", help="also write the figures as JSON")
    args = ap.parse_args(argv)
    parts = set(args.parts.split(","))
    out: dict[str, Any] = {}
    with tempfile.TemporaryDirectory() as tmp_name:
        tmp = Path(tmp_name)
        if args.model is None:
            from fbgforce.bench.bench_publish import small_model

            model = small_model(tmp)
        else:
            model = args.model
        if "preload" in parts:
            r = out["preload"] = run_preload(model, tmp)
            print("1. preload step +60 pm, tare, press, reset, silence")
            print(f"   rest before the step (first tare): p99 |F| "
                  f"{r['rest_before_step_p99_N']:.3f} N")
            print(f"   after the step, before the tare: median force "
                  f"{r['step_force_median_N']:.2f} N, contact on "
                  f"{100 * r['step_contact_share']:.0f} % of samples")
            print(f"   tare: {r['tare']['result']} in {r['tare']['answered_s']:.3f} s "
                  f"({r['tare']['message']})")
            print(f"   rest after the tare: p99 |F| {r['rest_after_tare_p99_N']:.3f} N over "
                  f"{r['rest_after_tare_n']} samples")
            print(f"   tracker offset when the tare was asked for: "
                  f"{r['tracker_offset_at_tare_pm']} pm")
            print(f"   press (peak {r['press_peak_N']:.1f} N): RMSE {r['press_rmse_N']:.3f} N "
                  f"(the same press without the step, offline: "
                  f"{r['press_rmse_no_step_offline_N']:.3f} N; with the step and no tare, "
                  f"offline: {r['press_rmse_step_untared_offline_N']:.3f} N, its rest p99 "
                  f"{r['untared_rest_after_step_p99_N']:.3f} N)")
            print(f"   reset: {r['reset']['result']} in {r['reset']['answered_s']:.3f} s; rest "
                  f"after it: p99 |F| {r['rest_after_reset_p99_N']:.3f} N over "
                  f"{r['rest_after_reset_n']} samples")
            p = r["diag_period_s"]
            print(f"   /diagnostics: {r['diagnostics']} records, period median {p[0]:.3f} s "
                  f"(min {p[1]:.3f}, max {p[2]:.3f}), samples_lost key: {r['diag_lost_key']}")
            print(f"   silence: level {r['silence_level']} after {r['silence_to_warn_s']} s; "
                  f"back to OK {r['back_to_ok_s']} s after samples returned; "
                  f"stream exit {r['exit_code']}", flush=True)
        if "commands" in parts:
            r = out["commands"] = run_commands(model, tmp, args.commands, args.garbage)
            print(f"2. {r['commands']} commands over UDP loopback in {r['seconds']} s: "
                  f"DONE {r['done']}, lost {r['lost']}, refused/failed "
                  f"{r['refused_or_failed']}, applied by the stream {r['applied_by_stream']}, "
                  f"applied twice {r['applied_twice']}")
            print(f"   client: {r['client_sends']} sends, {r['dropped_sends']} sends and "
                  f"{r['dropped_answers']} answers dropped on purpose; stream answered "
                  f"{r['repeats_answered']} repeats again")
            print(f"   garbage: {r['garbage_sent']} sent, {r['garbage_counted_bad']} counted bad "
                  f"by the stream (the rest dropped by the kernel), stream survived: "
                  f"{r['stream_survived']}; decoder on {r['decoder_random_datagrams']} random "
                  f"datagrams: {r['decoder_exceptions']} exceptions", flush=True)
        if "step" in parts:
            print("3. step time, streams without and with --control (1 kHz)")
            r = out["step"] = run_step_time(model, tmp, args.rounds, args.seconds)
            print(f"   median compute us/sample: plain {r['median']['plain'][0]:.2f} (spread "
                  f"{r['spread']['plain'][0]:.2f}), control {r['median']['control'][0]:.2f} "
                  f"(spread {r['spread']['control'][0]:.2f}), difference "
                  f"{r['difference'][0]:+.2f}")
            print(f"   median process CPU us/sample: plain {r['median']['plain'][1]:.1f} (spread "
                  f"{r['spread']['plain'][1]:.1f}), control {r['median']['control'][1]:.1f} "
                  f"(spread {r['spread']['control'][1]:.1f}), difference "
                  f"{r['difference'][1]:+.1f}", flush=True)
    if args.json:
        Path(args.json).write_text(json.dumps(out, indent=1, default=str))
    return 0


if __name__ == "__main__":
    sys.exit(main())
