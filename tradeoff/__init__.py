"""``fbgforce tradeoff``: what accuracy costs in time, on a grid of models x engines.

For every trained variant (filter x network width) and every engine that can run it, the
same test presses are scored with :mod:`fbgforce.evaluation.metrics`, and the cost is measured: host time
per sample (single-sample streaming calls and batches, all engines interleaved in one run,
:mod:`fbgforce.tradeoff.timing`), the filter's delay, multiply-accumulates, model bytes and, when
the Cortex-M4 toolchain is there, instructions per step on target (:mod:`fbgforce.target`).

Variants
    ``filter``: ``none``, ``causal`` Gaussian at several sigmas (what ships), ``centred`` (the
    paper's offline smoothing, a reference that cannot run in a controller). ``width``: the
    paper's hidden widths, half and quarter. The default ``star`` grid varies the filter at the
    paper width and the width at the shipped filter (7 models); ``full`` is the product.
Engines
    ``float`` (fbgforce.model), ``onnx`` (onnxruntime), ``cfloat`` (C single
    precision), ``fixed`` (C fixed point, int16 weights), ``fixed-int8`` (int8 weights, same
    model), ``fixed-int8-qat`` (int8 weights after quantization-aware fine-tuning,
    :mod:`fbgforce.trainer.qat`). Engines not built yet are listed with ``status`` "missing".

The reference row is the paper-width model with the shipped causal filter on ``float``.
``error_index`` is the geometric mean of four ratios to it (force, x and y RMSE, contact error
rate): 1.0 means the reference's accuracy, 1.1 about 10 % worse. A row ``matches`` the
reference when each RMSE is at most 5 % higher and contact accuracy at most 0.2 points lower.

Modules: :mod:`~fbgforce.tradeoff.grid` (variants, engines, settings),
:mod:`~fbgforce.tradeoff.artifacts` (data, trained and exported models, reused across runs),
:mod:`~fbgforce.tradeoff.timing` and :mod:`~fbgforce.tradeoff.timers` (host timing),
:mod:`~fbgforce.tradeoff.scoring` (error index, Pareto fronts, speed ratios),
:mod:`~fbgforce.tradeoff.outputs` and :mod:`~fbgforce.tradeoff.plot` (JSON, CSV, Markdown,
PNG), :mod:`~fbgforce.tradeoff.run` (the whole run), :mod:`~fbgforce.tradeoff.cli` (the command).
"""
