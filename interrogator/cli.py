"""``fbgforce emulate | stream | record``: serial I/O commands (docs/serial.md, docs/cli.md)."""
from __future__ import annotations

import argparse
import math
import sys
from typing import Any

from fbgforce import signals
from fbgforce.cliargs import (add_data, add_model, add_seed, command, non_negative_int,
                               positive_float, positive_int)
from fbgforce.errors import InputError


def _add_stop_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--duration", type=positive_float, metavar="S",
                   help="stop S seconds after the first sample (default: run until stopped)")
    p.add_argument("--samples", type=positive_int, metavar="N", help="stop after N samples")
    p.add_argument("--idle-timeout", type=positive_float, metavar="S",
                   help="stop when no sample arrived for S seconds (default: wait, reconnecting)")
    p.add_argument("--start-timeout", type=positive_float, metavar="S",
                   help="fail (exit 2) if the first sample has not arrived after S seconds "
                        "(default: 5 s, or --duration/--idle-timeout if longer, when any stop "
                        "option is given; otherwise wait for the device until stopped)")
    p.add_argument("--baud", type=positive_int, default=None,
                   help="line speed for real UARTs (default 3000000; ptys/sockets ignore it)")
    p.add_argument("--quiet", action="store_true", help="no live status on stderr")


def _add_peak_map_option(p: argparse.ArgumentParser, text: str) -> None:
    p.add_argument("--peak-map", metavar="MAP", default=None,
                   help=text + "; MAP = five CH:K (K-th peak of channel CH) or CH:LO-HI (the one "
                               "peak between LO and HI nm), for wl1,wl2,wl3,wl4,wlT")


def _peak_map(text: str | None, model_dir: str | None = None) -> Any:
    """--peak-map, else the model's ``hyperion_peak_map`` metadata, else the default."""
    from fbgforce.interrogator.hyperion import PeakMap, peak_map_from_model

    if text is not None:
        try:
            return PeakMap.parse(text)
        except ValueError as exc:
            raise InputError(str(exc), column="--peak-map") from None
    if model_dir is not None:
        try:
            found = peak_map_from_model(model_dir)
        except ValueError as exc:
            raise InputError(f"hyperion_peak_map: {exc}", path=f"{model_dir}/model.json") from None
        if found is not None:
            return found
    return PeakMap.default()


def _protocol(args: argparse.Namespace) -> str:
    """--protocol, or what the source implies (hyperion:// -> hyperion, else native)."""
    if args.protocol is not None:
        return str(args.protocol)
    return "hyperion" if args.port.startswith("hyperion://") else "native"


def _open_reader(args: argparse.Namespace, model_dir: str | None = None, **kw: Any) -> Any:
    from fbgforce.interrogator.reader import open_reader

    protocol = _protocol(args)
    hyperion = args.port.startswith("hyperion://")
    if hyperion != (protocol == "hyperion"):
        raise InputError("hyperion:// sources speak --protocol hyperion and only they do",
                         column="--protocol")
    try:
        return open_reader(args.port, protocol, peak_map=_peak_map(args.peak_map, model_dir)
                           if protocol == "hyperion" else None, **kw, **_baud(args))
    except ValueError as exc:
        raise InputError(str(exc), column="--source") from None


def register(subparsers: Any) -> None:
    """Add ``emulate``, ``stream`` and ``record``."""
    _register_emulate(subparsers)
    _register_stream(subparsers)
    _register_record(subparsers)


def _register_emulate(subparsers: Any) -> None:
    with command(subparsers, "emulate", _emulate,
                 help="virtual interrogator on a pseudo-terminal or TCP (plays a scene in real "
                      "time)",
                 description="Play a simulated scene (or a dataset file) in real time as an FBG "
                             "interrogator would: on a pseudo-terminal, native frames pushed at "
                             "--rate or FiSpec-style answers to '?>'/'P>' polls; on TCP "
                             "(--protocol hyperion), a Luna/Micron Optics Hyperion's command "
                             "port and peak stream. The scene's dropout effect becomes real "
                             "line faults. Prints the device path(s) or URL; playback starts "
                             "when every port has a client. Protocols: docs/protocol.md.") as p:
        src = p.add_mutually_exclusive_group(required=True)
        src.add_argument("--scene", help="built-in scene name or scene TOML path")
        add_data(src, "play a dataset file (CSV/npz) instead", nargs=None, required=False)
        p.add_argument("--pty", action="store_true", default=True,
                       help="serve on a new pseudo-terminal (the transport of native and fispec)")
        p.add_argument("--protocol", choices=("native", "fispec", "hyperion"), default="native",
                       help="native frames, FiSpec polls (pty) or a Hyperion instrument (TCP)")
        p.add_argument("--address", default="127.0.0.1",
                       help="hyperion: address to listen on (default 127.0.0.1)")
        p.add_argument("--command-port", type=non_negative_int, default=51971,
                       help="hyperion: command port (default 51971; 0 = any free port)")
        p.add_argument("--stream-port", type=non_negative_int, default=51972,
                       help="hyperion: peak stream port (default 51972; 0 = any free port)")
        _add_peak_map_option(p, "hyperion: which channel and peak carries FBG 1..4 and T "
                                "(default 1:1,1:2,1:3,1:4,1:5)")
        p.add_argument("--rate", type=positive_float, default=1000.0,
                       help="samples per second of playback (default 1000)")
        p.add_argument("--loadcell", action="store_true",
                       help="open a second pty with the stage/load-cell line protocol")
        add_seed(p, "scene seed (default: the scene's); also seeds the fault details",
                 type=non_negative_int, default=None)
        p.add_argument("--device", type=non_negative_int, default=None,
                       help="scene device number")
        p.add_argument("--duration", type=positive_float, metavar="S",
                       help="play at most S seconds (default: the whole recording)")
        _add_playback_options(p)


