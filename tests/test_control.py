"""Tare, reset and health while streaming: LiveEstimator.tare()/.reset() against the offline
runtime, the UDP control datagram (exactly once, garbage), the C and Python clients, and the
whole of it end to end through the emulator (a command during a sensor fault, a client that
sends garbage, the 1 Hz status record)."""
from __future__ import annotations

import dataclasses
import json
import os
import shutil
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from conftest import start_emulator, wait_for_line
from fbgforce import sim
from fbgforce.recordings import dataset
from fbgforce.cli import main
from fbgforce.errors import InputError
from fbgforce.interrogator import control as C
from fbgforce.interrogator import health as H
from fbgforce.interrogator import publish as U
from fbgforce.interrogator.protocol import nm_to_fm
from fbgforce.interrogator.stream import LiveEstimator
from fbgforce.pybind import Runtime

ROOT = Path(__file__).resolve().parents[1]
EXAMPLE = ROOT / "examples" / "udp_receiver"
CI = os.environ.get("CI", "").lower() == "true"
STEP_PM = 60.0
RAW = ("force_mN", "x_um", "y_um", "contact_conf_q15", "status")


def _playback(n: int = 1500, step_at: int = 500, stuck: tuple[int, int] | None = None,
              press: bool = False, seed: int = 0) -> np.ndarray:
    """Wavelengths (nm): the smoke scene's unloaded fingertip with its noise, +60 pm on the
    strain gratings from ``step_at`` (a preload), FBG 1 frozen over ``stuck`` (a stuck peak:
    a sensor fault after the runtime's stuck_samples) and, with ``press``, one of the scene's
    presses (preloaded too) after the rest."""
    d = sim.simulate("smoke", seed=5)
    rest = d.wl_nm[:200]
    rng = np.random.default_rng(seed)
    wl = rest.mean(axis=0) + rng.normal(0.0, rest.std(axis=0), (n, 5))
    if press:
        seg = d.wl_nm[993:1549] - d.wl_nm[800:990].mean(axis=0) + rest.mean(axis=0)
        wl = np.concatenate([wl, seg, wl[-400:]])
    wl[step_at:, :4] += STEP_PM / 1000.0
    if stuck is not None:
        wl[stuck[0]:stuck[1], 0] = wl[stuck[0], 0]
    return wl


def _push(est: LiveEstimator, fm: np.ndarray, batch: int, commands: dict[int, str]
          ) -> tuple[dict[str, np.ndarray], dict[int, object]]:
    """Push ``fm`` in batches; before the batch starting at sample k give ``commands[k]``."""
    outs, given = [], {}
    for k in range(0, len(fm), batch):
        if k in commands:
            given[k] = getattr(est, commands[k])()
        outs.append(est.push(fm[k:k + batch]))
    return {key: np.concatenate([o[key] for o in outs if len(o["contact"])])
            for key in outs[-1]}, given


def _same(a: dict[str, np.ndarray], b: np.ndarray) -> None:
    for k in RAW:
        assert np.array_equal(np.asarray(a[k]), np.asarray(b[k])), k


def test_tare_while_streaming_takes_the_next_window_as_baseline_between_samples(
        small_exported_dir):
    """A tare given between two batches averages the next 200 samples and runs every later
    sample on that baseline (the window ends inside a batch: the split is at the sample), as
    the offline runtime does with the tare at that sample; its answer gives the change."""
    fm = nm_to_fm(_playback())
    est = LiveEstimator(small_exported_dir, tare_samples=200)
    k0 = 37 * 19  # a batch boundary after the step
    out, given = _push(est, fm, 37, {k0: "tare"})
    cmd = given[k0]
    assert cmd.done and cmd.ok and cmd.samples == 200 and cmd.faults == 0, cmd
    assert np.all(np.abs(np.array(cmd.change_pm[:4]) - STEP_PM) < 2.0), cmd.change_pm
    assert abs(cmd.change_pm[4]) < 2.0
    assert "+6" in cmd.message and "pm" in cmd.message
    rt = Runtime(small_exported_dir)
    rt.tare(fm[:200].astype(np.int32))
    base0 = rt.baseline_fm
    head = rt.run_raw(fm[:k0 + 200].astype(np.int32))
    rt.tare(fm[k0:k0 + 200].astype(np.int32))
    assert np.allclose((rt.baseline_fm - base0) / 1000.0, cmd.change_pm, atol=1e-9)
    rt.set_baseline(rt.baseline_fm)
    tail = rt.run_raw(fm[k0 + 200:].astype(np.int32))
    _same(out, np.concatenate([head, tail]))
    assert est.command_counts == {"tare": 1, "reset": 0, "failed": 0}
    assert est.answered() == [cmd] and est.answered() == []


