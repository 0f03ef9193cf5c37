"""One verdict at scale: the C loader and the Python reader on 10^6 mutated blobs.

Mutates a valid blob with :func:`fbgforce.export.mutate.mutants` (bit flips, truncations,
length, header, layer-table and padding edits, extreme values in every parameter and array;
CRC fixed up in 90 % of them), asks both readers for their verdict and prints how many
mutants got each code and how many disagreed (goal: 0). Run from anywhere::

    python -m fbgforce.bench.bench_blob_verdict [--n 1000000] [--blob model.fbgm] [--json]

Without ``--blob`` the blob is a small random model with every kind of memory state.
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from collections import Counter
from typing import Any

import numpy as np
from tqdm import tqdm

from fbgforce.model import artifact as fm
from fbgforce.errors import InputError
from fbgforce.export import blob, mutate
from fbgforce.export.quantize import calibrate, quantize


def random_blob(seed: int = 0) -> bytes:
    """A small quantised model (random weights, memory of every kind)."""
    rng = np.random.default_rng(seed)
    mem = fm.Memory(ema_shifts=(3, 7), ema_gains=(2, 0), play_widths=(0.05,), play_gains=(3,),
                    loc_shift=4)
    pre = fm.Preprocess(temp_coeff=rng.uniform(0.9, 1.1, 4), filter_kind="causal", filter_sigma=1.5,
                        taps=np.exp(-0.5 * (np.arange(5) / 1.5) ** 2) / np.exp(-0.5 * (np.arange(5) / 1.5) ** 2).sum(),
                        input_mean=rng.normal(0, 50, 4), input_std=rng.uniform(100, 400, 4), memory=mem)

    def mlp(dims: list[int]) -> fm.MLP:
        return fm.MLP([rng.normal(0, np.sqrt(2 / a), (b, a)) for a, b in zip(dims[:-1], dims[1:])],
                      [rng.normal(0, 0.1, b) for b in dims[1:]])

    f = pre.n_features
    model = fm.HierarchicalModel(pre, mlp([f, 6, 5, 2]), mlp([f, 7, 1]), mlp([6 + mem.n_loc, 5, 4, 2]),
                                 force_offset=20.0, force_scale=15.0, xy_offset=[10.5, 13.5],
                                 xy_scale=[6.0, 7.5], baseline_nm=[1530, 1535, 1540, 1545, 1550])
    walk = np.cumsum(rng.normal(0.0, 0.004, (600, 5)), axis=0)
    q, _ = quantize(model, calibrate(model, [(model.baseline_nm + walk, model.baseline_nm)]))
    return blob.to_bytes(q)


def run(data: bytes, n: int, seed: int) -> dict[str, Any]:
    codes: Counter[str] = Counter()
    kinds: Counter[str] = Counter()
    disagree: list[dict[str, Any]] = []
    t0 = time.perf_counter()
    for i, (kind, mutant) in enumerate(tqdm(mutate.mutants(data, n, seed), total=n,
                                            desc="mutants", file=sys.stderr, mininterval=1.0)):
        c, py = mutate.c_verdict(mutant), mutate.python_verdict(mutant)
        codes[c] += 1
        kinds[kind] += 1
        if c != py and len(disagree) < 20:
            disagree.append({"index": i, "kind": kind, "c": c, "python": py})
    return {"mutants": n, "seed": seed, "blob_bytes": len(data), "disagreements": len(disagree),
            "first_disagreements": disagree, "verdicts": dict(codes.most_common()),
            "kinds": dict(kinds), "seconds": round(time.perf_counter() - t0, 1)}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m fbgforce.bench.bench_blob_verdict",
                                 description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=1_000_000, help="mutants (default 10^6)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--blob", default=None, help="a model.fbgm to mutate (default: a random model)")
    ap.add_argument("--json", action="store_true", help="print one JSON object")
    args = ap.parse_args(argv)
    try:
        if args.blob:
            blob.load_model_blob(args.blob)          # must be valid before it is mutated
            data = blob.blob_path(args.blob).read_bytes()
        else:
            data = random_blob(args.seed)
    except InputError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    res = run(data, args.n, args.seed)
    if args.json:
        print(json.dumps(res))
    else:
        print(f"{res['mutants']} mutants of a {res['blob_bytes']}-byte blob in {res['seconds']} s: "
              f"{res['disagreements']} disagreements (goal 0)")
        for code, count in res["verdicts"].items():
            print(f"  {code:20s} {count:9d}")
    return 0 if res["disagreements"] == 0 else 1


if __name__ == "__main__":
    raise SystemExit(main())
