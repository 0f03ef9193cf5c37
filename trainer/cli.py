"""Subcommands of the trainer: ``train``, ``evaluate``, ``analyze``, ``report`` (docs/cli.md)."""
from __future__ import annotations

import argparse
import sys
from typing import Any, Mapping

import numpy as np

from fbgforce import fileio
from fbgforce.cliargs import (add_data, add_model, add_seed, command, non_negative_float,
                               non_negative_int, positive_int)
from fbgforce.errors import InputError


def _check_files(paths: list[str], flag: str) -> None:
    for p in paths:
        fileio.check_input_file(p, flag)


def register(subparsers: Any) -> None:
    """Add ``train``, ``coverage``, ``evaluate``, ``analyze`` and ``report`` to the
    ``fbgforce`` command."""
    _register_train(subparsers)
    _register_coverage(subparsers)
    _register_evaluate(subparsers)
    _register_analyze(subparsers)
    _register_report(subparsers)


def _register_train(subparsers: Any) -> None:
    with command(subparsers, "train", _train,
                 help="train the hierarchical contact/force/location nets",
                 description="Fit preprocessing (tare, temperature coefficients, Gaussian "
                             "filter), split 8:1:1 by press, train the contact, force and "
                             "location nets (numpy, Adam, early stopping) and write a model "
                             "directory.") as p:
        add_data(p, "calibration recordings (CSV or npz, dataset contract), one device")
        p.add_argument("--out", required=True, metavar="MODEL_DIR", help="model directory to write")
        p.add_argument("--epochs", type=positive_int, default=200,
                       help="maximum epochs per net (early stopping usually ends sooner; default "
                            "200)")
        add_seed(p, "split, initialisation and shuffling seed")
        _add_preprocess_options(p)
        _add_net_options(p)


def _add_preprocess_options(p: argparse.ArgumentParser) -> None:
    """``train``'s filter, temperature reference, creep correction and contact decision."""
    from fbgforce.model.artifact import FILTER_KINDS
    from fbgforce.trainer.preprocess import DEFAULT_SIGMA, DEFAULT_SIGMA_MS
    from fbgforce.trainer.synthetic import IDLE_DRAWS, IDLE_MINUTES

    p.add_argument("--filter", choices=FILTER_KINDS, default="causal",
                   help="smoothing: causal (shipped, default), centred (offline, paper) or none")
    p.add_argument("--sigma", type=non_negative_float, default=None,
                   help=f"Gaussian sigma in samples (default {DEFAULT_SIGMA_MS:g} ms at the "
                        f"data's sample rate: {DEFAULT_SIGMA:g} at 1 kHz; 0 = no filter)")
    p.add_argument("--window", type=positive_int, default=None,
                   help="filter taps (causal) or half-width (centred); default ceil(3 sigma)")
    p.add_argument("--ref-shift", type=_ref_shift, default=None, metavar="auto|0..8",
                   help="the temperature grating's average before it compensates: auto "
                        "(default: 32 ms when that lowers the noise at rest by 5 %% or more, "
                        "else raw), 0 (raw) or N (2^N samples; docs/trainer.md)")
    p.add_argument("--creep", choices=("auto", "on", "off"), default="auto",
                   help="correct for the pad's fitted creep (its inverse or the tracker's term, "
                        "and creeping synthetic holds) only where the calibration establishes "
                        "it: a relaxation time clear of a rate effect, explained on held-out "
                        "releases, beyond what the noise fits (auto, default); wherever the "
                        "fit finds one (on); never (off). docs/trainer.md \"Evidence before "
                        "correction\"")
    p.add_argument("--decision", choices=("cusum", "schmitt"), default="cusum",
                   help="the contact decision's rise: a CUSUM on the contact net's margin "
                        "(cusum, default) or a Schmitt trigger with a rise count (schmitt), "
                        "each set from the calibration's rests (docs/runtime.md \"In use\"); "
                        "model.json keeps the other's fields in metadata.decision_rules")
    p.add_argument("--idle-pads", type=non_negative_int, default=None, metavar="N",
                   help=f"idle pads ({IDLE_MINUTES:g} minutes each of the calibration's rest "
                        "noise, no press) the CUSUM's threshold is also read on, so a pad left "
                        "alone for minutes raises no more false events than the rests allow "
                        f"(default {IDLE_DRAWS}; 0 = the rests alone; fewer train faster, "
                        "guard the idle pad's rare bad minutes less well and may miss a net "
                        "that reads a long rest as contact); docs/robustness.md \"An idle pad\"")
    p.add_argument("--track-calibration", choices=("on", "off"), default="on",
                   help="train the nets on the calibration as the at-rest tracker hands it on, "
                        "the tracker driven by a contact net fitted first, so they read loads "
                        "from the zero the runtime holds and not from the calibration's "
                        "wandering one (on, default; a tenth to a third more training time), or on "
                        "the recordings as tared (off). docs/trainer.md \"The tracker's zero\"")
    p.add_argument("--contact-plays", choices=("on", "off"), default="off",
                   help="let the contact net read the memory's play operators too (on), or "
                        "only the channels and the averages (off, default): at rest a play "
                        "follows the noise's record low, and a contact net that reads it "
                        "takes a pad left alone for minutes for a light press. "
                        "docs/trainer.md \"What the contact net reads\"")
    p.add_argument("--creep-inverse", action=argparse.BooleanOptionalAction, default=None,
                   help="take the pad's fitted creep out before the filter (--creep-inverse) or "
                        "let the at-rest tracker discount its recovery (--no-creep-inverse); "
                        "default: the inverse when the pad creeps more slowly than the memory's "
                        "longest average, which then cannot see it (docs/trainer.md \"The "
                        "pad's creep in use\")")