def test_a_sensor_fault_inside_the_window_fails_the_tare_and_keeps_the_baseline(
        small_exported_dir):
    fm = nm_to_fm(_playback(stuck=(700, 1000)))
    est = LiveEstimator(small_exported_dir, tare_samples=200)
    k0 = 37 * 19
    out, given = _push(est, fm, 37, {k0: "tare"})
    cmd = given[k0]
    assert cmd.done and not cmd.ok and cmd.faults > 0 and cmd.change_pm == [0.0] * 5
    assert "sensor fault" in cmd.message and "baseline kept" in cmd.message
    rt = Runtime(small_exported_dir)
    rt.tare(fm[:200].astype(np.int32))
    _same(out, rt.run_raw(fm.astype(np.int32)))  # nothing changed: the old baseline throughout
    assert est.command_counts["failed"] == 1


def test_reset_starts_the_state_afresh_and_tares(small_exported_dir):
    fm = nm_to_fm(_playback())
    est = LiveEstimator(small_exported_dir, tare_samples=200)
    k0 = 40 * 20
    out, given = _push(est, fm, 40, {k0: "reset"})
    cmd = given[k0]
    assert cmd.done and cmd.ok and cmd.name == "reset", cmd
    assert np.all(np.abs(np.array(cmd.change_pm[:4]) - STEP_PM) < 2.0)
    rt = Runtime(small_exported_dir)
    rt.tare(fm[:200].astype(np.int32))
    base0 = rt.baseline_fm
    a = rt.run_raw(fm[:k0].astype(np.int32))
    rt.set_baseline(base0)
    rt.reset()
    b = rt.run_raw(fm[k0:k0 + 200].astype(np.int32))
    rt.tare(fm[k0:k0 + 200].astype(np.int32))
    rt.set_baseline(rt.baseline_fm)
    c = rt.run_raw(fm[k0 + 200:].astype(np.int32))
    _same(out, np.concatenate([a, b, c]))


def test_commands_queue_and_each_gets_its_own_window(small_exported_dir):
    fm = nm_to_fm(_playback(n=1600))
    est = LiveEstimator(small_exported_dir, tare_samples=100)
    est.push(fm[:600])
    first, second = est.tare(), est.tare()
    est.push(fm[600:650])
    assert not first.done and est.busy
    est.push(fm[650:1600])
    assert first.ok and second.ok and not est.busy
    assert est.command_counts["tare"] == 2
    # The second window is the 100 samples after the first: the same rest, a tiny change.
    assert np.all(np.abs(second.change_pm) < 2.0)


def test_float_engine_tares_too(small_model_dir):
    fm = nm_to_fm(_playback())
    est = LiveEstimator(small_model_dir, engine="float", tare_samples=200)
    _, given = _push(est, fm, 50, {700: "tare"})
    assert given[700].ok and np.all(np.abs(np.array(given[700].change_pm[:4]) - STEP_PM) < 2.0)


def test_a_tare_without_samples_fails_in_time_and_the_stream_end_fails_the_rest(
        small_exported_dir):
    fm = nm_to_fm(_playback(n=400))
    est = LiveEstimator(small_exported_dir, tare_samples=200, command_timeout=2.0)
    est.push(fm[:300])
    cmd = est.tare()
    est.push(fm[300:350])
    est.expire(cmd.requested_s + 1.0)
    assert not cmd.done
    est.expire(cmd.requested_s + 2.0)
    assert cmd.done and not cmd.ok and "only 50 of 200 samples" in cmd.message
    late = est.tare()
    est.cancel("the stream ended")
    assert late.done and not late.ok and "the stream ended" in late.message


