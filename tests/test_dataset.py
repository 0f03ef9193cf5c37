"""The dataset contract: CSV/npz round trips, validation errors, splits (fbgforce.recordings.dataset)."""
from __future__ import annotations

import numpy as np
import pytest

from fbgforce.recordings import dataset as D
from fbgforce.errors import InputError
from fbgforce.geometry import NOMINAL


def make_ds(n_press: int = 6, per: int = 40, seed: int = 0) -> D.Dataset:
    """A small valid recording from the nominal model, with extras of every dtype."""
    rng = np.random.default_rng(seed)
    n = n_press * per
    shape = np.concatenate([np.zeros(per // 4), np.sin(np.linspace(0, np.pi, per - per // 4))])
    f = np.concatenate([rng.uniform(1, 70) * shape for _ in range(n_press)])
    contact = f > 0.05
    x = np.repeat(rng.uniform(0.5, 20.5, n_press), per)
    y = np.repeat(rng.uniform(0.5, 26.5, n_press), per)
    wl = NOMINAL.forward(f, x, y) + rng.normal(0, 0.004, (n, 5))
    return D.Dataset(
        t_s=np.arange(n) / 1000.0, wl_nm=wl, contact=contact,
        x_mm=np.where(contact, x, np.nan), y_mm=np.where(contact, y, np.nan),
        force_N=f, press_id=np.repeat(np.arange(n_press) + 10, per),
        extra={"dropout": (rng.random(n) < 0.1).astype(np.int8),
               "ok": rng.random(n) < 0.5,
               "temperature_K": rng.normal(0, 1, n),
               "note": np.array(["a", "bb"] * (n // 2)),
               "tag": np.array(["007", "1e3"] * (n // 2))},  # text that looks numeric
        source="test",
    )


def assert_same(a: D.Dataset, b: D.Dataset, exact: bool = True) -> None:
    tol = dict(rtol=0, atol=0) if exact else dict(rtol=0, atol=5.1e-5)  # coarsest CSV column: x/y at 0.1 µm
    np.testing.assert_allclose(a.t_s, b.t_s, **tol)
    np.testing.assert_allclose(a.wl_nm, b.wl_nm, **tol)
    np.testing.assert_array_equal(a.contact, b.contact)
    np.testing.assert_allclose(a.x_mm, b.x_mm, **tol)
    np.testing.assert_allclose(a.y_mm, b.y_mm, **tol)
    np.testing.assert_allclose(a.force_N, b.force_N, **tol)
    np.testing.assert_array_equal(a.press_id, b.press_id)
    assert a.extra.keys() == b.extra.keys()


def test_npz_round_trip_is_lossless(tmp_path):
    ds = make_ds()
    D.save(ds, tmp_path / "d.npz")
    back = D.load(tmp_path / "d.npz")
    assert_same(ds, back)
    for k, v in ds.extra.items():
        np.testing.assert_array_equal(back.extra[k], v)
        assert back.extra[k].dtype == v.dtype


def test_csv_round_trip_keeps_resolution_and_extras(tmp_path):
    ds = make_ds()
    D.save(ds, tmp_path / "d.csv")
    back = D.load(tmp_path / "d.csv")
    assert_same(ds, back, exact=False)
    assert back.extra["dropout"].dtype == np.int64
    np.testing.assert_array_equal(back.extra["dropout"], ds.extra["dropout"])
    assert back.extra["ok"].dtype == bool
    np.testing.assert_array_equal(back.extra["ok"], ds.extra["ok"])
    np.testing.assert_allclose(back.extra["temperature_K"], ds.extra["temperature_K"], rtol=1e-8)
    np.testing.assert_array_equal(back.extra["note"], ds.extra["note"])
    np.testing.assert_array_equal(back.extra["tag"], ds.extra["tag"])
    # CSV -> npz -> load is exact; CSV written again from the loaded data is byte-identical.
    D.save(back, tmp_path / "d2.npz")
    assert_same(back, D.load(tmp_path / "d2.npz"))
    D.save(back, tmp_path / "d2.csv")
    body = lambda p: [ln for ln in p.read_text().splitlines() if not ln.startswith("# source")]
    assert body(tmp_path / "d.csv") == body(tmp_path / "d2.csv")


@pytest.mark.parametrize("start_s,step_s", [(1764100000.0, 1e-3),      # Unix seconds, 1 kHz
                                            (1764100000.123, 5e-5),    # 20 kHz, off the second
                                            (3.0e5, 1e-3),             # a long-running clock
                                            (0.0, 1e-3)])
def test_csv_round_trips_time_exactly_at_any_magnitude(tmp_path, start_s, step_s):
    """Times come back bit for bit, so a clock in Unix seconds (1.76e9 s, where twelve
    significant digits are 10 ms) keeps its 1 ms steps and the file loads again; random
    float64 times too, not only round decimals."""
    ds = make_ds()
    ds.t_s = start_s + np.arange(len(ds)) * step_s
    D.save(ds, tmp_path / "d.csv")
    back = D.load(tmp_path / "d.csv")
    np.testing.assert_array_equal(back.t_s, ds.t_s)
    assert np.all(np.diff(back.t_s) > 0)
    # Arbitrary doubles: the shortest exact decimal, not a resolution.
    jitter = np.random.default_rng(1).uniform(0.1, 0.9, len(ds)) * step_s
    ds.t_s = start_s + np.cumsum(jitter)
    with D.CsvWriter(tmp_path / "chunks.csv", extra_kinds={k: D._extra_kind(v)
                                                           for k, v in ds.extra.items()}) as w:
        for a in range(0, len(ds), 70):
            w.write(ds.subset(slice(a, a + 70)))
    np.testing.assert_array_equal(D.load(tmp_path / "chunks.csv").t_s, ds.t_s)


def test_csv_empty_location_without_contact(tmp_path):
    ds = make_ds()
    D.save(ds, tmp_path / "d.csv")
    lines = [ln for ln in (tmp_path / "d.csv").read_text().splitlines() if not ln.startswith("#")]
    header = lines[0].split(",")
    row0 = lines[1].split(",")
    assert ds.contact[0] == 0 and row0[header.index("x_mm")] == "" and row0[header.index("y_mm")] == ""


def test_any_column_order_comments_crlf_and_unknown_extra(tmp_path):
    text = ("# a log converted from a real stage\r\n"
            "press_id,force_N,y_mm,x_mm,contact,wlT_nm,wl4_nm,wl3_nm,wl2_nm,wl1_nm,t_s,stage_z_mm\r\n"
            "3,0.0,,,0,1562,1554,1546,1538,1530,0.0,5.0\r\n"
            "# operator paused here\r\n"
            "\r\n"
            "3,2.5,4,3,1,1562,1554,1546,1538,1529.9,0.001,4.9\r\n")
    p = tmp_path / "log.csv"
    p.write_bytes(text.encode())
    ds = D.load(p)
    assert len(ds) == 2
    assert ds.wl_nm[1, 0] == 1529.9 and ds.x_mm[1] == 3 and ds.y_mm[1] == 4
    np.testing.assert_array_equal(ds.extra["stage_z_mm"], [5.0, 4.9])
    assert ds.press_id.dtype == np.int64 and ds.contact.dtype == bool


def test_small_negative_force_is_kept(tmp_path):
    ds = make_ds()
    ds.force_N[0] = -0.3  # load-cell noise around zero, no contact
    D.save(ds, tmp_path / "d.csv")
    assert D.load(tmp_path / "d.csv").force_N[0] == pytest.approx(-0.3)


HEADER = "t_s,wl1_nm,wl2_nm,wl3_nm,wl4_nm,wlT_nm,contact,x_mm,y_mm,force_N,press_id"
GOOD = ["0.000,1530,1538,1546,1554,1562,0,,,0.0,0",
        "0.001,1530,1538,1546,1554,1562,1,3,4,1.0,0",
        "0.002,1530,1538,1546,1554,1562,1,3,4,1.5,0",
        "0.003,1530,1538,1546,1554,1562,0,,,0.0,1"]


def csv_text(rows: list[str], header: str = HEADER) -> str:
    # Line 1 comment, line 2 header, data from line 3.
    return "# test file\n" + header + "\n" + "\n".join(rows) + "\n"


def replace_field(row: str, column: str, value: str) -> str:
    fields = row.split(",")
    fields[HEADER.split(",").index(column)] = value
    return ",".join(fields)


@pytest.mark.parametrize("rows_idx,column,value,fragment", [
    ([2], "t_s", "0.001", "time not increasing"),
    ([1], "t_s", "", "missing value"),
    ([1, 2], "wl3_nm", "1.546", "likely a unit mistake"),
    ([3], "wlT_nm", "1562000", "outside 1000-2000 nm"),
    ([1], "contact", "2", "contact must be 0 or 1"),
    ([0], "x_mm", "1.5", "without contact"),
    ([1], "y_mm", "", "missing where contact is 1"),
    ([1, 2], "force_N", "-3", "negative forces"),
    ([1], "force_N", "", "missing force"),
    ([2], "force_N", "12N", "not a number: '12N'"),
    ([0, 1, 3], "wl1_nm", "abc", "not a number"),
    ([3], "press_id", "1.5", "press_id must be an integer"),
])
def test_validation_error_names_file_line_column(tmp_path, rows_idx, column, value, fragment):
    rows = list(GOOD)
    for i in rows_idx:
        rows[i] = replace_field(rows[i], column, value)
    p = tmp_path / "bad.csv"
    p.write_text(csv_text(rows))
    with pytest.raises(InputError) as info:
        D.load(p)
    err = info.value
    assert err.path == str(p)
    assert err.line == rows_idx[0] + 3
    assert err.column == column
    assert fragment in str(err)
    if len(rows_idx) > 1:
        assert f"({len(rows_idx)} lines like this)" in str(err)
    assert str(p) in str(err) and f"line {err.line}" in str(err)


def test_several_problems_are_all_mentioned(tmp_path):
    rows = list(GOOD)
    rows[1] = replace_field(rows[1], "contact", "7")
    rows[3] = replace_field(rows[3], "wl2_nm", "1.538")
    p = tmp_path / "bad.csv"
    p.write_text(csv_text(rows))
    with pytest.raises(D.DatasetError) as info:
        D.load(p)
    assert [q.column for q in info.value.problems] == ["contact", "wl2_nm"]
    assert [q.line for q in info.value.problems] == [4, 6]
    assert "also line 6 column 'wl2_nm'" in str(info.value)


@pytest.mark.parametrize("text,line,column,fragment", [
    ("", None, None, "empty file"),
    ("# only a comment\n\n", None, None, "empty file"),
    ("# c\n" + HEADER + "\n", 2, None, "no data rows"),
    ("# c\n" + HEADER.replace(",press_id", "") + "\n" + GOOD[0][:-2] + "\n", 2, "press_id",
     "missing required column press_id"),
    ("# c\n" + HEADER + ",t_s\n" + GOOD[0] + ",0\n", 2, "t_s", "duplicate column"),
    ("# c\n" + HEADER + "\n" + GOOD[0] + "\n" + GOOD[1] + ",9\n", 4, None, "expected 11"),
])
def test_structural_errors(tmp_path, text, line, column, fragment):
    p = tmp_path / "bad.csv"
    p.write_text(text)
    with pytest.raises(InputError) as info:
        D.load(p)
    assert info.value.line == line and info.value.column == column
    assert fragment in str(info.value) and str(p) in str(info.value)


def test_missing_file_and_bad_suffix(tmp_path):
    with pytest.raises(InputError, match="no such file"):
        D.load(tmp_path / "nope.csv")
    with pytest.raises(InputError, match="use .csv or .npz"):
        D.load(tmp_path / "data.txt")


def test_npz_errors_name_array_and_row(tmp_path):
    ds = make_ds()
    arrays = {"t_s": ds.t_s, "wl_nm": ds.wl_nm, "contact": ds.contact, "x_mm": ds.x_mm,
              "y_mm": ds.y_mm, "force_N": ds.force_N}
    np.savez(tmp_path / "a.npz", **arrays)
    with pytest.raises(InputError, match="missing array 'press_id'"):
        D.load(tmp_path / "a.npz")
    wl = ds.wl_nm.copy()
    wl[7, 2] /= 1000.0
    np.savez(tmp_path / "b.npz", **{**arrays, "wl_nm": wl, "press_id": ds.press_id})
    with pytest.raises(InputError) as info:
        D.load(tmp_path / "b.npz")
    assert info.value.column == "wl3_nm" and "row 7" in str(info.value)


def test_save_refuses_invalid_data(tmp_path):
    ds = make_ds()
    ds.x_mm[0] = 1.0  # location without contact
    with pytest.raises(InputError, match="without contact"):
        D.save(ds, tmp_path / "d.csv")
    assert not (tmp_path / "d.csv").exists()


def test_split_by_press_is_disjoint_complete_and_seeded():
    ds = make_ds(n_press=20, per=10)
    train, val, test = D.split_by_press(ds, seed=3)
    ids = [set(np.unique(p.press_id)) for p in (train, val, test)]
    assert [len(i) for i in ids] == [16, 2, 2]
    assert not (ids[0] & ids[1] or ids[0] & ids[2] or ids[1] & ids[2])
    assert len(train) + len(val) + len(test) == len(ds)
    for part in (train, val, test):  # whole presses, original order
        assert np.all(np.diff(part.t_s) > 0)
        for pid in np.unique(part.press_id):
            assert np.sum(part.press_id == pid) == np.sum(ds.press_id == pid)
    again = D.split_by_press(ds, seed=3)
    assert all(np.array_equal(a.press_id, b.press_id) for a, b in zip((train, val, test), again))
    other = D.split_by_press(ds, seed=4)
    assert not np.array_equal(other[0].press_id, train.press_id)
    small = D.split_by_press(make_ds(n_press=3, per=10))
    assert all(len(p) > 0 for p in small)


def test_subset_and_concat():
    ds = make_ds()
    a = ds.subset(ds.press_id < 12)
    b = ds.subset(np.flatnonzero(ds.press_id >= 12))
    assert len(a) + len(b) == len(ds)
    both = D.concat([a, b])
    assert_same(both, ds)
    np.testing.assert_array_equal(both.extra["note"], ds.extra["note"])
    c = D.concat([a, D.Dataset(b.t_s, b.wl_nm, b.contact, b.x_mm, b.y_mm, b.force_N,
                               b.press_id)])
    assert np.isnan(c.extra["temperature_K"][len(a):]).all()
    assert len(ds.subset(slice(0, 5))) == 5