def _add_net_options(p: argparse.ArgumentParser) -> None:
    """``train``'s starting point, memory, widths and synthetic recordings."""
    p.add_argument("--init", metavar="MODEL_DIR", default=None,
                   help="start from another device's model (transfer learning)")
    p.add_argument("--train-fraction", type=float, default=1.0,
                   help="use only this fraction of the training presses (default 1)")
    p.add_argument("--memory", default=None, metavar="SPEC",
                   help="memory states after standardisation: none, ema, play, loc, both "
                        "(default both: ema, play and loc, or the --init model's), or e.g. "
                        "'ema:3,6+play:0.03,0.1+loc:5' (average shifts; play half-widths in "
                        "input standard deviations; the location averages' shift); "
                        "docs/trainer.md")
    p.add_argument("--restarts", default=None, metavar="SPEC",
                   help="initialisations tried per net, the lowest validation loss kept: N for "
                        "every net or e.g. 'force=3,location=2' (default contact=1, force=3, "
                        "location=1)")
    p.add_argument("--sizes", default=None, metavar="SPEC",
                   help="hidden widths of some nets, e.g. 'contact=70-50-20,location=70-50-40' "
                        "(default contact=36-26-10, force=50-30-16, location=36-26-20, about "
                        "half the paper's 70-50-20, 70-50-20, 70-50-40, for 8-9 %% of a "
                        "168 MHz Cortex-M4 at 1 kHz; the force net's weight decay then switches "
                        "off units it does not need); docs/trainer.md \"Widths and the "
                        "Cortex-M4\"")
    p.add_argument("--hold-augment", type=non_negative_float, default=None, metavar="SHARE",
                   help="share of the training presses the contact and force nets also see "
                        "held at their peak for 1.5-6 s (synthetic holds; default 0.2, "
                        "0 = off); docs/trainer.md \"Held grips\"")
    p.add_argument("--release-holds", choices=("auto", "on", "off"), default="off",
                   help="the force net also sees as many synthetic holds again on the presses' "
                        "releases, keeping the release's strain: only where the calibration "
                        "shows a friction (the gap between a press's rise and fall grows with "
                        "its load, not its speed, and predicts held-out presses; auto), always "
                        "(on) or never (off, default: they cost the egg-grasp loop). "
                        "docs/trainer.md \"Holds for a pad with friction\"")
    p.add_argument("--wander-holds", choices=("auto", "on", "off"), default="auto",
                   help="the force net also sees as many synthetic holds again whose load "
                        "wanders below the peak and back, the strain sticking at each turn and "
                        "sliding on the press's own rise or fall: only where the calibration "
                        "shows a friction (auto, default), always (on) or never (off). "
                        "docs/trainer.md \"Holds for a pad with friction\"")
    p.add_argument("--turn-guard", type=non_negative_float, default=None, metavar="MS",
                   help="the force net leaves out the MS milliseconds after each press's turn, "
                        "where a held load and an unloading one look alike: held grips read "
                        "less low, the start of each unloading worse (default 15, the causal "
                        "filter's length, with the creep inverse, else 0; docs/trainer.md "
                        "\"The turn\")")
    p.add_argument("--rest-augment", type=non_negative_float, default=None, metavar="SHARE",
                   help="share of the training presses the contact and force nets also see "
                        "after a rest of 3-60 s (synthetic long rests; default 0.2, 0 = off); "
                        "docs/trainer.md \"Long rests\"")