def test_health_levels_follow_the_documented_rules():
    h = H.Health("ab" * 32, 200.0, now=0.0)
    stats = {"lost_frames": 0, "reconnects": 0}
    assert h.snapshot(0.5, stats, 0.0)["level_name"] == "WARN"  # no sample yet, 0.5 s
    h.samples(1000, 1.45)
    h.estimates(np.zeros(1000, dtype=np.uint32))
    ok = h.snapshot(1.5, stats, 10.0)
    assert ok["level_name"] == "OK" and ok["message"] == "OK" and ok["rate_hz"] == 1000 / 1.0
    assert h.snapshot(1.8, stats, 10.0)["level_name"] == "WARN"  # silent 0.35 s
    silent = h.snapshot(2.6, stats, 10.0)
    assert silent["level_name"] == "ERROR" and "no sample for 1.1 s" in silent["message"]
    h.samples(500, 2.7)
    status = np.zeros(500, dtype=np.uint32)
    status[:10] = 0x20  # BASELINE_LIMIT
    h.estimates(status)
    warn = h.snapshot(2.7, {"lost_frames": 3, "reconnects": 1}, 170.0)
    assert warn["level_name"] == "WARN" and warn["flags_last_s"]["BASELINE_LIMIT"] == 10
    assert "3 samples lost" in warn["message"] and "reconnected" in warn["message"]
    h.samples(100, 2.8)
    h.estimates(np.full(100, 0x08, dtype=np.uint32))  # SENSOR_FAULT on every sample
    assert h.snapshot(2.8, {"lost_frames": 3, "reconnects": 1}, 0.0)["level_name"] == "ERROR"
    h.samples(100, 2.9)
    h.estimates(np.zeros(100, dtype=np.uint32))
    assert h.snapshot(2.9, {"lost_frames": 3, "reconnects": 1}, 0.0)["level_name"] == "OK"


def test_status_record_layout_and_receivers(tmp_path):
    health = H.Health("0123456789abcdef" * 4, 200.0, now=0.0)
    health.samples(999, 1.0)
    st = np.zeros(999, dtype=np.uint32)
    st[:7] = 0x40
    health.estimates(st)
    snap = health.snapshot(1.0, {"lost_frames": 2, "reconnects": 1}, 12.5,
                           {"tare": 3, "reset": 1, "failed": 2})
    data = U.encode_status(7, snap)
    assert len(data) == U.STATUS_SIZE == 92
    rec = U.decode_status(data)
    assert rec is not None and int(rec["seq"]) == 7 and int(rec["level"]) == H.WARN
    assert int(rec["received"]) == 999 and int(rec["lost"]) == 2
    assert int(rec["flags"][6]) == 7 and int(rec["tracker_offset_fm"]) == 12500
    assert int(rec["tares"]) == 3 and int(rec["failed"]) == 2
    assert bytes(rec["digest"]).hex() == "0123456789abcdef"
    bad = bytearray(data)
    bad[20] ^= 1
    assert U.decode_status(bytes(bad)) is None
    sys.path.insert(0, str(EXAMPLE))
    try:
        import receiver  # type: ignore[import-not-found]
    finally:
        sys.path.remove(str(EXAMPLE))
    r = receiver.decode_status(data)
    assert r is not None and (r.seq, r.level, r.received, r.lost, r.reconnects) == (7, 1, 999, 2, 1)
    assert r.flags[6] == 7 and r.tracker_offset_fm == 12500 and r.digest == "0123456789abcdef"
    assert receiver.decode_status(bytes(bad)) is None and receiver.decode(data) is None


def _example(name: str):
    sys.path.insert(0, str(EXAMPLE))
    try:
        return __import__(name)
    finally:
        sys.path.remove(str(EXAMPLE))


