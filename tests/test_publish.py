"""Estimates out to a controller: the UDP datagram (layout, C and Python receivers, 10,000
datagrams on loopback equal to the offline fixed engine) and LCM end to end."""
from __future__ import annotations

import json
import os
import shutil
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from conftest import offline_fixed, start_emulator, wait_for_line
from fbgforce import sim
from fbgforce.cli import main
from fbgforce.errors import InputError
from fbgforce.interrogator import protocol as P
from fbgforce.interrogator import publish as U

ROOT = Path(__file__).resolve().parents[1]
EXAMPLE = ROOT / "examples" / "udp_receiver"
CI = os.environ.get("CI", "").lower() == "true"


def _free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _est(n: int) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(0)
    return {"status": rng.integers(0, 32, n).astype(np.uint32), "contact": rng.random(n) < 0.5,
            "contact_conf_q15": rng.integers(0, 32768, n).astype(np.uint16),
            "force_mN": rng.integers(-5000, 70000, n).astype(np.int32),
            "x_um": rng.integers(-100, 21000, n).astype(np.int32),
            "y_um": rng.integers(-100, 27000, n).astype(np.int32)}


def test_datagram_layout_is_the_documented_one():
    assert U.DATAGRAM_SIZE == 48
    offsets = {name: U.DATAGRAM_DTYPE.fields[name][1] for name in U.DATAGRAM_DTYPE.names}
    assert offsets == {"magic": 0, "version": 4, "size": 6, "seq": 8, "sample_seq": 12,
                       "t_us": 16, "status": 24, "contact": 28, "reserved": 29,
                       "contact_conf_q15": 30, "force_mN": 32, "x_um": 36, "y_um": 40,
                       "crc32": 44}
    frames = [P.Frame(0xFFFFFFFF, -1, (0,) * 5), P.Frame(7, 123_456_789_012, (0,) * 5)]
    est = _est(2)
    d = U.encode_datagrams(5, U.estimate_records(frames, est))
    assert d[1][:8] == b"FBGO\x01\x00\x30\x00"
    assert d[1][8:12] == (6).to_bytes(4, "little") and d[1][12:16] == (7).to_bytes(4, "little")
    assert d[1][16:24] == (123_456_789_012).to_bytes(8, "little")
    assert d[0][16:24] == b"\xff" * 8  # t_us -1: no device timestamp
    assert d[1][44:] == P.crc32(d[1][:44]).to_bytes(4, "little")
    rec = U.decode_datagram(d[1])
    assert rec is not None and int(rec["force_mN"]) == int(est["force_mN"][1])
    bad = bytearray(d[1])
    bad[33] ^= 0x10
    assert U.decode_datagram(bytes(bad)) is None
    # The example Python receiver (no fbgforce inside) reads the same layout.
    sys.path.insert(0, str(EXAMPLE))
    try:
        import receiver  # type: ignore[import-not-found]
    finally:
        sys.path.remove(str(EXAMPLE))
    e = receiver.decode(d[1])
    assert e == (6, 7, 123_456_789_012, int(est["status"][1]), int(est["contact"][1]),
                 int(est["contact_conf_q15"][1]), int(est["force_mN"][1]), int(est["x_um"][1]),
                 int(est["y_um"][1]))
    assert receiver.decode(bytes(bad)) is None


def _compile_receiver(tmp_path: Path) -> Path:
    cc = shutil.which("cc") or shutil.which("gcc")
    if cc is None:
        if CI:
            pytest.fail("no C compiler")
        pytest.skip("no C compiler")
    exe = tmp_path / "receiver"
    subprocess.run([cc, "-std=c99", "-Wall", "-Wextra", "-Werror", "-pedantic", "-o", str(exe),
                    str(EXAMPLE / "receiver.c")], check=True, capture_output=True, text=True)
    return exe