def _register_coverage(subparsers: Any) -> None:
    with command(subparsers, "coverage", _coverage,
                 help="what a calibration log covers and what a model trained on it "
                      "will not know",
                 description="Force range, a map of press locations, loading speeds, hold "
                             "lengths, temperature range and rest time of calibration "
                             "recordings, and what a model trained on them has not seen "
                             "(docs/lab-import.md).") as p:
        add_data(p, "calibration recordings (CSV or npz, dataset contract)", metavar="LOG")


def _register_evaluate(subparsers: Any) -> None:
    from fbgforce.evaluation.engines import ENGINES
    from fbgforce.trainer.evaluate import SPLITS

    with command(subparsers, "evaluate", _evaluate,
                 help="score a model on recordings with one engine",
                 description="Run a model on each recording (tared on its own contact-free "
                             "samples) with an engine and print the shared metrics.") as p:
        add_model(p)
        add_data(p)
        p.add_argument("--engine", choices=tuple(ENGINES), default="float",
                       help="float (numpy float64, default), onnx, fixed, cfloat, intref")
        p.add_argument("--split", choices=SPLITS, default="all",
                       help="score all samples (default) or one part of the by-press split made "
                            "with the model's seed")
        p.add_argument("--resample", action="store_true",
                       help="bring recordings sampled at another rate than the model's to its "
                            "rate (linear interpolation) instead of refusing them")


def _register_analyze(subparsers: Any) -> None:
    with command(subparsers, "analyze", _analyze,
                 help="auto-encoder study: how many features the four channels hold",
                 description="Train 4->k->4 auto-encoders (k = 1, 2, 3) on the compensated, "
                             "filtered contact samples and print their reconstruction RMSE "
                             "(paper §VII-D).") as p:
        add_data(p)
        p.add_argument("--plot", metavar="PNG", default=None,
                       help="write the 3-feature embedding (paper Fig. 10); needs matplotlib")
        add_seed(p)
        p.add_argument("--epochs", type=positive_int, default=30)


def _register_report(subparsers: Any) -> None:
    from fbgforce.trainer.preprocess import DEFAULT_SIGMA_MS

    with command(subparsers, "report", _report,
                 help="the paper's results side by side with ours",
                 description="Model-based (nominal, fitted) vs network (causal, centred, "
                             "unfiltered) on the held-out test presses; contact success overall "
                             "and above 5 N; errors by force range and at the boundary. Writes "
                             "report.md and report.json.") as p:
        add_data(p)
        add_model(p, "use this model for the causal network instead of training one",
                  required=False)
        p.add_argument("--out", metavar="DIR", default=None,
                       help="write report.md and report.json")
        p.add_argument("--epochs", type=positive_int, default=200)
        add_seed(p)
        p.add_argument("--sigma", type=non_negative_float, default=None,
                       help=f"Gaussian sigma in samples (default {DEFAULT_SIGMA_MS:g} ms at the "
                            "data's sample rate)")