def test_control_datagrams_are_the_documented_layout_in_both_clients():
    offsets = {n: C.COMMAND_DTYPE.fields[n][1] for n in C.COMMAND_DTYPE.names}
    assert offsets == {"magic": 0, "version": 4, "size": 6, "session": 8, "seq": 12,
                       "command": 16, "reserved": 18, "crc32": 20} and C.COMMAND_SIZE == 24
    offsets = {n: C.ACK_DTYPE.fields[n][1] for n in C.ACK_DTYPE.names}
    assert offsets == {"magic": 0, "version": 4, "size": 6, "session": 8, "seq": 12,
                       "command": 16, "result": 18, "change_fm": 20, "samples": 40,
                       "message": 44, "crc32": 120} and C.ACK_SIZE == 124
    client = _example("control")
    assert client.encode_command(0xDEADBEEF, 5, 2) == C.encode_command(0xDEADBEEF, 5, C.RESET)
    ack = C.encode_ack(9, 5, C.TARE, C.FAILED, "sensor fault é" + "x" * 100,
                       [60000, -1, 2, 3, -70000], 200)
    got = client.decode_ack(ack)
    assert got is not None and got.change_fm == (60000, -1, 2, 3, -70000)
    assert (got.session, got.seq, got.command, got.result, got.samples) == (9, 5, 1, 1, 200)
    assert got.message.startswith("sensor fault é") and len(got.message.encode()) <= 76
    rec = C.decode_ack(ack)
    assert rec is not None and int(rec["result"]) == C.FAILED
    bad = bytearray(ack)
    bad[50] ^= 4
    assert client.decode_ack(bytes(bad)) is None and C.decode_ack(bytes(bad)) is None
    assert C.decode_command(C.encode_command(1, 2, 3)) is not None


class _Answered:
    """What :meth:`ControlServer.answer` reads of a command."""

    def __init__(self, token, ok=True, change_pm=(60.0, 60.0, 60.0, 60.0, 0.0)):
        self.token, self.ok, self.change_pm = token, ok, list(change_pm)
        self.message, self.samples = "done", 200


def _recv_ack(sock: socket.socket) -> np.void:
    rec = C.decode_ack(sock.recv(512))
    assert rec is not None
    return rec


def test_control_server_applies_each_command_once_and_ignores_garbage():
    server = C.ControlServer("udp://127.0.0.1:0")
    port = int(server.url.rsplit(":", 1)[1])
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.settimeout(5)
    to = ("127.0.0.1", port)
    try:
        rng = np.random.default_rng(7)
        for i in range(10_000):  # garbage: random bytes, cut and bit-flipped commands
            kind = i % 3
            if kind == 0:
                g = rng.bytes(int(rng.integers(0, 200)))
            elif kind == 1:
                g = C.encode_command(1, i, C.TARE)[:int(rng.integers(0, 24))]
            else:
                g = bytearray(C.encode_command(1, i, C.TARE))
                g[int(rng.integers(0, 24))] ^= 1 << int(rng.integers(0, 8))
                g = bytes(g)
            sock.sendto(g, to)
            if i % 200 == 199:
                assert server.poll() == []
        while server.poll():
            pass
        assert server.poll() == []
        sock.setblocking(False)
        with pytest.raises(BlockingIOError):
            sock.recv(512)  # garbage is never answered
        sock.setblocking(True)
        sock.settimeout(5)
        cmd = C.encode_command(42, 1, C.TARE)
        sock.sendto(cmd, to)
        sock.sendto(cmd, to)
        time.sleep(0.05)
        got = server.poll()
        assert len(got) == 1 and got[0][0] == "tare"
        assert [int(_recv_ack(sock)["result"]) for _ in range(2)] == [C.PENDING, C.PENDING]
        server.answer(_Answered(got[0][1]))
        done = _recv_ack(sock)
        assert int(done["result"]) == C.DONE and list(done["change_fm"]) == [60000] * 4 + [0]
        sock.sendto(cmd, to)  # a repeat after the answer: the same answer, not applied again
        time.sleep(0.05)
        assert server.poll() == []
        assert _recv_ack(sock).tobytes() == done.tobytes()
        sock.sendto(C.encode_command(42, 0, C.TARE), to)  # behind the session: refused
        sock.sendto(C.encode_command(42, 2, 9), to)  # unknown command: refused
        time.sleep(0.05)
        assert server.poll() == []
        refused = [_recv_ack(sock) for _ in range(2)]
        assert [int(r["result"]) for r in refused] == [C.REFUSED, C.REFUSED]
        assert b"stale" in bytes(refused[0]["message"])
        assert b"unknown command 9" in bytes(refused[1]["message"])
        stats = server.stats()
        assert stats["bad"] >= 10_000 - 1 and stats["commands"] == 1 and stats["refused"] == 2
    finally:
        sock.close()
        server.close()