def _start_receiver(cmd: list[str]) -> subprocess.Popen:
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    assert proc.stderr is not None
    line = proc.stderr.readline()  # "listening": bound, ready for datagrams
    assert "listening" in line, line
    return proc


def _receiver_rows(proc: subprocess.Popen, timeout: float = 30) -> np.ndarray:
    try:
        out, err = proc.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        proc.kill()
        out, err = proc.communicate()
        raise AssertionError(f"receiver did not get every datagram: {err}")
    assert proc.returncode == 0, err
    return np.loadtxt(out.splitlines(), delimiter=",", dtype=np.int64, ndmin=2)


@pytest.mark.slow
def test_stream_publishes_10000_datagrams_equal_to_offline_fixed(tmp_path, small_exported_dir,
                                                                 capsys):
    """emulate (Hyperion on TCP) -> stream --source hyperion:// --publish udp:// (twice) -> the
    C receiver and the Python receiver: every one of 10,000 datagrams arrives and carries the
    offline fixed engine's values for its sample."""
    exe = _compile_receiver(tmp_path)
    port_c, port_py = _free_udp_port(), _free_udp_port()
    rx_c = _start_receiver([str(exe), "127.0.0.1", str(port_c), "10000"])
    rx_py = _start_receiver([sys.executable, str(EXAMPLE / "receiver.py"), "127.0.0.1",
                             str(port_py), "10000"])
    em = start_emulator("--scene", "smoke", "--seed", "5", "--rate", "5000", "--protocol", "hyperion",
                  "--command-port", "0", "--stream-port", "0", "--linger", "0.5")
    try:
        url = wait_for_line(em, "interrogator:")
        assert url.startswith("hyperion://127.0.0.1:")
        code = main(["stream", "--source", url, "--model", str(small_exported_dir), "--samples",
                     "10000", "--publish", f"udp://127.0.0.1:{port_c}", "--publish",
                     f"udp://127.0.0.1:{port_py}", "--start-timeout", "30", "--quiet", "--json"])
        assert code == 0
        summary = json.loads(capsys.readouterr().out)
        rows_c = _receiver_rows(rx_c)
        rows_py = _receiver_rows(rx_py)
    finally:
        for p in (rx_c, rx_py, em):
            if p.poll() is None:
                p.kill()
                p.communicate()
    assert summary["protocol"] == "hyperion" and summary["samples"] == 10000
    assert summary["lost_frames"] == 0 and summary["bad_frames"] == 0
    assert [p["sent"] for p in summary["published"]] == [10000, 10000]
    assert summary["publish_latency_us"]["n"] > 9000
    assert np.array_equal(rows_c, rows_py)
    scene = sim.simulate("smoke", seed=5).subset(np.arange(10000))
    # seq, sample_seq, t_us, status, contact, conf_q15, force_mN, x_um, y_um
    assert rows_c[:, 0].tolist() == list(range(10000))
    assert rows_c[:, 1].tolist() == list(range(10000))
    t_us = np.round(scene.t_s * 1e6).astype(np.int64) + 1_700_000_000 * 1_000_000
    assert np.array_equal(rows_c[:, 2], t_us)
    off = offline_fixed(small_exported_dir, scene.wl_nm, summary["baseline_nm"])
    assert np.array_equal(rows_c[:, 3], off["status"])
    assert np.array_equal(rows_c[:, 4], off["contact"].astype(np.int64))
    assert np.array_equal(rows_c[:, 5], off["contact_conf_q15"])
    assert np.array_equal(rows_c[:, 6], off["force_mN"])
    assert np.array_equal(rows_c[:, 7], off["x_um"])
    assert np.array_equal(rows_c[:, 8], off["y_um"])
    assert rows_c[:, 4].any() and rows_c[:, 6].max() > 5000


def _need_lcm() -> None:
    try:
        import lcm  # noqa: F401
    except ImportError:
        if CI:
            pytest.fail("the lcm package (extra [lcm]) is missing; .ci/run installs it")
        pytest.skip("the lcm package is not installed: pip install 'fbgforce[lcm]'")


