"""What a run writes: tradeoff.json, tradeoff.csv, tradeoff.md (table and summary paragraph)
and, through :mod:`fbgforce.tradeoff.plot`, tradeoff.png."""
from __future__ import annotations

import csv
import json
from pathlib import Path
from typing import Any, Callable

from fbgforce.jsonutil import json_default
from fbgforce.tradeoff.plot import write_plot
from fbgforce.tradeoff.scoring import CONTACT_SLACK, MATCH_RMSE_FACTOR, METRIC_KEYS

def _fmt(v: Any, spec: str = ".3g") -> str:
    if v is None:
        return "–"
    if isinstance(v, bool):
        return "yes" if v else ""
    if isinstance(v, float):
        return format(v, spec)
    return str(v)


def _ns(v: float | None) -> str:
    if v is None:
        return "–"
    return f"{v / 1000:.1f} µs" if v >= 10000 else f"{v:.0f} ns"


def summary_paragraph(res: dict[str, Any]) -> str:
    """One paragraph, written from the numbers: what each step in cost buys."""
    rows = [r for r in res["rows"] if r.get("status") == "ok"]
    ref = next((r for r in rows if r.get("is_reference")), None)
    if ref is None:
        return "No configuration could be evaluated, so there is nothing to compare."
    by = {(r["variant"], r["engine"]): r for r in rows}
    parts = [_reference_sentence(ref), *_engine_sentences(by, ref["variant"]),
             _ratio_sentence(res.get("ratios", {})), _filter_sentence(rows, ref),
             _width_sentence(rows, ref), _memory_sentence(rows, ref), _paper_sentence(rows),
             _front_sentence(rows), *_m4_sentences(rows, by, ref["variant"]),
             _cheapest_sentence(rows, ref)]
    return " ".join(p for p in parts if p is not None)


def _accuracy(r: dict[str, Any]) -> str:
    """A row's four accuracy figures, as the paragraph quotes them."""
    return (f"force {r['rmse_force_N']:.2f} N, x {r['rmse_x_mm']:.2f} mm, y {r['rmse_y_mm']:.2f}"
            f" mm, contact {100 * r['contact_accuracy']:.1f} %")


def _relative(x: float | None) -> str:
    """A time ratio in words: slower or faster than, whichever side of 1 it lies."""
    if not x:
        return "–"
    return f"{x:.1f}× slower than" if x >= 1 else f"{1 / x:.1f}× faster than"


def _reference_sentence(ref: dict[str, Any]) -> str:
    """What the reference is and what it costs on the host."""
    return (f"The reference is the paper-size network ({ref['macs_nets']} MACs) with the "
            f"shipped causal filter (σ = {ref['sigma']:g} samples, {ref['filter_delay_ms']:.1f}"
            f" ms delay) in numpy float64: {_accuracy(ref)}, {_ns(ref.get('host_batch_ns'))} per "
            f"sample batched, {_ns(ref.get('host_single_ns'))} per single-sample call.")


def _engine_sentences(by: dict[tuple[str, str], dict[str, Any]], tag: str) -> list[str]:
    """One sentence per other engine that ran the reference variant: its error, its times
    and its model's size."""
    parts = []
    for name, what in (("onnx", "onnxruntime float32"), ("cfloat", "the C float build"),
                       ("fixed", "the C int16 fixed-point runtime"),
                       ("fixed-int8", "int8 weights"), ("fixed-int8-qat", "int8 weights after QAT")):
        r = by.get((tag, name))
        if r is None:
            continue
        parts.append(f"{what[0].upper() + what[1:]} gives error index {r['error_index']:.3f} "
                     f"({_accuracy(r)}) at {_ns(r.get('host_batch_ns'))} batched / "
                     f"{_ns(r.get('host_single_ns'))} single"
                     + (f", {r['model_bytes']} model bytes" if r.get("model_bytes") else "") + ".")
    return parts