def _add_playback_options(p: argparse.ArgumentParser) -> None:
    """``emulate``'s line faults, links and how playback starts and ends."""
    p.add_argument("--faults", metavar="SPEC", default=None,
                   help="extra line faults per sample, e.g. drop=0.01,flip=0.01,truncate=0.005,"
                        "garbage=0.005 (on top of the scene's dropout column)")
    p.add_argument("--link", metavar="PATH", help="also make PATH a symlink to the device")
    p.add_argument("--loadcell-link", metavar="PATH", help="symlink to the load-cell device")
    p.add_argument("--no-wait", action="store_true",
                   help="start playing at once instead of waiting for clients")
    p.add_argument("--linger", type=float, default=2.0, metavar="S",
                   help="after the last sample keep the ports open until clients close, at "
                        "most S seconds (default 2)")
    p.add_argument("--loop", action="store_true", help="repeat the recording until stopped")


def _register_stream(subparsers: Any) -> None:
    with command(subparsers, "stream", _stream,
                 help="live estimation from an interrogator through the C runtime",
                 description="Read an interrogator (device path or pyserial URL), tare on the "
                             "first samples, estimate contact, force and location for every "
                             "sample with the fixed-point C runtime, show a one-line live status "
                             "on stderr and optionally write the estimates as CSV.") as p:
        p.add_argument("--port", "--source", dest="port", required=True, metavar="DEV",
                       help="device path, pyserial URL (/dev/ttyUSB0, socket://host:port, "
                            "loop://) or hyperion://HOST[:PORT]")
        add_model(p)
        p.add_argument("--protocol", choices=("native", "fispec", "hyperion"), default=None,
                       help="default: hyperion for hyperion:// sources, else native")
        _add_peak_map_option(p, "hyperion: which channel and peak carries FBG 1..4 and T "
                                "(default: the model's hyperion_peak_map metadata, else "
                                "1:1,...,1:5)")
        _add_output_options(p)
        p.add_argument("--engine", choices=("fixed", "float"), default="fixed",
                       help="fixed (C fixed-point runtime, default) or float (numpy reference)")
        p.add_argument("--tare-samples", type=non_negative_int, default=200,
                       help="tare on the first N samples, fingertip unloaded (default 200 = "
                            "0.2 s; 0 = use the model's training baseline); a tare or reset "
                            "command averages as many (200 with 0)")
        p.add_argument("--channels", type=positive_int, default=5,
                       help="gratings per frame (default 5: FBG 1..4 and T; with more, the "
                            "first five are FBG 1..4 and T)")
        _add_stop_options(p)


def _add_output_options(p: argparse.ArgumentParser) -> None:
    """Where ``stream`` sends its estimates and takes its commands, and on which CPUs."""
    p.add_argument("--publish", metavar="URL", action="append", default=[],
                   help="also publish every estimate: udp://HOST:PORT (one datagram per sample, "
                        "docs/protocol.md), lcm://CHANNEL[?url=LCM_URL] (needs the [lcm] "
                        "extra) or ros2:///NAMESPACE[?frame_id=ID&domain=N] (ROS 2 topics "
                        "NAMESPACE/wrench and NAMESPACE/contact, needs the [ros2] extra, "
                        "docs/ros2.md); may be repeated")
    p.add_argument("--control", metavar="udp://HOST:PORT", default=None,
                   help="also take tare and reset commands on this UDP port (control datagrams, "
                        "docs/protocol.md; port 0 = any free port, printed on stderr); "
                        "ros2:// outputs serve NAMESPACE/tare and NAMESPACE/reset without it")
    p.add_argument("--cpu", type=non_negative_int, metavar="N",
                   help="run the estimator on CPU N alone and the publishing process on the "
                        "other CPUs, so that they never take turns on one core (docs/ros2.md)")
    p.add_argument("--out", metavar="FILE.csv", help="write samples and estimates as CSV")