LCM_SUBSCRIBER = r"""
import sys, lcm
from fbgforce.interrogator.lcmtypes.estimate_t import estimate_t
lc = lcm.LCM(sys.argv[1]); want = int(sys.argv[3]); rows = []
def on(channel, data):
    m = estimate_t.decode(data)
    rows.append((m.seq, m.sample_seq, m.t_us, m.status, int(m.contact), m.contact_conf_q15,
                 m.force_mN, m.x_um, m.y_um))
# LCM keeps 30 messages per subscription by default; the publisher sends a batch at a time.
lc.subscribe(sys.argv[2], on).set_queue_capacity(100000)
print("listening", file=sys.stderr, flush=True)
while len(rows) < want:
    lc.handle_timeout(20000)
print("\n".join(",".join(str(v) for v in r) for r in rows))
"""


def test_lcm_end_to_end_with_lcm_subscriber(tmp_path, small_exported_dir, capsys):
    """stream --publish lcm:// -> LCM's own subscriber in another process (multicast with
    ttl=0 on this host): every message arrives with the offline fixed engine's values."""
    _need_lcm()
    lcm_url = f"udpm://239.255.76.67:{_free_udp_port()}?ttl=0"
    channel = f"FBGFORCE_TEST_{os.getpid()}"
    n = 2000
    sub = _start_receiver([sys.executable, "-c", LCM_SUBSCRIBER,
                           lcm_url + "&recv_buf_size=4194304", channel, str(n)])
    em = start_emulator("--scene", "smoke", "--seed", "5", "--rate", "5000", "--protocol", "hyperion",
                  "--command-port", "0", "--stream-port", "0", "--linger", "0.5")
    try:
        url = wait_for_line(em, "interrogator:")
        assert main(["stream", "--source", url, "--model", str(small_exported_dir), "--samples",
                     str(n), "--publish", f"lcm://{channel}?url={lcm_url}", "--start-timeout",
                     "30", "--quiet", "--json"]) == 0
        summary = json.loads(capsys.readouterr().out)
        rows = _receiver_rows(sub)
    finally:
        for p in (sub, em):
            if p.poll() is None:
                p.kill()
                p.communicate()
    assert rows[:, 0].tolist() == list(range(n)) and rows[:, 1].tolist() == list(range(n))
    scene = sim.simulate("smoke", seed=5).subset(np.arange(n))
    off = offline_fixed(small_exported_dir, scene.wl_nm, summary["baseline_nm"])
    for col, key in ((3, "status"), (5, "contact_conf_q15"), (6, "force_mN"), (7, "x_um"),
                     (8, "y_um")):
        assert np.array_equal(rows[:, col], off[key]), key


@pytest.mark.parametrize("name", ["estimate_t", "status_t"])
def test_lcm_type_is_generated_from_its_lcm_file(tmp_path, name):
    """estimate_t.py and status_t.py are lcm-gen's output for their .lcm files (stale check)."""
    _need_lcm()
    gen = shutil.which("lcm-gen") or str(Path(sys.executable).parent / "lcm-gen")
    src = ROOT / "interrogator" / "lcmtypes"
    subprocess.run([gen, "-p", "--ppath", str(tmp_path), str(src / f"{name}.lcm")], check=True,
                   capture_output=True)
    assert (tmp_path / "fbgforce" / f"{name}.py").read_text() == (
        src / f"{name}.py").read_text(), f"regenerate: lcm-gen -p {name}.lcm"