def test_control_url_errors_name_the_flag():
    with pytest.raises(InputError, match="expected udp://HOST:PORT") as err:
        C.ControlServer("tcp://127.0.0.1:5")
    assert err.value.column == "--control"


def _compile(tmp_path: Path, name: str) -> Path:
    cc = shutil.which("cc") or shutil.which("gcc")
    if cc is None:
        if CI:
            pytest.fail("no C compiler")
        pytest.skip("no C compiler")
    exe = tmp_path / name
    subprocess.run([cc, "-std=c99", "-Wall", "-Wextra", "-Werror", "-pedantic", "-o", str(exe),
                    str(EXAMPLE / f"{name}.c")], check=True, capture_output=True, text=True)
    return exe


def _free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class _EstimateSink:
    """The test's end of ``--publish udp://``: what it has seen of the stream so far (the
    samples flagged as sensor faults, the status records, the last sample) and the command
    answers the controller got."""

    def __init__(self) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1 << 22)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.settimeout(10)
        self.seen: dict[str, list] = {"faults": [], "status": [], "answers": [], "last": [-1]}

    def wait_sample(self, cond) -> None:
        """Reads the published records until a sample satisfies ``cond``, noting every status
        record and every faulty sample on the way."""
        seen = self.seen
        while True:
            d = self.sock.recv(256)
            rec = U.decode_datagram(d)
            if rec is None:
                st = U.decode_status(d)
                assert st is not None
                seen["status"].append((time.monotonic(), int(st["level"]), int(st["received"])))
                continue
            seen["last"][0] = int(rec["sample_seq"])
            if int(rec["status"]) & 0x08:
                seen["faults"].append(int(rec["sample_seq"]))
            if cond(rec):
                return


def _send_commands(sink: _EstimateSink, py_client, c_client: Path, control_port: int, n: int,
                   errors: list[BaseException]) -> None:
    """The controller, paced by the published samples: a tare during the stuck peak, a tare
    from the C client after it, 2000 garbage datagrams, then one reset sent twice under the
    same sequence number; an exception goes to ``errors`` for the test's thread."""
    try:
        client = py_client.Client("127.0.0.1", control_port)
        sink.wait_sample(lambda r: int(r["status"]) & 0x08)  # during the fault
        sink.seen["answers"].append(("fault", client.send("tare")))
        sink.wait_sample(lambda r: int(r["sample_seq"]) >= 1600)
        res = subprocess.run([str(c_client), "127.0.0.1", str(control_port), "tare"],
                             capture_output=True, text=True, timeout=30)
        sink.seen["answers"].append(("c", res))
        junk = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        rng = np.random.default_rng(3)
        for i in range(2000):
            junk.sendto(rng.bytes(int(rng.integers(0, 130))), ("127.0.0.1", control_port))
            if i % 100 == 99:
                time.sleep(0.01)  # within what the socket's buffer holds between turns
        junk.close()
        sink.wait_sample(lambda r: int(r["sample_seq"]) >= 1900)
        ack = client.send("reset")
        client.seq -= 1  # the same command again: answered again, not applied again
        again = client.send("reset")
        sink.seen["answers"].append(("reset", ack, again))
        sink.wait_sample(lambda r: int(r["sample_seq"]) >= n - 1)
    except BaseException as exc:  # reported by the test's thread
        errors.append(exc)


