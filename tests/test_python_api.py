"""The researcher's API: the worked example of docs/python-api.md runs as written, every name
the doc lists resolves from ``import fbgforce``, and datasets survive a pandas round trip."""
from __future__ import annotations

import inspect
import re
from pathlib import Path

import numpy as np
import pytest

import fbgforce

DOC = Path(__file__).resolve().parents[1] / "docs" / "python-api.md"


def _worked_example() -> str:
    text = DOC.read_text()
    section = text.split("## Worked example", 1)[1]
    return re.search(r"```python\n(.*?)```", section, re.S).group(1)


@pytest.mark.slow
def test_worked_example_runs(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    code = _worked_example()
    exec(compile(code, str(DOC), "exec"), {"__name__": "__doc_example__"})
    printed = capsys.readouterr().out
    assert "C runtime: same contact decision" in printed and "test split:" in printed
    assert (tmp_path / "api-example" / "model" / "model.fbgm").is_file()


def test_documented_names_resolve():
    names = set(re.findall(r"`fbgforce\.(\w+)", DOC.read_text()))
    assert names >= {"simulate", "load_dataset", "save_dataset", "to_dataframe", "from_dataframe",
                     "train", "predict", "evaluate", "save_model", "load_model", "export_model",
                     "Runtime", "Dataset"}
    # Modules are named too (fbgforce.samples.wavelength_array): they need not be callable.
    modules = {n for n in names if n == "errors" or inspect.ismodule(getattr(fbgforce, n, None))}
    for name in names - modules:
        assert callable(getattr(fbgforce, name)), name
    assert set(fbgforce.__all__) >= names - modules
    with pytest.raises(AttributeError):
        fbgforce.no_such_function  # noqa: B018


def test_dataframe_round_trip_and_validation(small_dataset_path):
    pd = pytest.importorskip("pandas", reason="pandas is optional; the round trip needs it")
    from fbgforce.errors import InputError

    ds = fbgforce.load_dataset(small_dataset_path).subset(slice(0, 3000))
    ds.extra["temperature_K"] = np.linspace(293.0, 294.0, len(ds))
    df = fbgforce.to_dataframe(ds)
    assert list(df.columns[:11]) == ["t_s", "wl1_nm", "wl2_nm", "wl3_nm", "wl4_nm", "wlT_nm",
                                     "contact", "x_mm", "y_mm", "force_N", "press_id"]
    back = fbgforce.from_dataframe(df[df.columns[::-1]])   # column order does not matter
    for k in ("t_s", "wl_nm", "contact", "force_N", "press_id"):
        assert np.array_equal(getattr(back, k), getattr(ds, k)), k
    assert np.array_equal(back.x_mm, ds.x_mm, equal_nan=True)
    assert np.array_equal(back.extra["temperature_K"], ds.extra["temperature_K"])
    assert back.source == ds.source
    # Validated like a file: the first bad row and its column are named.
    bad = df.copy()
    bad.loc[1234, "wl2_nm"] = 1.55e-6                       # metres, not nm
    with pytest.raises(InputError, match=r"row 1234.*|wl2_nm") as exc:
        fbgforce.from_dataframe(bad, source="my frame")
    assert "my frame" in str(exc.value) and "wl2_nm" in str(exc.value)
    with pytest.raises(InputError, match="force_N"):
        fbgforce.from_dataframe(df.drop(columns=["force_N"]))
    assert isinstance(df, pd.DataFrame)