def test_lcm_status_record_carries_the_health():
    """An lcm:// output publishes the health snapshot as fbgforce.status_t on CHANNEL_STATUS."""
    _need_lcm()
    import lcm

    from fbgforce.interrogator.health import Health
    from fbgforce.interrogator.lcmtypes.status_t import status_t

    lcm_url = f"udpm://239.255.76.67:{_free_udp_port()}?ttl=0"
    channel = f"FBGFORCE_STATUS_TEST_{os.getpid()}"
    got: list = []
    rx = lcm.LCM(lcm_url)
    rx.subscribe(channel + U.STATUS_CHANNEL_SUFFIX, lambda ch, data: got.append(
        status_t.decode(data)))
    pub = U.LcmPublisher(f"lcm://{channel}?url={lcm_url}")
    health = Health("fe" * 32, 200.0, now=0.0)
    health.samples(10, 0.9)
    health.estimates(np.array([0x08] * 10, dtype=np.uint32))
    snap = health.snapshot(1.0, {"lost_frames": 4, "reconnects": 0}, 3.0, {"tare": 2})
    pub.publish_status(snap)
    deadline = time.monotonic() + 5
    while not got and time.monotonic() < deadline:
        rx.handle_timeout(100)
    pub.close()
    assert got, "no status_t arrived"
    m = got[0]
    assert m.level == 2 and "sensor fault on 10 of 10 samples" in m.message
    assert (m.received, m.lost, m.tares, m.flags[3]) == (10, 4, 2, 10)
    assert m.model_digest == "fe" * 32 and m.tracker_bound_pm == 200.0


def test_publish_bad_url_exits_2(tmp_path, small_exported_dir, capsys):
    assert main(["stream", "--source", "loop://", "--model", str(small_exported_dir),
                 "--publish", "tcp://x:1"]) == 2
    assert "--publish" in capsys.readouterr().err


def test_float_engine_estimates_are_rounded_to_the_datagram_units():
    est = {"status": np.array([0, 8], dtype=np.uint32), "contact": np.array([True, False]),
           "p_contact": np.array([0.75, 0.01]), "force_N": np.array([12.3456, 0.0]),
           "x_mm": np.array([10.0004, np.nan]), "y_mm": np.array([13.5006, np.nan])}
    ints = U.estimate_integers(est)
    assert ints["contact_conf_q15"].tolist() == [24576, 328]
    assert ints["force_mN"].tolist() == [12346, 0]
    assert ints["x_um"].tolist() == [10000, 0] and ints["y_um"].tolist() == [13501, 0]
    rec = U.decode_datagram(U.encode_datagrams(
        0, U.estimate_records([P.Frame(3, -1, (0,) * 5)] * 2, est))[1])
    assert rec is not None and int(rec["status"]) == 8 and int(rec["t_us"]) == -1


def test_lcm_type_ships_with_the_package():
    from importlib import resources

    files = resources.files("fbgforce.interrogator.lcmtypes")
    assert files.joinpath("estimate_t.lcm").is_file()
    from fbgforce.interrogator.lcmtypes.estimate_t import estimate_t

    m = estimate_t()
    m.force_mN, m.sample_seq = 1234, 2**32 - 1
    assert estimate_t.decode(m.encode()).force_mN == 1234


class _SameBatchReader:
    """A reader that returns the same batch of frames ``batches`` times, then nothing."""

    def __init__(self, batch: list[P.Frame], batches: int) -> None:
        self.batch, self.left = batch, batches

    def read(self, wait: float = 0.02) -> list[P.Frame]:
        if self.left <= 0:
            return []
        self.left -= 1
        return self.batch

    def stats(self) -> dict[str, int]:
        return {"lost_frames": 0}

    def close(self) -> None:
        pass


class _TaredEstimator:
    """Returns the same estimates for every batch, at once (the stream loop alone is measured);
    never given a command."""

    engine = "fixed"
    baseline_fm = np.zeros(5, dtype=np.int64)
    baseline_nm = np.zeros(5)
    compute_s = 0.0
    estimated = 0
    tracker_offset_pm = 0.0
    tracker_bound_pm = 200.0
    command_counts = {"tare": 0, "reset": 0, "failed": 0}

    def digest(self) -> str:
        return "0" * 64

    def expire(self, now: float) -> None:
        pass

    def cancel(self, reason: str) -> None:
        pass

    def answered(self) -> list:
        return []

    def __init__(self, k: int) -> None:
        self.out = {"contact": np.zeros(k, bool), "p_contact": np.zeros(k),
                    "force_N": np.zeros(k), "x_mm": np.zeros(k), "y_mm": np.zeros(k),
                    "status": np.zeros(k, np.uint32)}

    def push(self, wl_fm: np.ndarray) -> dict[str, np.ndarray]:
        return self.out