def _assert_answers(seen: dict[str, list]) -> None:
    """The tare during the fault failed; the C client's tare took the +60 pm step; the reset
    sent twice was answered the same both times."""
    assert seen["faults"], "the stuck peak never showed as a sensor fault"
    (_, fault), (_, c_res), (_, reset, again) = seen["answers"]
    assert fault.result == 1 and "sensor fault" in fault.message, fault
    assert c_res.returncode == 0, c_res.stderr
    seq, result, command, *change = c_res.stdout.strip().split(",", 9)
    assert result == "DONE" and command == "1"
    change_fm = [int(v) for v in change[:5]]
    assert all(abs(v - STEP_PM * 1000) < 2000 for v in change_fm[:4]), change_fm
    assert reset.result == 0 and again == reset


@pytest.mark.slow
def test_stream_takes_commands_over_udp_end_to_end(tmp_path, small_exported_dir, capsys):
    """emulate (Hyperion) plays a preload step, then a stuck peak, then a press -> stream
    --control --publish udp://: a tare sent during the fault fails and keeps the baseline; a
    tare from the C client after it takes the +60 pm; a client that sends garbage changes
    nothing; a reset from the Python client is applied once although sent twice; the status
    record arrives once a second; the summary counts it all."""
    c_client = _compile(tmp_path, "control")
    py_client = _example("control")
    wl = _playback(n=3000, step_at=300, stuck=(1100, 1500), press=True)
    base = sim.simulate("smoke", seed=5).subset(np.arange(len(wl)))
    data = tmp_path / "step.csv"
    dataset.save(dataclasses.replace(base, wl_nm=wl), data)
    n = len(wl)
    sink = _EstimateSink()
    control_port = _free_udp_port()
    errors: list[BaseException] = []
    em = start_emulator("--data", str(data), "--rate", "1000", "--protocol", "hyperion",
                        "--command-port", "0", "--stream-port", "0", "--linger", "0.5")
    thread = threading.Thread(target=_send_commands, daemon=True,
                              args=(sink, py_client, c_client, control_port, n, errors))
    try:
        source = wait_for_line(em, "interrogator:")
        thread.start()
        code = main(["stream", "--source", source, "--model", str(small_exported_dir),
                     "--samples", str(n), "--control", f"udp://127.0.0.1:{control_port}",
                     "--publish", f"udp://127.0.0.1:{sink.sock.getsockname()[1]}",
                     "--start-timeout", "30", "--quiet", "--json"])
        captured = capsys.readouterr()
        thread.join(30)
    finally:
        sink.sock.close()
        if em.poll() is None:
            em.kill()
            em.communicate()
    assert not errors, errors
    assert code == 0, captured.err
    summary = json.loads(captured.out)
    seen = sink.seen
    _assert_answers(seen)
    assert summary["commands"] == {"tare": 1, "reset": 1, "failed": 1}
    ctl = summary["control"]
    assert ctl["bad"] == 2000 and ctl["commands"] == 3 and ctl["answered"] == 3
    assert ctl["url"] == f"udp://127.0.0.1:{control_port}"
    health = summary["health"]
    assert health["level_name"] in ("OK", "WARN", "ERROR") and health["received"] > 0
    assert health["model_digest"] == LiveEstimator(small_exported_dir).digest()
    assert health["commands"]["failed"] == 1
    # One status record a second (the controller thread reads them late at times: only
    # their number is checked here; bench/bench_control.py measures their period), each
    # counting the samples received so far.
    times = [t for t, _, _ in seen["status"]]
    assert abs(len(times) - summary["duration_s"]) <= 1.5, (len(times), summary["duration_s"])
    assert [r for _, _, r in seen["status"]] == sorted(r for _, _, r in seen["status"])
    assert summary["published"][0]["status_sent"] == len(seen["status"])


def test_stream_control_url_it_cannot_use_exits_2_with_one_line(small_exported_dir, capsys):
    model = str(small_exported_dir)
    assert main(["stream", "--source", "loop://", "--model", model, "--control",
                 "tcp://127.0.0.1:9"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--control: expected udp://HOST:PORT" in err[0], err
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as taken:
        taken.bind(("127.0.0.1", 0))
        port = taken.getsockname()[1]
        assert main(["stream", "--source", "loop://", "--model", model, "--control",
                     f"udp://127.0.0.1:{port}"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and f"--control: cannot listen on 127.0.0.1:{port}" in err[0], err
