"""The grid: which models are trained (variants), which engines run them, and the settings."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from fbgforce import contract
from fbgforce.trainer.synthetic import IDLE_DRAWS

WIDTHS = {"paper": 1.0, "half": 0.5, "quarter": 0.25}
#: The memory axis: none, and the shipped memory (trainer DEFAULT_MEMORY, "both": two averages
#: and two plays of the load signal, and the location averages) at a smaller (the plays alone)
#: and a larger size (four plays, no location averages): 0, 2, 4, 6 load states.
MEMORIES = ("none", "play", "both", "ema:4,7+play:0.03,0.1,0.25,0.5")
DEFAULT_MEMORY = "both"


@dataclass(frozen=True)
class Variant:
    """One trained model of the grid."""

    filter: str
    sigma: float
    width: str
    memory: str = DEFAULT_MEMORY

    @property
    def tag(self) -> str:
        f = "nofilter" if self.filter == "none" else f"{self.filter}-s{self.sigma:g}"
        mem = "" if self.memory == DEFAULT_MEMORY else "-mem-" + "".join(
            ch if ch.isalnum() or ch == "." else "_" for ch in self.memory)
        return f"{self.width}-{f}{mem}"

    @property
    def causal(self) -> bool:
        return self.filter != "centred"


@dataclass(frozen=True)
class EngineSpec:
    """An engine column: which ``fbgforce.evaluation.engines`` engine on which model artifact."""

    name: str
    engine: str
    artifact: str  # "float" (plain model dir), "int8" or "int8-qat" (sibling dirs)
    weight_bits: int | None
    act_bits: int | None
    dtype_bytes: float


ENGINE_SPECS = (
    EngineSpec("float", "float", "float", None, None, 8),
    EngineSpec("onnx", "onnx", "float", None, None, 4),
    EngineSpec("cfloat", "cfloat", "float", None, None, 4),
    EngineSpec("fixed", "fixed", "float", 16, 16, 2),
    EngineSpec("fixed-int8", "fixed", "int8", 8, 16, 1),
    EngineSpec("fixed-int8-qat", "fixed", "int8-qat", 8, 16, 1),
)
SPECS_BY_NAME = {spec.name: spec for spec in ENGINE_SPECS}
#: Other names ``fbgforce tradeoff --engines`` accepts for the engine columns (docs/cli.md):
#: each column is named as ``fbgforce.evaluation.engines`` names its engine (``float``, ``onnx``,
#: ``cfloat``, ``fixed``), with the weight format where it is not the export's default int16.
ENGINE_ALIASES = {"numpy-f64": "float", "onnx-f32": "onnx", "c-float": "cfloat", "c-int16": "fixed",
                  "c-int8": "fixed-int8", "c-int8-qat": "fixed-int8-qat"}


@dataclass
class Settings:
    """Everything that shapes a run (written to tradeoff.json)."""

    seed: int = 0
    epochs: int = 200
    time_budget_s: float | None = None
    sigmas: tuple[float, ...] = (2.0, 5.0, 10.0)
    default_sigma: float = 5.0
    widths: tuple[str, ...] = ("paper", "half", "quarter")
    memories: tuple[str, ...] = MEMORIES
    grid: str = "star"
    centred: bool = True
    qat_epochs: int = 3
    single_calls: int = 3000
    batch_size: int = 2000
    batch_reps: int = 60
    rounds: int = 6
    target: bool = True
    engines: tuple[str, ...] = tuple(s.name for s in ENGINE_SPECS)
    #: Run the int8 engines (export, QAT) on every causal variant, or only on the reference
    #: variant (quick mode: each export costs seconds).
    int8_all_variants: bool = True
    #: Idle pads each training reads the CUSUM's threshold on (``TrainParams.idle_pads``).
    idle_pads: int = IDLE_DRAWS


def quick_settings(seed: int = 0) -> Settings:
    """Small everything: for CI (< 60 s on a small scene)."""
    return Settings(seed=seed, epochs=4, time_budget_s=5.0, sigmas=(5.0,), widths=("paper", "quarter"),
                    memories=("none", DEFAULT_MEMORY),
                    qat_epochs=1, single_calls=300, batch_size=500, batch_reps=15, rounds=3,
                    target=False, int8_all_variants=False, idle_pads=4)


def variants(s: Settings) -> list[Variant]:
    """The models of the grid (see the module docstring); ``grid == "memory"``: only the
    memory axis on the shipped configuration (paper width, default causal filter)."""
    if s.grid == "memory":
        return [Variant("causal", s.default_sigma, "paper", m) for m in s.memories]
    filters = [("none", 0.0)] + [("causal", sg) for sg in s.sigmas]
    if s.centred:
        filters.append(("centred", s.default_sigma))
    out: list[Variant] = []
    for kind, sg in filters:
        for w in s.widths:
            star_ok = w == "paper" or (kind == "causal" and sg == s.default_sigma)
            if s.grid == "full" or star_ok:
                out.append(Variant(kind, sg, w))
    # The memory axis: every memory on the shipped configuration (paper width, default causal
    # filter); in the full grid on every causal variant.
    for mem in s.memories:
        if mem == DEFAULT_MEMORY:
            continue
        for v in list(out):
            if v.memory == DEFAULT_MEMORY and v.filter == "causal" and (
                    s.grid == "full" or (v.width == "paper" and v.sigma == s.default_sigma)):
                out.append(Variant(v.filter, v.sigma, v.width, mem))
    return out


def scaled_sizes(width: str) -> dict[str, list[int]]:
    """Hidden widths of every net, the paper's scaled by the width factor (at least 2)."""
    from fbgforce.trainer.params import PAPER_SIZES

    f = WIDTHS[width]
    return {k: [max(2, int(round(h * f))) for h in v] for k, v in PAPER_SIZES.items()}


def step_macs(model: Any) -> int:
    """Multiply-accumulates of one full step of ``model`` (a ``HierarchicalModel``): the
    causal filter (strain channels x taps) and every layer of the three nets."""
    pre = model.preprocess
    return int(model.macs) + (0 if pre.filter_kind == "none" else contract.N_STRAIN * int(pre.taps.size))