def _train(args: argparse.Namespace) -> dict[str, Any]:
    from fbgforce.model import modeldir as fm
    from fbgforce.trainer.params import TrainParams
    from fbgforce.trainer.train import train

    _check_files(args.data, "--data")
    augment = {name: getattr(args, name) for name in ("hold_augment", "rest_augment", "idle_pads")
               if getattr(args, name) is not None}
    params = TrainParams(epochs=args.epochs, seed=args.seed, filter=args.filter,
                         memory=args.memory, restarts=_restarts(args.restarts),
                         sizes=_sizes(args.sizes),
                         sigma=args.sigma, window=args.window, ref_shift=args.ref_shift,
                         creep_inverse=args.creep_inverse, creep=args.creep,
                         release_holds=args.release_holds, wander_holds=args.wander_holds,
                         decision=args.decision, init=args.init,
                         track_calibration=args.track_calibration == "on",
                         contact_plays=args.contact_plays == "on",
                         train_fraction=args.train_fraction,
                         turn_guard_s=None if args.turn_guard is None else args.turn_guard / 1000.0,
                         **augment)
    fileio.check_output_dir(args.out, "--out")
    model = train(args.data, params)
    fm.save(model, args.out, "--out")
    md = model.metadata
    test = md["metrics"]["test"] or {}
    from fbgforce.evaluation.metrics import headline
    print(f"fbgforce train: wrote {args.out} in {md['times_s']['train']:.1f} s; test: "
          f"{headline(test)}; {_reference_summary(md['temperature']['reference'])}; "
          f"{_creep_summary(md['creep'], model.preprocess)}", file=sys.stderr)
    from fbgforce.trainer.coverage import coverage_lines

    for c in md.get("corrections", []):
        print(f"fbgforce train: correction {c['name']}: {'on' if c['applied'] else 'off'} "
              f"({c['why']})", file=sys.stderr)
    for line in coverage_lines(md["coverage"]):
        print(f"fbgforce train: {line}", file=sys.stderr)
    for warning in md.get("warnings", []):
        print(f"fbgforce train: warning: {warning}", file=sys.stderr)
    return {"model": str(args.out), "seconds": md["times_s"]["prepare"] + md["times_s"]["train"],
            "epochs": {k: v["epochs_run"] for k, v in md["training"].items()},
            "filter": md["filter"], "temp_coeff": md["temperature"]["temp_coeff"],
            "temperature_reference": md["temperature"]["reference"],
            "val": md["metrics"]["val"], "test": md["metrics"]["test"],
            "coverage": md["coverage"], "corrections": md.get("corrections", []),
            "warnings": md.get("warnings", [])}


def _ref_shift(text: str) -> int | None:
    """argparse type of ``--ref-shift``: ``auto`` (None) or a shift 0 .. MAX_REF_SHIFT."""
    from fbgforce import contract

    if text == "auto":
        return None
    top = contract.LIMIT["MAX_REF_SHIFT"]
    try:
        value = int(text)
    except ValueError:
        value = -1
    if not 0 <= value <= top:
        raise argparse.ArgumentTypeError(f"must be auto or 0 .. {top}, not {text}")
    return value


def _reference_summary(ref: Mapping[str, Any]) -> str:
    """The temperature reference's choice (trainer.preprocess.choose_ref_shift) in words."""
    if ref.get("given"):
        return f"temperature reference as given: --ref-shift {ref['ref_shift']}"
    noise = ref["rest_noise_pm2"]
    if noise["raw"] is None:
        return "temperature reference raw (no rest samples to measure its noise)"
    figures = f"rest noise {noise['raw']:.3g} pm^2 raw, {noise['averaged']:.3g} averaged"
    if ref["ref_shift"]:
        return f"temperature reference averaged over 2^{ref['ref_shift']} samples ({figures})"
    return f"temperature reference raw ({figures} over 2^{ref['candidate']} samples)"