def _register_record(subparsers: Any) -> None:
    with command(subparsers, "record", _record,
                 help="record a calibration log (interrogator + stage/load cell) as a dataset",
                 description="Read the interrogator and the stage/load-cell port, join the "
                             "samples on the sample counter and write a dataset file "
                             "(docs/dataset.md) ready for 'fbgforce train'.") as p:
        p.add_argument("--port", "--source", dest="port", required=True, metavar="DEV",
                       help="interrogator device, URL or hyperion://HOST[:PORT]")
        p.add_argument("--loadcell-port", required=True, metavar="DEV2",
                       help="stage/load-cell device or URL")
        p.add_argument("--out", required=True, metavar="FILE.csv",
                       help="dataset to write (.csv/.npz), or a rosbag2 log (.mcap; needs the "
                            "[ros2] extra)")
        add_model(p, "with an .mcap --out: also log the fixed-point runtime's estimates "
                     "(/fbgforce/contact, /fbgforce/wrench) of the recorded samples",
                  required=False)
        p.add_argument("--tare-samples", type=non_negative_int, default=200,
                       help="with --model: tare on the first N recorded samples (default 200)")
        p.add_argument("--protocol", choices=("native", "fispec", "hyperion"), default=None,
                       help="default: hyperion for hyperion:// sources, else native")
        _add_peak_map_option(p, "hyperion: which channel and peak carries FBG 1..4 and T "
                                "(default 1:1,1:2,1:3,1:4,1:5)")
        p.add_argument("--rate", type=positive_float, default=1000.0,
                       help="device sample rate, for time stamps when the protocol has none "
                            "(fispec)")
        p.add_argument("--loadcell-baud", type=positive_int, default=115200)
        _add_stop_options(p)


def _emulate(args: argparse.Namespace) -> dict[str, Any]:
    from fbgforce.interrogator import emulator as E

    try:
        rates = E.parse_fault_rates(args.faults)
    except ValueError as exc:
        raise InputError(str(exc), column="--faults") from None
    if args.linger < 0:
        raise InputError("must be >= 0", column="--linger")
    if args.data is not None:
        from fbgforce import fileio

        fileio.check_input_file(args.data, "--data")
    hyperion = args.protocol == "hyperion"
    if hyperion and args.link:
        raise InputError("hyperion serves TCP ports, not a pty: use --command-port/--stream-port",
                         column="--link")
    peak_map = _peak_map(args.peak_map) if hyperion else None
    playback = E.load_playback(args.scene, args.data, seed=args.seed, device=args.device)
    plan = E.plan_faults(len(playback), rates=rates, dropout=playback.dropout,
                         seed=args.seed if args.seed is not None else 0)
    if hyperion:
        try:
            em: Any = E.HyperionEmulator(
                playback, rate=args.rate, faults=plan, address=args.address,
                command_port=args.command_port, stream_port=args.stream_port, peak_map=peak_map,
                wait_client=not args.no_wait, linger=args.linger, loop=args.loop,
                loadcell=args.loadcell, loadcell_link=args.loadcell_link)
        except OSError as exc:
            raise InputError(f"cannot listen on {args.address}: {exc.strerror or exc}",
                             column="--command-port") from None
    else:
        em = E.Emulator(playback, protocol=args.protocol, rate=args.rate, faults=plan,
                        loadcell=args.loadcell, seed=args.seed, wait_client=not args.no_wait,
                        linger=args.linger, loop=args.loop, link=args.link,
                        loadcell_link=args.loadcell_link)
    out = sys.stderr if args.json else sys.stdout
    for role, path in em.paths.items():
        print(f"{role}: {path}", file=out, flush=True)
    if not args.no_wait:
        print("emulate: waiting for a client on every port (Ctrl-C to stop)", file=sys.stderr,
              flush=True)
    max_samples = None if args.duration is None else math.ceil(args.duration * args.rate)
    stopped_by = None
    try:
        stats = em.run(max_samples=max_samples)
    except KeyboardInterrupt as exc:  # Ctrl-C or SIGTERM: how an endless emulator ends
        stats, stopped_by = em.stats, signals.signal_name(exc)
    finally:
        em.close()
    ports = {"address": em.address, "command_port": em.command_port,
             "stream_port": em.stream_port, "peak_map": peak_map.text()} if hyperion else {}
    result = {"protocol": args.protocol, "rate_hz": args.rate, **em.paths, **ports,
              "samples": len(playback), "fault_plan": {
                  name: int((plan == code).sum()) for code, name in enumerate(E.FAULTS) if code},
              **stats.as_dict(), "interrupted": stopped_by is not None, "signal": stopped_by}
    if not args.json:
        print(f"emulate: played {stats.samples_played} samples, {stats.frames_sent} intact frames"
              f" ({stats.dropped} dropped, {stats.flipped} flipped, {stats.truncated} truncated, "
              f"{stats.garbage_bursts} garbage bursts)", file=sys.stderr)
    return result


