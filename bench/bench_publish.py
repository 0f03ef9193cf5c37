"""Arrival-to-publication latency of ``fbgforce stream --publish`` at 1 kHz (prints a table).

    python bench/bench_publish.py [--model MODEL_DIR] [--seconds 10] [--rate 1000]

For each source (native frames on a pseudo-terminal, a Hyperion peak stream on loopback TCP)
a virtual interrogator plays the ``smoke`` scene in a child process at ``--rate`` samples/s;
this process runs the stream (fixed-point C runtime) and publishes every estimate as a UDP
datagram, through the publishing process ``fbgforce stream`` uses, to a receiver in another
child process. Latency is measured per sample from the moment the reader handed its batch
over to the moment the publishing process's send of its datagram returned (the
``publish_latency_us`` of the stream summary), over the samples after the tare. A sample
waits in the reader's batch for up to its 20 ms read window only when the line is quiet; at
1 kHz a batch holds the one or few samples that arrived together.

Without ``--model`` a small model is trained and exported first (about 20 s).
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
from pathlib import Path
from typing import Any


def small_model(tmp: Path) -> Path:
    """A small model trained on the smoke scene and exported into ``tmp`` (about 20 s)."""
    from fbgforce import sim
    from fbgforce.recordings import dataset
    from fbgforce.model import modeldir as fm
    from fbgforce.export.exporter import export_model
    from fbgforce.trainer.train import train

    data = tmp / "smoke.csv"
    dataset.save(sim.simulate("smoke", seed=0), data)
    out = tmp / "model"
    fm.save(train([data], epochs=40, seed=0, filter="causal", progress=False), out)
    export_model(out)
    return out


def _drain(port: int, ready: Any, stop: Any, counts: Any) -> None:
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1 << 22)
    sock.bind(("127.0.0.1", port))
    sock.settimeout(0.1)
    ready.set()
    n = 0
    while not stop.is_set():
        try:
            sock.recv(256)
            n += 1
        except socket.timeout:
            pass
    counts.value = n


def _emulate(args: list[str]) -> None:
    from fbgforce.cli import main

    sys.stdout = open(os.devnull, "w")
    main(["emulate", *args])


def run(source: str, model: Path, seconds: float, rate: float, tmp: Path) -> dict[str, Any]:
    from fbgforce.interrogator.hyperion import HyperionReader
    from fbgforce.interrogator.publish import PublisherProcess
    from fbgforce.interrogator.reader import NativeReader
    from fbgforce.interrogator.stream import LiveEstimator, run_stream

    ctx = mp.get_context("spawn")
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        cmd_port = s.getsockname()[1]
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        udp_port = s.getsockname()[1]
    common = ["--scene", "smoke", "--seed", "5", "--rate", str(rate), "--duration",
              str(seconds + 0.5), "--linger", "0.5"]
    if source == "hyperion":
        emu_args = common + ["--protocol", "hyperion", "--command-port", str(cmd_port),
                             "--stream-port", str(cmd_port + 1)]
    else:
        link = tmp / f"tty-{source}"
        emu_args = common + ["--link", str(link)]
    ready, stop, counts = ctx.Event(), ctx.Event(), ctx.Value("l", 0)
    rx = ctx.Process(target=_drain, args=(udp_port, ready, stop, counts))
    rx.start()
    ready.wait(10)
    emu = ctx.Process(target=_emulate, args=(emu_args,))
    emu.start()
    if source == "hyperion":
        reader: Any = HyperionReader(f"hyperion://127.0.0.1:{cmd_port}")
    else:
        while not link.exists():
            time.sleep(0.01)
        reader = NativeReader(str(link))
    pub = PublisherProcess([f"udp://127.0.0.1:{udp_port}"])
    est = LiveEstimator(model)
    try:
        summary = run_stream(reader, est, duration=seconds, start_timeout=30, idle_timeout=2,
                             status=False, publication=pub)
    finally:
        reader.close()
        pub.close()
    emu.join(20)
    time.sleep(0.2)
    stop.set()
    rx.join(5)
    lat = summary["publish_latency_us"]
    return {"source": source, "samples": summary["samples"], "rate_hz": summary["rate_hz"],
            "lost_frames": summary["lost_frames"], "published": summary["published"][0]["sent"],
            "received": counts.value, "p50_us": lat["p50"], "p99_us": lat["p99"],
            "max_us": lat["max"], "compute_us_per_sample": summary["compute_us_per_sample"]}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--model", type=Path, help="exported model directory (default: train one)")
    ap.add_argument("--seconds", type=float, default=10.0)
    ap.add_argument("--rate", type=float, default=1000.0)
    ap.add_argument("--json", metavar="FILE", help="also write the rows as JSON")
    args = ap.parse_args(argv)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        model = args.model or small_model(Path(tmp))
        print(f"{'source':<10} {'samples':>8} {'rate Hz':>8} {'lost':>5} {'published':>9} "
              f"{'received':>9} {'p50 us':>8} {'p99 us':>8} {'max us':>8} {'compute us':>10}")
        for source in ("native", "hyperion"):
            r = run(source, model, args.seconds, args.rate, Path(tmp))
            rows.append(r)
            print(f"{r['source']:<10} {r['samples']:>8} {r['rate_hz']:>8.1f} {r['lost_frames']:>5} "
                  f"{r['published']:>9} {r['received']:>9} {r['p50_us']:>8.1f} "
                  f"{r['p99_us']:>8.1f} {r['max_us']:>8.1f} {r['compute_us_per_sample']:>10.1f}",
                  flush=True)
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