class _CountingPublisher:
    sent = 0

    def publish(self, records: np.ndarray) -> None:
        self.sent += len(records)

    def stats(self) -> dict[str, int]:
        return {"sent": self.sent}


@pytest.mark.slow
def test_stream_publish_memory_is_flat_over_a_million_samples():
    """One million published samples (a quarter hour at 1 kHz) raise the stream loop's peak
    memory by less than 1 MB: the latency summary is a fixed-size histogram, not a list per sample."""
    import tracemalloc

    from fbgforce.interrogator.stream import run_stream

    k = 2000
    batch = [P.Frame(i, i, (1_546_000_000,) * 5) for i in range(k)]
    pub = _CountingPublisher()
    tracemalloc.start()
    try:
        base = tracemalloc.get_traced_memory()[0]
        summary = run_stream(_SameBatchReader(batch, 500), _TaredEstimator(k), status=False,
                             publication=U.Outputs([pub]), max_samples=10**6)
        grown = tracemalloc.get_traced_memory()[1] - base  # the peak, while the loop ran
    finally:
        tracemalloc.stop()
    assert pub.sent == summary["publish_latency_us"]["n"] == 10**6
    assert grown < 1 << 20, grown


class _StatusCountingPublisher(_CountingPublisher):
    statuses = 0

    def publish_status(self, health: dict) -> None:
        self.statuses += 1


def test_bench_ros2s_accounted_publication_takes_what_a_stream_hands_it(monkeypatch):
    """bench_ros2 wraps the publication to take the processes' usage before it finishes: the
    wrapper passes on the batches and every second's health snapshot (the stream hands both)
    and takes the usage once, before the summary."""
    from fbgforce.bench.bench_ros2 import _Accounted
    from fbgforce.interrogator import health
    from fbgforce.interrogator.stream import run_stream

    monkeypatch.setattr(health, "PERIOD_S", 0.0)     # a snapshot between every two batches
    k = 20
    batch = [P.Frame(i, i, (1_546_000_000,) * 5) for i in range(k)]
    pub, taken = _StatusCountingPublisher(), []
    summary = run_stream(_SameBatchReader(batch, 5), _TaredEstimator(k), status=False,
                         publication=_Accounted(U.Outputs([pub]), lambda: taken.append(pub.sent)),
                         max_samples=5 * k, idle_timeout=0.2)
    assert pub.sent == summary["publish_latency_us"]["n"] == 5 * k
    assert pub.statuses >= 5 and taken == [5 * k]


def test_latency_summary_percentiles_are_within_the_documented_bound():
    from fbgforce.interrogator.publish import LatencySummary

    rng = np.random.default_rng(3)
    values = np.concatenate([rng.lognormal(11, 1.0, 50_000), rng.uniform(0, 3, 20)]).astype(np.int64)
    s = LatencySummary()
    for v in values.tolist():
        s.add(v)
    s.add(40_000, 7)
    values = np.concatenate([values, np.full(7, 40_000)])
    for q in (1, 50, 90, 99, 99.9, 100):
        exact = float(np.percentile(values, q, method="inverted_cdf"))
        assert abs(s.percentile_ns(q) - exact) <= 0.0055 * exact + 1, q
    assert s.n == values.size and s.max_ns == values.max()
    assert s.summary_us()["max"] == round(values.max() / 1000, 1)