def _baud(args: argparse.Namespace) -> dict[str, Any]:
    return {} if args.baud is None else {"baudrate": args.baud}


def _start_timeout(args: argparse.Namespace) -> float | None:
    from fbgforce.interrogator.nodata import start_timeout_for

    return start_timeout_for(args.start_timeout, args.duration, args.samples, args.idle_timeout)


def _stream(args: argparse.Namespace) -> dict[str, Any]:
    import time

    from fbgforce.interrogator.nodata import no_data_error
    from fbgforce.interrogator.publish import PublisherProcess, separate_cpus
    from fbgforce.interrogator.stream import N_GRATINGS, LiveEstimator, run_stream

    if args.channels < N_GRATINGS:
        raise InputError(f"the model reads {N_GRATINGS} gratings per sample (FBG 1..4 and T); "
                         f"frames of {args.channels} cannot feed it", column="--channels")
    publish_cpus = None if args.cpu is None else \
        sorted(separate_cpus(args.cpu, publishing=bool(args.publish)))
    est = LiveEstimator(args.model, engine=args.engine, tare_samples=args.tare_samples)
    control = None
    if args.control is not None:
        from fbgforce.interrogator.control import ControlServer

        control = ControlServer(args.control)
        print(f"stream: control on {control.url}", file=sys.stderr, flush=True)
    publication = None
    try:
        # The outputs are open before the reader: a sample never waits for them to start.
        publication = PublisherProcess(args.publish, cpus=publish_cpus) if args.publish else None
        sources: list[Any] = [s for s in (control, publication) if s is not None]
        reader = _open_reader(args, args.model, channels=args.channels)
        protocol = _protocol(args)
        started = time.monotonic()
        try:
            result = run_stream(reader, est, out=args.out, duration=args.duration,
                                max_samples=args.samples, idle_timeout=args.idle_timeout,
                                start_timeout=_start_timeout(args), status=not args.quiet,
                                publication=publication, commands=sources)
        finally:
            reader.close()
    finally:
        if publication is not None:
            publication.close()
        if control is not None:
            control.close()
    if result["received"] == 0:
        raise no_data_error(args.port, protocol, time.monotonic() - started,
                            reader.stats(), reader.link.last_error, baud=args.baud,
                            interrupted=result["interrupted"])
    result = {"port": args.port, "protocol": protocol, **result, "cpu": args.cpu,
              "publish_cpus": publish_cpus if args.publish else None,
              "control": None if control is None else control.stats()}
    if not args.json:
        print(f"stream: {result['samples']} samples estimated, {result['lost_frames']} lost, "
              f"{result['bad_frames']} bad frames" + (f", written to {args.out}" if args.out else ""),
              file=sys.stderr)
    return result


def _record(args: argparse.Namespace) -> dict[str, Any]:
    import time

    from fbgforce.interrogator.nodata import no_data_error
    from fbgforce.interrogator.reader import LoadCellReader
    from fbgforce.interrogator.record import run_record

    estimator = None
    if args.model is not None:
        from fbgforce.interrogator.stream import LiveEstimator

        estimator = LiveEstimator(args.model, tare_samples=args.tare_samples)
    reader = _open_reader(args)
    loadcell = LoadCellReader(args.loadcell_port, baudrate=args.loadcell_baud)
    # Open both now: a device that waits for its clients starts only when both are there.
    reader.link.open()
    loadcell.link.open()
    started = time.monotonic()
    try:
        result = run_record(reader, loadcell, args.out, duration=args.duration,
                            max_samples=args.samples, idle_timeout=args.idle_timeout,
                            start_timeout=_start_timeout(args), rate_hz=args.rate,
                            status=not args.quiet, estimator=estimator)
    except InputError as exc:
        # Nothing joined: when the interrogator itself was silent, say what was tried there.
        if exc.column == "--port" and reader.stats().get("frames", 0) == 0:
            raise no_data_error(args.port, _protocol(args), time.monotonic() - started,
                                reader.stats(), reader.link.last_error, baud=args.baud) from None
        raise
    finally:
        reader.close()
        loadcell.close()
    if not args.json:
        print(f"record: wrote {result['samples']} samples ({result['presses']} presses) to "
              f"{result['out']}; unmatched {result['unmatched_frames']} frames / "
              f"{result['unmatched_loadcell_lines']} lines, lost {result['lost_frames']}",
              file=sys.stderr)
    return result