def _creep_summary(creep: Mapping[str, Any], pre: Any) -> str:
    """The pad's fitted creep (trainer.creep_fit.fit_creep), whether the model corrects for it and
    why (trainer.creep_evidence.creep_choice), in words."""
    found = creep.get("fitted", creep)
    evidence = creep.get("evidence") or {}
    if not creep["magnitude"]:
        if not found.get("magnitude"):
            return "no pad creep found"
        return (f"pad creep fitted at {100 * found['magnitude']:.1f} % over "
                f"{found['time_constant_s']:.2g} s, not corrected for: "
                f"{evidence.get('why', 'not established')}")
    what = "taken out before the filter" if pre.creep else "discounted by the at-rest tracker"
    return (f"pad creep {100 * creep['magnitude']:.1f} % over {creep['time_constant_s']:.2g} s, "
            f"{what} ({evidence.get('why', 'established')})")


def _coverage(args: argparse.Namespace) -> dict[str, Any]:
    from fbgforce.recordings import dataset
    from fbgforce.trainer.coverage import coverage, coverage_lines

    _check_files(args.data, "--data")
    cov = coverage([dataset.load(p) for p in args.data])
    if not args.json:
        print("\n".join(coverage_lines(cov)))
    cov["data"] = list(args.data)
    return cov


def _restarts(spec: str | None) -> int | dict[str, int] | None:
    """``--restarts``: ``N`` or ``net=N,net=N``; InputError naming the option otherwise."""
    if spec is None:
        return None
    try:
        if "=" not in spec:
            value: int | dict[str, int] = int(spec)
            counts = [value]
        else:
            value = {k.strip(): int(v) for k, v in (part.split("=", 1) for part in spec.split(","))}
            counts = list(value.values())
    except ValueError:
        raise InputError(f"expected N or net=N,... (e.g. force=3,location=2), not {spec!r}",
                         column="--restarts") from None
    if any(c < 1 for c in counts):
        raise InputError(f"every count must be at least 1, not {spec!r}", column="--restarts")
    return value


def _sizes(spec: str | None) -> dict[str, list[int]] | None:
    """``--sizes``: ``net=W-W-W,net=W-W`` (hidden widths, input to output); InputError naming
    the option otherwise. The ranges are TrainParams' to check."""
    if spec is None:
        return None
    try:
        return {k.strip(): [int(w) for w in v.split("-")]
                for k, v in (part.split("=", 1) for part in spec.split(","))}
    except ValueError:
        raise InputError(f"expected net=W-W-W,... (e.g. contact=70-50-20,location=70-50-40), "
                         f"not {spec!r}", column="--sizes") from None


def _evaluate(args: argparse.Namespace) -> dict[str, Any]:
    from fbgforce.evaluation.metrics import headline
    from fbgforce.trainer.evaluate import evaluate

    _check_files(args.data, "--data")
    out = evaluate(args.model, args.data, engine=args.engine, split=args.split,
                   resample=args.resample)
    if not args.json:
        print(f"{args.engine}: {headline(out)} (n={out['n_samples']})")
        for line in (_onset_against_bound(out), _holds_line(out)):
            if line:
                print(line)
    for warning in out["warnings"]:
        print(f"fbgforce evaluate: warning: {warning}", file=sys.stderr)
    return out