def _ratio_sentence(ratios: dict[str, Any]) -> str | None:
    """onnxruntime's and numpy's times relative to the C int16 runtime's, when it was timed."""
    if not ratios.get("onnx_over_fixed_batch"):
        return None
    return (f"Same model, same run, relative to the C int16 runtime: batched, onnxruntime is "
            f"{_relative(ratios['onnx_over_fixed_batch'])} it and numpy "
            f"{_relative(ratios['float_over_fixed_batch'])} it; in single-sample calls "
            f"onnxruntime is {_relative(ratios['onnx_over_fixed_single'])} it and numpy "
            f"{_relative(ratios['float_over_fixed_single'])} it.")


def _filter_sentence(rows: list[dict[str, Any]], ref: dict[str, Any]) -> str | None:
    """What filter delay buys: the paper-width float rows with the reference's memory, causal
    filters first, by delay."""
    filt = sorted((r for r in rows if r["width"] == "paper" and r["engine"] == "float"
                   and r.get("memory") == ref.get("memory")),
                  key=lambda r: (not r["causal"], r["filter_delay_ms"]))
    if len(filt) <= 1:
        return None
    desc = "; ".join(
        f"{'no filter' if r['filter'] == 'none' else r['filter'] + ' σ=' + format(r['sigma'], 'g')}"
        f" ({r['filter_delay_ms']:.1f} ms{' look-ahead' if not r['causal'] else ''}): "
        f"force {r['rmse_force_N']:.2f} N, y {r['rmse_y_mm']:.2f} mm, "
        f"index {r['error_index']:.2f}" for r in filt)
    return f"Filter delay against accuracy at paper width: {desc}."


def _width_sentence(rows: list[dict[str, Any]], ref: dict[str, Any]) -> str | None:
    """What network width buys: the float rows with the reference's filter and memory,
    widest first."""
    widths = sorted((r for r in rows if r["engine"] == "float" and r["filter"] == ref["filter"]
                     and r["sigma"] == ref["sigma"] and r.get("memory") == ref.get("memory")),
                    key=lambda r: -r["macs_nets"])
    if len(widths) <= 1:
        return None
    desc = "; ".join(f"{r['width']} ({r['macs_nets']} MACs): index {r['error_index']:.2f}, "
                     f"{_ns(r.get('host_batch_ns'))}" for r in widths)
    return f"Network width: {desc}."


def _memory_sentence(rows: list[dict[str, Any]], ref: dict[str, Any]) -> str | None:
    """What the memory costs and buys: the reference's engine, width and filter with every
    memory, fewest states first."""
    mems = sorted((r for r in rows if r["engine"] == ref["engine"] and r["width"] == ref["width"]
                   and r["filter"] == ref["filter"] and r["sigma"] == ref["sigma"]
                   and r.get("status") == "ok"), key=lambda r: r.get("memory_states", 0))
    if len(mems) <= 1:
        return None
    desc = "; ".join(
        f"{r['memory']} ({r['memory_states']} states, {r['memory_state_bytes']} "
        f"bytes of state, {r['macs_nets']} MACs): {_accuracy(r)}, index {r['error_index']:.3f}, "
        f"{_ns(r.get('host_batch_ns'))}" for r in mems)
    return f"Memory (what the pad's hysteresis costs a memoryless net): {desc}."


def _paper_sentence(rows: list[dict[str, Any]]) -> str | None:
    """Where the paper's own, offline configuration stands, when it was run."""
    paper_cfg = next((r for r in rows if not r["causal"] and r["width"] == "paper"
                      and r["engine"] == "float"), None)
    if paper_cfg is None:
        return None
    return (f"The paper's own configuration (paper width, centred Gaussian σ = "
            f"{paper_cfg['sigma']:g}) reaches error index {paper_cfg['error_index']:.3f} "
            f"({_accuracy(paper_cfg)}) but needs {paper_cfg['filter_delay_ms']:.0f} ms of future "
            f"samples, so it is an offline reference, off the deployable front.")


