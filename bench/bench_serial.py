"""Serial-path headroom: decoder throughput and sustained pty rates (prints a table).

    python bench/bench_serial.py [--seconds 2] [--rates 1000,5000,10000,20000]

1. Native-frame decoding in Python (``FrameDecoder.feed`` on 4 KiB chunks): frames/s.
2. Virtual interrogator -> ``NativeReader`` over a real pseudo-terminal, in two processes
   (emulator in a child process), for a few playback rates: frames received, lost, achieved
   rate. The issue's requirement is 1 kHz with zero lost frames; this shows the margin.
"""
from __future__ import annotations

import argparse
import multiprocessing as mp
import time

import numpy as np


def _synthetic(n: int):
    from fbgforce.recordings.dataset import Dataset

    t = np.arange(n) / 1000.0
    wl = 1530.0 + 8.0 * np.arange(5) + 0.01 * np.sin(t[:, None] * np.arange(1, 6))
    c = np.zeros(n, dtype=bool)
    return Dataset(t_s=t, wl_nm=wl, contact=c, x_mm=np.full(n, np.nan), y_mm=np.full(n, np.nan),
                   force_N=np.zeros(n), press_id=np.zeros(n, dtype=np.int64), source="bench")


def bench_decoder(n: int = 50_000) -> float:
    from fbgforce.interrogator import protocol as P

    data = b"".join(P.encode_frames(0, np.arange(n) * 1000,
                                    np.full((n, 5), 1_546_000_000, dtype=np.int64)))
    dec = P.FrameDecoder(5)
    t0 = time.perf_counter()
    got = 0
    for k in range(0, len(data), 4096):
        got += len(dec.feed(data[k:k + 4096]))
    dt = time.perf_counter() - t0
    assert got == n
    return n / dt


def _play(link: str, n: int, rate: float) -> None:
    from fbgforce.interrogator import emulator as E

    E.Emulator(E.Playback.from_dataset(_synthetic(n)), rate=rate, link=link, linger=1.0).run()


def bench_pty(rate: float, seconds: float, link: str) -> dict[str, float]:
    from fbgforce.interrogator import reader as R

    n = int(rate * seconds)
    proc = mp.get_context("spawn").Process(target=_play, args=(link, n, rate))
    proc.start()
    import os

    while not os.path.exists(link):
        time.sleep(0.01)
    rd = R.NativeReader(link)
    got = 0
    t_first = t_last = None
    for batch in R.iter_batches(rd, idle_timeout=0.5, start_timeout=30):
        now = time.monotonic()
        t_first = now if t_first is None else t_first
        t_last = now
        got += len(batch)
    rd.close()
    proc.join(10)
    s = rd.stats()
    span = (t_last - t_first) if t_first is not None else 0.0
    return {"rate": rate, "sent": n, "received": got, "lost": s["lost_frames"],
            "achieved_hz": (got - 1) / span if span > 0 else 0.0}


def main() -> None:
    import tempfile

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=2.0)
    ap.add_argument("--rates", default="1000,5000,10000,20000")
    args = ap.parse_args()
    print(f"native frame decoding (Python): {bench_decoder():,.0f} frames/s")
    print(f"{'rate Hz':>8} {'sent':>7} {'received':>9} {'lost':>5} {'achieved Hz':>12}")
    with tempfile.TemporaryDirectory() as tmp:
        for k, rate in enumerate(float(r) for r in args.rates.split(",")):
            r = bench_pty(rate, args.seconds, f"{tmp}/tty{k}")
            print(f"{r['rate']:8.0f} {r['sent']:7d} {r['received']:9d} {r['lost']:5d} "
                  f"{r['achieved_hz']:12.1f}")


if __name__ == "__main__":
    main()