def test_receivers_count_duplicates_and_publisher_restarts_as_such(tmp_path):
    """A duplicated datagram is dropped and counted, a publisher that starts again from 0 is a
    restart: neither adds ~2**32 to "missing" (C and Python receivers alike)."""
    exe = _compile_receiver(tmp_path)
    seqs = [7, 8, 9, 9, 10, 12, 13, 0, 1, 1, 2]
    accepted = [7, 8, 9, 10, 12, 13, 0, 1, 2]
    frame = P.Frame(3, 3000, (1_546_000_000,) * 5)
    grams = [bytes(U.encode_datagrams(s, U.estimate_records([frame], _est(1)))[0])
             for s in seqs]
    for cmd in ([str(exe)], [sys.executable, str(EXAMPLE / "receiver.py")]):
        port = _free_udp_port()
        rx = _start_receiver(cmd + ["127.0.0.1", str(port), str(len(accepted))])
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as tx:
            for g in grams:
                tx.sendto(g, ("127.0.0.1", port))
        out, err = rx.communicate(timeout=30)
        assert rx.returncode == 0, err
        assert [int(line.split(",")[0]) for line in out.splitlines()] == accepted, cmd
        assert "received 9, bad 0, missing 1, duplicates 2, restarts 1" in err, (cmd, err)


def _records(first: int, n: int, arrived_ns: int) -> np.ndarray:
    frames = [P.Frame(s, 1000 * s, (0,) * 5) for s in range(first, first + n)]
    return U.estimate_records(frames, _est(n), arrived_ns)


def _udp_sink() -> tuple[socket.socket, str]:
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1 << 22)
    sock.bind(("127.0.0.1", 0))
    sock.settimeout(5)
    return sock, f"udp://127.0.0.1:{sock.getsockname()[1]}"


def _publish_ten(pub: U.PublisherProcess, sock: socket.socket
                 ) -> tuple[dict, list[np.void]]:
    """Ten records through ``pub`` to the sink ``sock``: the summary and what arrived."""
    pub.publish(_records(0, 10, time.monotonic_ns()))
    summary = pub.finish()
    return summary, _drain_sink(sock, 10)


def _drain_sink(sock: socket.socket, n: int) -> list[np.void]:
    got = []
    while len(got) < n:
        rec = U.decode_datagram(sock.recv(256))
        assert rec is not None
        got.append(rec)
    return got


def test_publisher_process_publishes_every_record_it_accepts_in_order():
    """Batches of 1..7 records through a 64-record ring (it wraps many times): the child sends
    every accepted record once, in order, with the estimate unchanged; a refused batch is
    counted, and samples that waited for the tare count in no latency."""
    sock, url = _udp_sink()
    rng = np.random.default_rng(1)
    pub = U.PublisherProcess([url], capacity=64)
    accepted: list[np.ndarray] = []
    seq = 0
    try:
        while seq < 3000:
            n = int(rng.integers(1, 8))
            batch = _records(seq, n, -1 if seq == 0 else time.monotonic_ns())
            dropped = pub.dropped
            pub.publish(batch)
            if pub.dropped == dropped:
                accepted.append(batch)
            seq += n
            if seq % 50 < 7:
                time.sleep(0.002)  # let the child catch up now and then
        summary = pub.finish()
        sent = np.concatenate(accepted)
        got = _drain_sink(sock, len(sent))
    finally:
        pub.close()
        sock.close()
    assert summary["published"][0]["sent"] == len(sent)
    assert summary["publish_dropped"] == seq - len(sent)
    assert len(sent) > 1000  # the ring was refilled many times over
    assert [int(r["seq"]) for r in got] == list(range(len(sent)))
    for k in ("sample_seq", "t_us", *U.ESTIMATE_FIELDS):
        assert [int(r[k]) for r in got] == sent[k].astype(np.int64).tolist(), k
    assert summary["publish_latency_us"]["n"] == len(sent) - len(accepted[0])