def _front_sentence(rows: list[dict[str, Any]]) -> str | None:
    """The deployable Pareto front of error against host compute, fastest first."""
    front = sorted((r for r in rows if r.get("pareto_compute")), key=lambda r: r["host_batch_ns"])
    if not front:
        return None
    return "Deployable Pareto front, error against host compute: " + ", ".join(
        f"{r['variant']}/{r['engine']} ({_ns(r['host_batch_ns'])}, index {r['error_index']:.3f})"
        for r in front) + "."


def _m4_sentences(rows: list[dict[str, Any]], by: dict[tuple[str, str], dict[str, Any]],
                  tag: str) -> list[str]:
    """The Cortex-M4 cost of every counted fixed-point row, costliest first, and what int8
    weights trade on the reference variant when both widths were counted."""
    m4 = [r for r in rows if r["engine"] == "fixed" and r.get("m4_instructions_per_step")]
    if not m4:
        return []
    desc = "; ".join(
        f"{r['variant']} {r['m4_instructions_per_step']} instructions per step"
        + (f", {r['m4_cycles_per_step_estimate']} estimated cycles "
           f"({100 * r['m4_budget_fraction_cycles_at_168MHz']:.1f} % of a 1 kHz period at "
           f"168 MHz)" if r.get("m4_cycles_per_step_estimate") else
           f" ({100 * r['m4_budget_fraction_at_168MHz']:.1f} % of a 1 kHz period at 168 MHz "
           f"at one instruction per cycle)")
        for r in sorted(m4, key=lambda r: -r["m4_instructions_per_step"]))
    parts = [f"On the Cortex-M4 (DSP build, int16, worst step; cycles estimated from the "
             f"executed instruction mix, docs/firmware.md): {desc}."]
    r16, r8 = by.get((tag, "fixed")), by.get((tag, "fixed-int8"))
    if r16 and r8 and r16.get("m4_instructions_per_step") and r8.get("m4_instructions_per_step"):
        parts.append(f"Int8 weights shrink the blob from {r16['model_bytes']} to "
                     f"{r8['model_bytes']} bytes but take {r8['m4_instructions_per_step']} "
                     f"instead of {r16['m4_instructions_per_step']} instructions per step on "
                     f"the M4 ({r8['m4_instructions_per_step'] / r16['m4_instructions_per_step']:.1f}×"
                     f"; the portable int16 build takes {r16.get('m4_instructions_portable')}).")
    return parts


def _cheapest_sentence(rows: list[dict[str, Any]], ref: dict[str, Any]) -> str | None:
    """The cheapest deployable configuration that matches the reference; when none does, the
    closest cheaper one on the reference's engine and how far off it is."""
    cheaper = [r for r in rows if r.get("matches_reference") and r["causal"] and r is not ref
               and (r["macs"] < ref["macs"] or r["filter_delay_ms"] < ref["filter_delay_ms"] - 1e-9)]
    if cheaper:
        best = min(cheaper, key=lambda r: (r["macs"], r["filter_delay_ms"], r.get("host_batch_ns") or 0))
        engines = [r["engine"] for r in cheaper if r["variant"] == best["variant"]]
        return (f"Cheapest configuration matching the reference (every RMSE within "
                f"{100 * (MATCH_RMSE_FACTOR - 1):.0f} %, contact within "
                f"{100 * CONTACT_SLACK:.1f} points): {best['variant']}, {best['macs']} MACs "
                f"against the reference's {ref['macs']} ({ref['macs'] / best['macs']:.1f}× fewer), "
                f"{best['filter_delay_ms']:.1f} ms delay, index {best['error_index']:.3f}; it "
                f"matches on {', '.join(engines)}.")
    worse = sorted((r for r in rows if r["causal"] and r is not ref and r["engine"] == ref["engine"]
                    and (r["macs"] < ref["macs"] or r["filter_delay_ms"] < ref["filter_delay_ms"])),
                   key=lambda r: r["error_index"])
    if not worse:
        return None
    w = worse[0]
    return (f"No cheaper configuration matches the reference: the closest, {w['variant']}"
            f" ({w['macs']} MACs, {w['filter_delay_ms']:.1f} ms), is at error index "
            f"{w['error_index']:.3f} ({_accuracy(w)}).")


