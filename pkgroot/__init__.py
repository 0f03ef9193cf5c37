"""fbgforce: contact, force and contact location from fibre Bragg gratings.

The researcher's API (docs/python-api.md), all from ``import fbgforce``:

======================  ==================================================================
``simulate``            a recording from the built-in simulator (``fbgforce.sim.simulate``)
``load_dataset``        a recording from a CSV or npz file (``fbgforce.recordings.dataset.load``)
``save_dataset``        write one (``fbgforce.recordings.dataset.save``)
``to_dataframe``        a recording as a pandas DataFrame (needs pandas)
``from_dataframe``      a recording from a DataFrame, validated like a file (needs pandas)
``train``               train the three nets (``fbgforce.trainer.train.train``)
``predict``             the float pipeline on an (n, 5) numpy array of wavelengths (nm)
``evaluate``            metrics of a model directory on recordings, any engine
``save_model``          write a model directory; ``load_model`` reads one
``export_model``        ONNX, the fixed-point blob and C source of a model directory
``Runtime``             the fixed-point C runtime (``fbgforce.pybind.Runtime``)
``Dataset``             the recording type (``fbgforce.recordings.dataset.Dataset``)
======================  ==================================================================

The core, in this directory, follows the data: ``fbgforce.recordings`` (the dataset format and
every way into it), ``fbgforce.model`` (the model directory and the float reference engine),
``fbgforce.evaluation`` (metrics, every engine by name, figures), above base modules
(``contract``, ``units``, ``errors``, ``fileio``, ``jsonutil``, ``signals``, ``samples``,
``progress``, ``geometry``). The other parts live in sibling top-level directories of the
repository and are mapped onto this namespace by ``pyproject.toml``: ``fbgforce.sim``
(simulator), ``fbgforce.trainer`` (numpy training), ``fbgforce.export`` (ONNX and fixed-point
export), ``fbgforce.pybind`` (the cffi binding of the C runtime), ``fbgforce.interrogator``
(serial I/O), ``fbgforce.teleop``.
"""
from __future__ import annotations

import importlib
from typing import Any

from fbgforce.contract import VERSION_STR as __version__

#: Public name -> "module:attribute". Resolved on first use, so that `import fbgforce` stays
#: cheap for the CLI and simulation/training work where the C extension is not built.
_API = {
    "simulate": "fbgforce.sim:simulate",
    "load_dataset": "fbgforce.recordings.dataset:load",
    "save_dataset": "fbgforce.recordings.dataset:save",
    "to_dataframe": "fbgforce.recordings.dataset:to_dataframe",
    "from_dataframe": "fbgforce.recordings.dataset:from_dataframe",
    "Dataset": "fbgforce.recordings.dataset:Dataset",
    "train": "fbgforce.trainer.train:train",
    "predict": "fbgforce.model.floatref:predict",
    "evaluate": "fbgforce.trainer.evaluate:evaluate",
    "save_model": "fbgforce.model.modeldir:save",
    "load_model": "fbgforce.model.modeldir:load",
    "export_model": "fbgforce.export.exporter:export_model",
    "Runtime": "fbgforce.pybind:Runtime",
}

__all__ = sorted(_API) + ["__version__"]


def __getattr__(name: str) -> Any:
    target = _API.get(name)
    if target is None:
        raise AttributeError(f"module 'fbgforce' has no attribute {name!r}")
    module_name, attr = target.split(":")
    value = getattr(importlib.import_module(module_name), attr)
    globals()[name] = value  # later look-ups skip this function
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_API))