def test_publisher_process_never_waits_for_a_stopped_child():
    """The child stopped (SIGSTOP): publish returns at once, the ring takes what fits and the
    rest is refused and counted; the child, continued, publishes what the ring held."""
    import signal

    sock, url = _udp_sink()
    pub = U.PublisherProcess([url], capacity=64)
    slowest = 0.0
    try:
        os.kill(pub._child.pid, signal.SIGSTOP)
        try:
            for i in range(100):
                t0 = time.perf_counter()
                pub.publish(_records(10 * i, 10, time.monotonic_ns()))
                slowest = max(slowest, time.perf_counter() - t0)
        finally:
            os.kill(pub._child.pid, signal.SIGCONT)
        summary = pub.finish()
        got = _drain_sink(sock, 60)
    finally:
        pub.close()
        sock.close()
    assert slowest < 0.5, slowest  # a publish that waited would wait for ever
    assert summary["published"][0]["sent"] == 60 and summary["publish_dropped"] == 940
    assert [int(r["sample_seq"]) for r in got] == list(range(60))


def test_publisher_process_reports_an_output_it_cannot_open():
    with pytest.raises(InputError, match="expected udp://HOST:PORT") as err:
        U.PublisherProcess(["udp://no-port"])
    assert err.value.column == "--publish"


def test_publisher_process_outlives_the_stop_signals_of_its_process_group():
    """Ctrl-C and service managers signal the whole process group: the child ignores SIGINT and
    SIGTERM and publishes everything the stream hands over until the stream ends it."""
    import signal

    sock, url = _udp_sink()
    pub = U.PublisherProcess([url])
    try:
        for signum in (signal.SIGINT, signal.SIGTERM):
            os.kill(pub._child.pid, signum)
        time.sleep(0.2)
        summary, got = _publish_ten(pub, sock)
    finally:
        pub.close()
        sock.close()
    assert summary["published"][0]["sent"] == 10 and summary["publish_dropped"] == 0
    assert [int(r["sample_seq"]) for r in got] == list(range(10))


needs_affinity = pytest.mark.skipif(not hasattr(os, "sched_setaffinity"),
                                    reason="this system does not let a process choose its CPUs")


def _thread_cpus(pid: int | str) -> list[set[int]]:
    return [os.sched_getaffinity(int(t)) for t in os.listdir(f"/proc/{pid}/task")]


@pytest.fixture
def allowed_cpus():
    """The CPUs this test process may run on, given back to it after the test (``stream
    --cpu`` run in-process pins the process)."""
    cpus = os.sched_getaffinity(0)
    yield cpus
    U.pin_process(cpus)


@needs_affinity
def test_publisher_process_runs_on_the_cpus_it_is_given(allowed_cpus):
    cpu = max(allowed_cpus)
    sock, url = _udp_sink()
    pub = U.PublisherProcess([url], cpus={cpu})
    try:
        assert {frozenset(c) for c in _thread_cpus(pub._child.pid)} == {frozenset({cpu})}
        summary, got = _publish_ten(pub, sock)
    finally:
        pub.close()
        sock.close()
    assert summary["published"][0]["sent"] == 10
    assert [int(r["sample_seq"]) for r in got] == list(range(10))
    assert all(c == allowed_cpus for c in _thread_cpus("self"))  # the caller stays as it was