# --------------------------------------------------------------------------------------------
# Outputs
# --------------------------------------------------------------------------------------------

CSV_COLUMNS = ("variant", "engine", "width", "filter", "sigma", "memory", "memory_states",
               "memory_state_bytes", "causal", "weight_bits",
               "act_bits", "qat", "status", *METRIC_KEYS, "n_samples", "error_index",
               "matches_reference", "is_reference", "host_single_ns", "host_single_p99_ns",
               "host_batch_ns", "host_batch_min_ns", "m4_instructions_per_step",
               "m4_cycles_per_step_estimate", "m4_instructions_portable", "m4_bit_exact",
               "filter_taps", "filter_delay_ms",
               "macs", "macs_nets", "model_bytes", "pareto_compute", "pareto_delay")


def markdown_table(res: dict[str, Any]) -> str:
    """The grid as a Markdown table, best error index first within each variant group."""
    head = ("| variant | engine | memory | contact % | force N | x mm | y mm | error index | single | "
            "batch | M4 instr. | M4 cycles (est.) | delay ms | MACs | state B | bytes | Pareto |")
    lines = [head, "|" + "---|" * (head.count("|") - 1)]
    for r in res["rows"]:
        if r.get("status") != "ok":
            continue
        mark = []
        if r.get("is_reference"):
            mark.append("**ref**")
        if r.get("pareto_compute"):
            mark.append("P-time")
        if r.get("pareto_delay"):
            mark.append("P-delay")
        if r.get("matches_reference") and not r.get("is_reference"):
            mark.append("≈ref")
        lines.append("| " + " | ".join([
            r["variant"] + ("" if r["causal"] else " (offline)"), r["engine"],
            r.get("memory", "none"), _fmt(100 * r["contact_accuracy"], ".2f"), _fmt(r["rmse_force_N"], ".3f"),
            _fmt(r["rmse_x_mm"], ".3f"), _fmt(r["rmse_y_mm"], ".3f"), _fmt(r["error_index"], ".3f"),
            _ns(r.get("host_single_ns")), _ns(r.get("host_batch_ns")),
            _fmt(r.get("m4_instructions_per_step")), _fmt(r.get("m4_cycles_per_step_estimate")),
            _fmt(r["filter_delay_ms"], ".1f"),
            str(r["macs"]), _fmt(r.get("memory_state_bytes")), _fmt(r.get("model_bytes")),
            " ".join(mark)]) + " |")
    missing = [r for r in res["rows"] if r.get("status") != "ok"]
    if missing:
        seen = {}
        for r in missing:
            seen.setdefault((r["engine"], r["status"]), []).append(r["variant"])
        lines.append("")
        lines.append("Not measured: " + "; ".join(
            f"{eng} ({len(v)} variants): {st}" for (eng, st), v in seen.items()))
    return "\n".join(lines)



def write_outputs(res: dict[str, Any], out: Path, log: Callable[[str], None]) -> None:
    """tradeoff.json, tradeoff.csv, tradeoff.md and tradeoff.png in ``out``."""
    from fbgforce import fileio

    fileio.write_text(out / "tradeoff.json", json.dumps(res, indent=1, default=json_default) + "\n",
                      "--out")
    with fileio.Outputs("--out") as files, files.open(out / "tradeoff.csv", "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(CSV_COLUMNS)
        for r in res["rows"]:
            w.writerow(["" if r.get(c) is None else r.get(c) for c in CSV_COLUMNS])
    note = write_plot(res, out / "tradeoff.png")
    if note:
        log(note)
    res["plot"] = None if note else str(out / "tradeoff.png")
    md = ["# Accuracy against time", "", f"Data: {', '.join(str(d.get('path') or d.get('source')) for d in res['data'])}; "
          f"held-out test presses (split 8:1:1 by press, seed {res['settings']['seed']}).", "",
          markdown_table(res), "", res["summary"], ""]
    if res["plot"]:
        md += ["![accuracy against time](tradeoff.png)", ""]
    fileio.write_text(out / "tradeoff.md", "\n".join(md), "--out")