def _onset_against_bound(out: dict[str, Any]) -> str | None:
    """The median onset beside the quickest the recordings' noise allows on the same presses
    (``noise_allows``), or None when either is not there."""
    timing, allows = out.get("contact_timing"), out.get("noise_allows")
    onset = (timing or {}).get("onset_delay_ms", {}).get("median")
    if onset is None or not allows or not allows.get("onset_bound_ms"):
        return None
    from fbgforce.evaluation.onset_bound import delay_text, lag_text, median_onset_ms

    above = out.get("contact_accuracy_above_1N")
    return (f"onset: median {onset:.1f} ms after the label; the noise "
            f"({allows['noise_pm']:.1f} pm{lag_text(allows)}) allows no decision sooner than "
            + delay_text(median_onset_ms(allows))
            + f" on these {allows['presses']} presses"
            + ("" if above is None or allows["detected_above_1N"] is None else
               f"; samples above 1 N found {100 * above:.2f} %, at best "
               f"{100 * allows['detected_above_1N']:.2f} %"))


def _holds_line(out: dict[str, Any]) -> str | None:
    """The force over the held grips, all of them and away from the load's turns
    (``holds``), or None without holds."""
    holds = out.get("holds")
    if not holds or holds["force_bias_N"] is None:
        return None
    text = (f"holds: {holds['holds']} ({holds['seconds']:.0f} s), force bias "
            f"{holds['force_bias_N']:+.3f} N, RMSE {holds['rmse_force_N']:.3f} N")
    away = holds["away_from_turns"]
    if away["force_bias_N"] is not None:
        text += (f"; more than {away['after_turn_s']:g} s after a turn of the load "
                 f"({100 * away['fraction']:.0f} % of the held samples): "
                 f"{away['force_bias_N']:+.3f} N, {away['rmse_force_N']:.3f} N")
    direction = holds.get("by_direction")
    if direction and None not in (direction[d]["force_bias_N"] for d in ("rising", "falling")):
        text += (f"; load rising {direction['rising']['force_bias_N']:+.3f} N, falling "
                 f"{direction['falling']['force_bias_N']:+.3f} N")
    return text


def _analyze(args: argparse.Namespace) -> dict[str, Any]:
    from fbgforce.trainer.analysis import autoencoder_study, plot_embedding
    from fbgforce.trainer.data import load_datasets
    from fbgforce.trainer.train import prepare

    _check_files(args.data, "--data")
    if args.plot:
        fileio.check_output_file(args.plot, "--plot")
    ds_list, described = load_datasets(args.data)
    data = prepare(ds_list, seed=args.seed, sources=[d["path"] for d in described])
    rows = np.flatnonzero(data.contact)
    if rows.size < 10:
        raise InputError("fewer than 10 contact samples to analyse", path=args.data[0],
                         column="contact")
    feats = data.feats[rows]
    z = (feats - feats.mean(axis=0)) / np.maximum(feats.std(axis=0), 1e-3)
    res = autoencoder_study(z, seed=args.seed, epochs=args.epochs)
    emb, emb_rows = res.pop("embedding", None), res.pop("embedding_rows", None)
    if args.plot:
        if emb is None:
            raise InputError("no 3-feature embedding to plot", column="--plot")
        r = rows[emb_rows]
        res["plot"] = (args.plot if plot_embedding(emb, data.force_N[r], data.x_mm[r],
                                                   data.y_mm[r], args.plot) else None)
        if res["plot"] is None:
            print("fbgforce analyze: matplotlib is not installed; no plot written",
                  file=sys.stderr)
    if not args.json:
        print("k  auto-encoder RMSE  PCA RMSE   (standardised units)")
        for k, a, b in zip(res["ks"], res["rmse"], res["rmse_pca"]):
            print(f"{k}  {a:17.3g}  {b:8.3g}")
    res["data"] = [d["path"] for d in described]
    return res


def _report(args: argparse.Namespace) -> dict[str, Any]:
    from fbgforce.trainer.report import build_report, to_markdown, write

    _check_files(args.data, "--data")
    if args.out:
        fileio.check_output_dir(args.out, "--out")
    rep = build_report(args.data, model_dir=args.model, epochs=args.epochs, seed=args.seed,
                       sigma=args.sigma)
    if args.out:
        md, js = write(rep, args.out)
        rep["files"] = [str(md), str(js)]
    if not args.json:
        print(to_markdown(rep))
    return rep