@needs_affinity
def test_stream_cpu_keeps_the_estimator_and_the_publishing_process_apart(
        allowed_cpus, small_exported_dir, capsys):
    """``stream --cpu N``: the stream's process ends up on CPU N alone, the publishing process
    on the other CPUs (both in the summary), and every estimate is published."""
    if len(allowed_cpus) < 2:
        pytest.skip("one CPU: nothing to keep apart")
    cpu = min(allowed_cpus)
    sock, url = _udp_sink()
    em = start_emulator("--scene", "smoke", "--seed", "5", "--rate", "5000", "--protocol",
                        "hyperion", "--command-port", "0", "--stream-port", "0", "--linger", "0.5")
    try:
        source = wait_for_line(em, "interrogator:")
        code = main(["stream", "--source", source, "--model", str(small_exported_dir),
                     "--samples", "1000", "--publish", url, "--cpu", str(cpu),
                     "--start-timeout", "30", "--quiet", "--json"])
        pinned = _thread_cpus("self")
        summary = json.loads(capsys.readouterr().out)
        got = _drain_sink(sock, 1000)
    finally:
        sock.close()
        if em.poll() is None:
            em.kill()
            em.communicate()
    assert code == 0 and all(c == {cpu} for c in pinned)
    assert summary["cpu"] == cpu and summary["publish_cpus"] == sorted(allowed_cpus - {cpu})
    assert summary["published"][0]["sent"] == 1000 and summary["publish_dropped"] == 0
    assert [int(r["seq"]) for r in got] == list(range(1000))


@needs_affinity
def test_stream_cpu_it_cannot_use_exits_2_with_one_line(allowed_cpus, small_exported_dir,
                                                        capsys):
    model = str(small_exported_dir)
    assert main(["stream", "--source", "loop://", "--model", model, "--cpu", "4096"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--cpu: CPU 4096 is not one this process may run on" in err[0], err
    assert all(c == allowed_cpus for c in _thread_cpus("self"))  # refused before pinning
    cpu = min(allowed_cpus)
    U.pin_process({cpu})
    assert main(["stream", "--source", "loop://", "--model", model, "--cpu", str(cpu),
                 "--publish", "udp://127.0.0.1:9"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and f"--cpu: CPU {cpu} is the only one" in err[0], err


@pytest.mark.slow
def test_a_publisher_killed_mid_run_stays_in_the_summary_with_what_it_sent(small_exported_dir,
                                                                           capsys):
    """The publishing process killed (SIGKILL) while the stream runs: the stream goes on, says
    so on stderr when it happens, and its summary still lists the output with the datagrams it
    sent before dying and says that it died."""
    import multiprocessing as mp
    import signal
    import threading

    sock, url = _udp_sink()
    received: list[int] = []
    killed: list[int] = []

    def kill_after_500() -> None:
        while len(received) < 500:
            try:
                rec = U.decode_datagram(sock.recv(256))
            except OSError:
                return
            if rec is not None:
                received.append(int(rec["seq"]))
        for child in mp.active_children():
            if child.name == "fbgforce-publish":
                os.kill(child.pid, signal.SIGKILL)
                killed.append(child.pid)

    em = start_emulator("--scene", "smoke", "--seed", "5", "--rate", "1000", "--protocol",
                        "hyperion", "--command-port", "0", "--stream-port", "0", "--linger", "0.5")
    watcher = threading.Thread(target=kill_after_500, daemon=True)
    try:
        source = wait_for_line(em, "interrogator:")
        watcher.start()
        code = main(["stream", "--source", source, "--model", str(small_exported_dir),
                     "--samples", "3000", "--publish", url, "--start-timeout", "30",
                     "--quiet", "--json"])
        captured = capsys.readouterr()
        watcher.join(10)
    finally:
        sock.close()
        if em.poll() is None:
            em.kill()
            em.communicate()
    assert killed, "the publishing process was never killed"
    summary = json.loads(captured.out)
    assert code == 0 and summary["samples"] == 3000
    (entry,) = summary["published"]
    assert entry["url"] == url and entry["died"] is True and entry["exit_code"] == -signal.SIGKILL
    # The counts as the child stored them after its last whole batch (a few ms of samples).
    assert 400 <= entry["sent"] < 3000
    assert summary["publish_dropped"] >= 3000 - entry["sent"] - 100
    lines = [ln for ln in captured.err.splitlines() if "publishing process died" in ln]
    assert len(lines) == 1 and "killed by SIGKILL" in lines[0] and url in lines[0], captured.err
