"""fbgforce import / protocol / coverage, tested as a lab would use them: the simulator writes
the raw logs (interrogator + stage on its own clock), the import must give back the
simulator's dataset."""
from __future__ import annotations

import json
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from fbgforce.recordings import dataset, labimport as li, stagelog
from fbgforce.errors import InputError
from fbgforce.sim import simulate
from fbgforce.sim.lablogs import write_lab_logs


@pytest.fixture(scope="module")
def smoke():
    return simulate("smoke")


def _import(directory, **flags):
    values = li.load_map(directory / "import.toml") | {"out": str(directory / "out.csv")}
    values.update(flags)
    return li.import_files(li.make_spec(values), progress=False)


#: A Unix-epoch start (2025-11-25): most acquisition software stamps its rows in epoch seconds.
EPOCH_S = "1764100000"


def _epoch_clocks(directory, out=None, start_s=EPOCH_S):
    """The lab logs of ``directory`` (written by ``write_lab_logs``) with both clocks counting
    from ``start_s`` Unix seconds, written to ``out`` (default in place) with their map: each
    time field shifted in decimal, so it keeps the digits the log wrote."""
    from decimal import Decimal

    out = directory if out is None else out
    out.mkdir(parents=True, exist_ok=True)
    for name in ("interrogator.csv", "stage.csv"):
        lines = (directory / name).read_text().splitlines()
        rows = [lines[0]]
        for ln in lines[1:]:
            t, rest = ln.split(",", 1)
            rows.append(f"{Decimal(t) + Decimal(start_s)},{rest}")
        (out / name).write_text("\n".join(rows) + "\n")
    if out != directory:
        (out / "import.toml").write_text((directory / "import.toml").read_text())
    return out


def _clock_error_ms(result, offset_s, drift_ppm, duration_s):
    """Largest error of the fitted stage clock over the log, ms."""
    e0 = result["offset_s"] - offset_s
    e1 = e0 + (result["drift_ppm"] - drift_ppm) * 1e-6 * duration_s
    return 1e3 * max(abs(e0), abs(e1))


def _assert_within_one_sample(imp, ds):
    """The imported dataset is the simulator's up to one sample of alignment."""
    assert len(imp) == len(ds)
    assert np.array_equal(imp.t_s, ds.t_s)
    assert np.abs(imp.wl_nm - ds.wl_nm).max() < 2e-6
    f = ds.force_N
    step = np.maximum(np.abs(np.diff(f, prepend=f[0])), np.abs(np.diff(f, append=f[-1])))
    assert np.all(np.abs(imp.force_N - f) <= 1.2 * step + 0.02)
    # Contact differs only next to a contact edge; press ids only next to a change of press
    # or where the unloading's tail is within a few mN of rest (where the press ends).
    edge = np.convolve(np.diff(ds.contact.astype(int), prepend=0) != 0, [1, 1, 1], "same") > 0
    assert not np.any((imp.contact != ds.contact) & ~edge)
    back = np.convolve(np.diff(ds.press_id, prepend=0) != 0, [1, 1, 1], "same") > 0
    tail = (f < 2 * li.REST_BAND_N) & ~ds.contact
    assert not np.any((imp.press_id != ds.press_id) & ~(back | tail))
    both = imp.contact & ds.contact
    assert np.abs(imp.x_mm[both] - ds.x_mm[both]).max() < 1e-3
    assert np.abs(imp.y_mm[both] - ds.y_mm[both]).max() < 1e-3


def test_import_gives_back_the_simulators_dataset(smoke, tmp_path):
    write_lab_logs(smoke, tmp_path, rate_hz=500, offset_s=0.1, drift_ppm=80, jitter_s=1e-4)
    res = _import(tmp_path)
    assert _clock_error_ms(res, 0.1, 80, smoke.t_s[-1]) <= 1.0
    assert res["presses"] == smoke.n_presses == 20
    assert res["dropped"] == {k: 0 for k in li.DROP_REASONS.values()}
    assert res["alignment"]["correlation"] > 0.9
    _assert_within_one_sample(dataset.load(tmp_path / "out.csv"), smoke)


@pytest.mark.slow
def test_epoch_stamped_logs_import_and_train(smoke, tmp_path):
    """Both logs stamped in Unix seconds (1764100000.000 with 1 ms steps): the clock is found
    within 1 ms, the dataset keeps every sample's time (strictly increasing, to the float64
    the log's field reads as) and loads again, its labels are those of the same logs on
    small times, and ``fbgforce train`` trains on it (it refused the file: ``t_s`` written
    to 12 significant digits, 10 ms at this magnitude)."""
    from fbgforce.cli import main

    write_lab_logs(smoke, tmp_path / "plain", rate_hz=500, offset_s=0.1, drift_ppm=80,
                   jitter_s=1e-4)
    epoch = _epoch_clocks(tmp_path / "plain", tmp_path / "epoch")
    assert (epoch / "interrogator.csv").read_text().splitlines()[2].startswith(EPOCH_S + ".001")
    res = _import(epoch)
    # The simulator's stage clock drifts from its time zero, now the epoch start, which is
    # the import's reference (the first interrogator sample).
    assert _clock_error_ms(res, 0.1, 80, smoke.t_s[-1]) <= 1.0
    assert res["presses"] == smoke.n_presses
    imp = dataset.load(epoch / "out.csv")
    assert len(imp) == len(smoke) and np.all(np.diff(imp.t_s) > 0)
    assert np.abs(imp.t_s - (float(EPOCH_S) + smoke.t_s)).max() < 1e-6
    # Against the same logs on small times: the epoch's float64 steps (0.24 µs) move the
    # fitted clock by microseconds, the labels by no more than that moves the load.
    res_plain = _import(tmp_path / "plain")
    assert abs(res["offset_s"] - res_plain["offset_s"]) < 2e-5
    plain = dataset.load(tmp_path / "plain" / "out.csv")
    assert np.array_equal(imp.contact, plain.contact)
    assert np.array_equal(imp.press_id, plain.press_id)
    assert np.abs(imp.force_N - plain.force_N).max() < 0.01
    assert main(["train", "--data", str(epoch / "out.csv"), "--out", str(tmp_path / "m"),
                 "--epochs", "1", "--idle-pads", "0"]) == 0


@pytest.mark.slow
@pytest.mark.parametrize("unit,per_s,start", [("ms", 1000, "0"), ("ns", 10**9, EPOCH_S)])
def test_clocks_in_other_units_import_with_their_flags(smoke, tmp_path, unit, per_s, start):
    """Both clocks counting ms (from zero) or ns (Unix epoch: 1.764e18, beyond float64's
    integers): with --fbg-time-unit and --stage-time-unit the clock is found as in seconds."""
    from decimal import Decimal

    write_lab_logs(smoke, tmp_path, rate_hz=500, offset_s=0.1, drift_ppm=80, jitter_s=1e-4)
    for name in ("interrogator.csv", "stage.csv"):
        lines = (tmp_path / name).read_text().splitlines()
        rows = [lines[0]]
        for ln in lines[1:]:
            t, rest = ln.split(",", 1)
            rows.append(f"{((Decimal(t) + Decimal(start)) * per_s).normalize():f},{rest}")
        (tmp_path / name).write_text("\n".join(rows) + "\n")
    res = _import(tmp_path, **{"fbg-time-unit": unit, "stage-time-unit": unit})
    assert _clock_error_ms(res, 0.1, 80, smoke.t_s[-1]) <= 1.0
    assert res["fbg"]["rate_hz"] == pytest.approx(1000.0, rel=1e-6)
    imp = dataset.load(tmp_path / "out.csv")
    assert np.abs(imp.t_s - (float(start) + smoke.t_s)).max() < 1e-6


def test_sample_rate_of_an_epoch_clock():
    """float64 rounds each 1 ms step of a Unix-epoch clock by up to 0.24 µs, so the median step
    reads the rate 72 ppm off (1000.07 Hz); the mean of the regular steps reads it to 1 ppm,
    gaps and dropped samples left out as the median leaves them. A clock from zero keeps the
    median's rate, bit for bit."""
    from fbgforce.recordings import tare

    t = float(EPOCH_S) + np.arange(20000) / 1000.0
    t = np.delete(t, np.arange(500, 20000, 997))           # dropped samples
    t[12000:] += 0.5                                          # a gap
    assert tare.sample_rate_hz(t) == pytest.approx(1000.0, rel=1e-6)
    small = np.arange(20000) / 1000.0
    assert tare.sample_rate_hz(small) == 1.0 / float(np.median(np.diff(small)))


@pytest.mark.parametrize("rate_hz,offset_s,drift_ppm", [
    (100, 0.1, 80), (2000, 0.1, -80), (500, 2.0, 80), (500, -2.0, -80), (100, -2.0, 80)])
def test_import_stage_rates_and_offsets(smoke, tmp_path, rate_hz, offset_s, drift_ppm):
    write_lab_logs(smoke, tmp_path, rate_hz=rate_hz, offset_s=offset_s, drift_ppm=drift_ppm,
                   jitter_s=0.1 / rate_hz)
    res = _import(tmp_path)
    assert _clock_error_ms(res, offset_s, drift_ppm, smoke.t_s[-1]) <= 1.0
    assert res["stage"]["rate_hz"] == pytest.approx(rate_hz, rel=1e-3)
    imp = dataset.load(tmp_path / "out.csv")
    assert len(imp) == len(smoke) and imp.n_presses == 20


@pytest.mark.parametrize("magnitude,time_constant_s", [(0.2, 0.05), (0.15, 0.1)])
def test_import_clock_is_free_of_the_pads_lag(tmp_path, magnitude, time_constant_s):
    """A pad whose gratings lag the load far more than the calibration pad's (15-20 % relaxing
    with 50-100 ms, which puts the flanks' line several ms early): the lag fitted with the
    clock's level keeps the clock within 1 ms."""
    from fbgforce.sim import load_scene

    scene = load_scene("smoke")
    effects = {k: dict(v) for k, v in scene.effects.items()}
    effects["viscoelastic"] = {"magnitude": magnitude, "time_constant_s": time_constant_s}
    ds = simulate(scene.replace(effects=effects))
    write_lab_logs(ds, tmp_path, rate_hz=500, offset_s=0.1, drift_ppm=80, jitter_s=1e-4)
    res = _import(tmp_path)
    assert _clock_error_ms(res, 0.1, 80, ds.t_s[-1]) <= 1.0
    assert res["alignment"]["lag_ms"] > 1.0          # the lag was there, and taken out


def _import_foreign(tmp_path: Path, variant: str, load_cell_noise_N: float, *,
                    rate_hz: float = 500, offset_s: float = 0.1, drift_ppm: float = 80,
                    jitter_s: float = 1e-4) -> tuple[dict, float]:
    """Import the lab logs of 40 presses of a tests/foreign.py fingertip (seed 1); returns
    the import's summary and the clock error (ms, :func:`_clock_error_ms`)."""
    sys.path.insert(0, str(Path(__file__).parent))
    import foreign as fg

    spec = replace(fg.VARIANTS[variant], load_cell_noise_N=load_cell_noise_N)
    ds = fg.log(fg.device(spec, fg.device_seed(variant)), 1, 40)
    flags = fg.write_lab_logs(ds, tmp_path, rate_hz=rate_hz, offset_s=offset_s,
                              drift_ppm=drift_ppm, jitter_s=jitter_s)
    res = li.import_files(li.make_spec(flags | {"out": str(tmp_path / "out.csv")}),
                          progress=False)
    return res, _clock_error_ms(res, offset_s, drift_ppm, ds.t_s[-1] - ds.t_s[0])


def test_import_a_foreign_fingertip(tmp_path):
    """Logs from a fingertip the simulator does not make (tests/foreign.py: gratings stretched
    by the load, a pad relaxing 8 % with 50 ms and rubbing 12 %, peaks in pm in its own
    column order, a tab-separated stage log in mN and µm)."""
    res, clock_ms = _import_foreign(tmp_path, "hysteretic_pad", 0.005)
    assert clock_ms <= 1.0
    assert res["presses"] == 40


def test_a_noisy_load_cell_labels_no_touch_at_rest(tmp_path):
    """A load cell with 30 mN of noise (tests/foreign.py's default) reads above the dataset's
    50 mN on 5 % of the samples at rest; the import raises the contact threshold to five times
    the noise it measures, so the rests carry no contact label."""
    res, clock_ms = _import_foreign(tmp_path, "hysteretic_pad", 0.03)
    assert res["load_cell_noise_N"] == pytest.approx(0.03, rel=0.3)
    assert res["contact_threshold_N"] == pytest.approx(5 * res["load_cell_noise_N"])
    out = dataset.load(tmp_path / "out.csv")
    force = np.asarray(out.force_N)
    # Contact runs away from every press (more than 0.1 s from any load above 0.3 N, ten
    # times the noise): none, where the dataset's 50 mN labels more than ten.
    near = np.convolve(force > 0.3, np.ones(2 * int(0.1 * 1000) + 1), "same") > 0
    assert stagelog.runs(np.asarray(out.contact, dtype=bool) & ~near)[0].size == 0
    assert stagelog.runs(stagelog.label_contact(force) & ~near)[0].size > 10
    assert res["presses"] == 40 and clock_ms <= 1.0
    # A quiet load cell keeps the dataset's rule.
    assert stagelog.contact_threshold(0.005) == dataset.CONTACT_THRESHOLD_N


@pytest.mark.parametrize("rate_hz,offset_s,drift_ppm", [(500, 0.1, 80), (2000, 2.0, -80)])
def test_import_finds_no_lag_in_a_noisy_pad_without_one(tmp_path, rate_hz, offset_s, drift_ppm):
    """A foreign fingertip whose gratings follow the load without lag, read by a 500 Hz
    interrogator with 8 pm of noise (tests/foreign.py ``rate500_nodrift``): the lag's fit
    must not trade the start and end of each press for a lag the noise suggests."""
    res, clock_ms = _import_foreign(tmp_path, "rate500_nodrift", 0.005, rate_hz=rate_hz,
                                    offset_s=offset_s, drift_ppm=drift_ppm,
                                    jitter_s=0.1 / rate_hz)
    assert clock_ms <= 1.0
    assert abs(res["alignment"]["lag_ms"]) < 0.6


def test_bench_lab_clock_measures_the_import_against_the_true_clock(smoke, tmp_path, capsys):
    """bench/bench_lab_clock.py: the import's clock error at both ends against clock.json or
    the flags (the errors the import's own offset and drift give), one line and exit 2 when
    the true clock is missing."""
    from fbgforce.bench import bench_lab_clock as bench

    write_lab_logs(smoke, tmp_path / "lab", rate_hz=500, offset_s=0.1, drift_ppm=80,
                   jitter_s=1e-4)
    (tmp_path / "lab" / "clock.json").write_text('{"offset_s": 0.1, "drift_ppm": 80}')
    assert bench.main([str(tmp_path / "lab"), "--json", str(tmp_path / "c.json")]) == 0
    row = json.loads((tmp_path / "c.json").read_text())["logs"][0]
    res = _import(tmp_path / "lab")
    assert row["error_start_ms"] == pytest.approx(1e3 * (res["offset_s"] - 0.1))
    assert max(abs(row["error_start_ms"]), abs(row["error_end_ms"])) == pytest.approx(
        _clock_error_ms(res, 0.1, 80, smoke.t_s[-1] - smoke.t_s[0]))
    assert bench.main([str(tmp_path / "lab"), "--offset-s", "0.101", "--drift-ppm", "80",
                       "--json", str(tmp_path / "d.json")]) == 0
    shifted = json.loads((tmp_path / "d.json").read_text())["logs"][0]
    assert shifted["error_start_ms"] == pytest.approx(row["error_start_ms"] - 1.0)
    (tmp_path / "lab" / "clock.json").unlink()
    capsys.readouterr()
    with pytest.raises(SystemExit) as exc:
        bench.main([str(tmp_path / "lab")])
    assert exc.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "clock.json" in err[0] and "--offset-s" in err[0]


def test_import_pm_units_other_names_and_order(smoke, tmp_path):
    """Wavelengths in pm, force in mN, position in µm, columns renamed and shuffled, extra
    columns, tab-separated stage log: through flags (no map) the same dataset comes back."""
    write_lab_logs(smoke, tmp_path, rate_hz=500, offset_s=-0.05, drift_ppm=40, jitter_s=1e-4)
    fbg = np.loadtxt(tmp_path / "interrogator.csv", delimiter=",", skiprows=1)
    st = np.loadtxt(tmp_path / "stage.csv", delimiter=",", skiprows=1)
    with open(tmp_path / "fbg_pm.csv", "w") as fh:
        fh.write("# Interrogator export\nstatus,Ch T [pm],Ch 3 [pm],Time [s],Ch 1 [pm],"
                 "Ch 4 [pm],Ch 2 [pm]\n")
        for r in fbg:
            fh.write(f"ok,{r[5] * 1e3:.3f},{r[3] * 1e3:.3f},{r[0]:.9f},{r[1] * 1e3:.3f},"
                     f"{r[4] * 1e3:.3f},{r[2] * 1e3:.3f}\n")
    with open(tmp_path / "stage_mn.tsv", "w") as fh:
        fh.write("y_um\tload_mN\tx_um\tclock\n")
        for r in st:
            fh.write(f"{r[3] * 1e3:.1f}\t{r[1] * 1e3:.3f}\t{r[2] * 1e3:.1f}\t{r[0]:.9f}\n")
    out = tmp_path / "ds.csv"
    cmd = [sys.executable, "-m", "fbgforce.cli", "import",
           "--fbg", str(tmp_path / "fbg_pm.csv"),
           "--fbg-columns", "t=Time [s],wl1=Ch 1 [pm],wl2=Ch 2 [pm],wl3=Ch 3 [pm],"
                            "wl4=Ch 4 [pm],wlT=Ch T [pm]",
           "--fbg-unit", "pm",
           "--stage", str(tmp_path / "stage_mn.tsv"),
           "--stage-columns", "t=clock,force=load_mN,x=x_um,y=y_um",
           "--force-unit", "mN", "--position-unit", "um", "--out", str(out), "--json"]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    res = json.loads(proc.stdout)
    assert set(res) >= {"dataset", "samples", "presses", "offset_s", "drift_ppm", "alignment",
                        "fbg", "stage", "dropped", "seconds"}
    assert set(res["alignment"]) >= {"correlation", "residual_ms", "presses_used"}
    assert _clock_error_ms(res, -0.05, 40, smoke.t_s[-1]) <= 1.0
    _assert_within_one_sample(dataset.load(out), smoke)


def test_samples_outside_the_stage_log_are_dropped_and_counted(smoke, tmp_path):
    write_lab_logs(smoke, tmp_path, rate_hz=500, offset_s=0.0, drift_ppm=0, jitter_s=0)
    lines = (tmp_path / "stage.csv").read_text().splitlines()
    # The stage log starts 0.5 s before the interrogator: cut it to start 0.5 s after.
    keep = [lines[0]] + [ln for ln in lines[1:] if float(ln.split(",")[0]) >= 0.5]
    (tmp_path / "stage.csv").write_text("\n".join(keep) + "\n")
    res = _import(tmp_path)
    assert res["dropped"]["before_stage_log"] == pytest.approx(500, abs=2)
    assert res["samples"] + res["dropped"]["before_stage_log"] == len(smoke)


def _rewrite_stage(directory, fn):
    st = np.loadtxt(directory / "stage.csv", delimiter=",", skiprows=1)
    st = fn(st)
    np.savetxt(directory / "stage.csv", st, fmt="%.9f", delimiter=",", header="time,Fz,X,Y",
               comments="")


@pytest.mark.parametrize("case,expect", [
    ("no_overlap", "no overlap"),
    ("no_presses", "no presses"),
    ("not_increasing", "line 101, column 't': time not increasing"),
    ("irregular", "irregular sampling"),
    ("untared", "tare it"),
])
def test_import_refuses_what_it_cannot_trust(smoke, tmp_path, case, expect):
    write_lab_logs(smoke, tmp_path, rate_hz=500, offset_s=0.1, drift_ppm=80, jitter_s=1e-4)

    def change(st):
        if case == "no_overlap":
            st[:, 0] += 100.0
        elif case == "no_presses":
            st[:, 1] = 0.0
        elif case == "not_increasing":
            st[99, 0] = st[98, 0]                 # data row 99 is file line 101
        elif case == "irregular":
            st = st[np.random.default_rng(0).random(st.shape[0]) > 0.2]
        elif case == "untared":
            st[:, 1] += 0.3
        return st

    _rewrite_stage(tmp_path, change)
    with pytest.raises(InputError, match=expect):
        _import(tmp_path)


@pytest.mark.parametrize("column,value", [(1, "nan"), (1, "inf"), (1, "1e300"), (1, "-inf"),
                                          (2, "nan"), (3, "1e300")])
def test_bad_stage_values_are_dropped_and_counted(smoke, tmp_path, column, value):
    """A few load-cell (or position) readings that are no reading (NaN, inf, 1e300), some in
    the middle of presses, are dropped and counted as the interrogator's bad wavelengths are:
    the import aligns as without them and no numpy warning is raised (they ended in
    "alignment failed: ... correlate at best -inf", with an overflow warning for 1e300)."""
    import warnings

    write_lab_logs(smoke, tmp_path, rate_hz=500, offset_s=0.1, drift_ppm=80, jitter_s=1e-4)
    lines = (tmp_path / "stage.csv").read_text().splitlines()
    rows = [1000, 1001, 2500, 4000, 6000]
    for i in rows:
        fields = lines[i].split(",")
        fields[column] = value
        lines[i] = ",".join(fields)
    (tmp_path / "stage.csv").write_text("\n".join(lines) + "\n")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        res = _import(tmp_path)
    assert res["stage"]["bad_rows"] == len(rows)
    assert res["stage"]["rows"] == len(lines) - 1
    assert _clock_error_ms(res, 0.1, 80, smoke.t_s[-1]) <= 1.0
    assert res["presses"] == smoke.n_presses
    assert len(dataset.load(tmp_path / "out.csv")) == len(smoke)


def test_many_bad_stage_values_are_refused_naming_the_first(smoke, tmp_path):
    """More than 1 % of the stage rows without a reading is a wrong column or unit, not a few
    glitches: refused with the first one's file, line and column, one line on stderr."""
    write_lab_logs(smoke, tmp_path, rate_hz=500, offset_s=0.1, drift_ppm=80, jitter_s=1e-4)
    lines = (tmp_path / "stage.csv").read_text().splitlines()
    for i in range(300, 500):
        fields = lines[i].split(",")
        fields[1] = "1e300"
        lines[i] = ",".join(fields)
    (tmp_path / "stage.csv").write_text("\n".join(lines) + "\n")
    proc = subprocess.run([sys.executable, "-m", "fbgforce.cli", "import", "--map",
                           str(tmp_path / "import.toml"), "--out", str(tmp_path / "o.csv")],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2
    assert proc.stderr.count("\n") == 1 and "Warning" not in proc.stderr, proc.stderr
    assert "stage.csv, line 301, column 'force'" in proc.stderr
    assert "1e+300" in proc.stderr and "--force-unit" in proc.stderr


def test_import_refuses_an_ambiguous_alignment(tmp_path):
    """Identical presses at one period and one place: every period fits as well."""
    from fbgforce.sim import load_scene

    scene = load_scene("smoke").replace(schedule={"force_min_N": 30.0, "force_max_N": 30.0,
                                                  "n_presses": 30, "region": "interior",
                                                  "band_mm": 10.0})
    ds = simulate(scene)
    write_lab_logs(ds, tmp_path, rate_hz=500, offset_s=0.1, drift_ppm=80, jitter_s=1e-4)
    with pytest.raises(InputError, match="ambiguous"):
        _import(tmp_path)


def test_import_names_a_wrong_unit_and_a_missing_column(smoke, tmp_path):
    write_lab_logs(smoke, tmp_path, rate_hz=500, offset_s=0.1, drift_ppm=80, jitter_s=1e-4)
    with pytest.raises(InputError, match=r"interrogator.csv, line 2: .*--fbg-unit"):
        _import(tmp_path, **{"fbg-unit": "pm"})
    with pytest.raises(InputError, match=r"stage.csv, line 1: no column\(s\) 'Fx'"):
        _import(tmp_path, **{"stage-columns": "t=time,force=Fx,x=X,y=Y"})
    with pytest.raises(InputError, match="missing key"):
        _import(tmp_path, **{"fbg-columns": "t=timestamp,wl1=peak1"})


def test_cli_import_bad_input_is_one_line_exit_2(smoke, tmp_path):
    write_lab_logs(smoke, tmp_path, rate_hz=500, offset_s=0.1, drift_ppm=80, jitter_s=1e-4)
    proc = subprocess.run([sys.executable, "-m", "fbgforce.cli", "import", "--map",
                           str(tmp_path / "import.toml"), "--out", str(tmp_path / "o.csv"),
                           "--fbg-unit", "pm"], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2
    assert proc.stderr.count("\n") == 1 and "Traceback" not in proc.stderr


def test_press_numbering_follows_the_simulator_and_merges_chatter():
    t = np.arange(40) * 5e-3
    f = np.zeros(40)
    f[5:10] = 1.0
    f[11:14] = 1.0        # a 5 ms dip below the threshold: the same press
    f[14:18] = [0.04, 0.02, 0.01, 0.002]   # the end of its unloading, below the threshold
    f[30:35] = 2.0
    f[37] = 1.0           # a 1-sample blip after the rest: contact, but no new press
    contact = stagelog.label_contact(f)
    ids = li.number_presses(t, f)
    # The rest before a press carries its id, the unloading's end (to the first sample where
    # the load stops falling) its own; after the last press its id stays.
    assert ids.tolist() == [0] * 18 + [1] * 22
    assert contact[37] and not contact[10] and not contact[14]


def test_lab_logs_leave_the_dataset_unchanged(tmp_path):
    """The stage clock is a logging option: the dataset is the same with it."""
    from fbgforce.cli import main

    assert main(["simulate", "--scene", "smoke", "--out", str(tmp_path / "a.csv")]) == 0
    assert main(["simulate", "--scene", "smoke", "--out", str(tmp_path / "b.csv"),
                 "--lab-logs", str(tmp_path / "lab"), "--stage-rate-hz", "100"]) == 0
    assert (tmp_path / "a.csv").read_bytes() == (tmp_path / "b.csv").read_bytes()
    assert (tmp_path / "lab" / "stage.csv").is_file()


def test_csv_writer_in_chunks_equals_save(smoke, tmp_path):
    dataset.save(smoke, tmp_path / "one.csv")
    kinds = {k: "float64" for k in smoke.extra}
    with dataset.CsvWriter(tmp_path / "chunks.csv", smoke.source, kinds) as w:
        for a in range(0, len(smoke), 4000):
            w.write(smoke.subset(slice(a, a + 4000)))
    assert (tmp_path / "one.csv").read_text() == (tmp_path / "chunks.csv").read_text()


# ------------------------------------------------------------------------------ protocol

def test_protocol_default_covers_what_a_model_needs(tmp_path):
    from fbgforce.cli import main
    from fbgforce.recordings.protocol import COLUMNS

    out = tmp_path / "program.csv"
    assert main(["protocol", "--out", str(out)]) == 0
    text = out.read_text()
    lines = [ln for ln in text.splitlines() if not ln.startswith("#")]
    assert lines[0].split(",") == list(COLUMNS)
    rows = np.loadtxt(lines[1:], delimiter=",")
    col = {name: rows[:, i] for i, name in enumerate(COLUMNS)}
    assert rows.shape[0] == 300
    assert col["force_N"].max() > 65 and col["force_N"].max() <= 70 and col["force_N"].min() < 1
    assert 0.5 <= col["x_mm"].min() and col["x_mm"].max() <= 20.5
    assert col["y_mm"].min() < 3 and col["y_mm"].max() > 24
    speed = col["force_N"] / col["ramp_s"]
    assert speed.max() > 300 and speed.min() < 5             # fast taps and slow ramps
    long_hold = (col["hold_s"] >= 1.5) & (col["hold_s"] <= 6)
    assert long_hold.sum() >= 50 and (col["hold_s"] == 0).sum() >= 50
    assert col["rest_s"].min() >= 0.2
    assert col["rest_s"][col["rest_s"] >= 10].sum() >= 30    # long rests between groups
    duration = (col["rest_s"] + 2 * col["ramp_s"] + col["hold_s"]).sum()
    assert float(text.split("# duration: ")[1].split(" s")[0]) == pytest.approx(duration, abs=0.1)
    assert "temperature" in text and "kelvin" in text


# ------------------------------------------------------------------------------ coverage

def test_coverage_says_what_a_log_lacks(smoke, tmp_path):
    from fbgforce.trainer.coverage import coverage

    cov = coverage([smoke])
    assert cov["presses"] == 20
    assert cov["force_N"]["max"] == pytest.approx(smoke.force_N.max())
    assert sum(map(sum, cov["location_map"]["counts"])) == 20
    missing = " ".join(cov["missing"])
    assert "holds of 1.5 s" in missing and "long rests" in missing and "temperature" in missing
    from fbgforce.sim import load_scene

    held = simulate(load_scene("smoke").replace(schedule={"hold_s": 2.0, "n_presses": 4}))
    cov_held = coverage([held])
    assert cov_held["holds"]["longest_s"] >= 1.9
    assert "holds of 1.5 s" not in " ".join(cov_held["missing"])
    dataset.save(smoke, tmp_path / "s.csv")
    proc = subprocess.run([sys.executable, "-m", "fbgforce.cli", "coverage", "--data",
                           str(tmp_path / "s.csv"), "--json"], capture_output=True, text=True,
                          timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert json.loads(proc.stdout)["missing"] == cov["missing"]


# ------------------------------------------------------------------------------ scoring

def test_a_model_scores_the_import_like_the_simulators_file(small_model_dir, small_dataset_path,
                                                          tmp_path):
    """What the labels are worth: one model scored on the imported dataset and on the
    simulator's own file, every metric within 2 % (training two models instead measures the
    training's own variance, docs/lab-import.md)."""
    from fbgforce.trainer.evaluate import evaluate

    ds = dataset.load(small_dataset_path)
    write_lab_logs(ds, tmp_path, rate_hz=500, offset_s=0.1, drift_ppm=80, jitter_s=1e-4)
    _import(tmp_path)
    own = evaluate(small_model_dir, [small_dataset_path], split="all")
    imported = evaluate(small_model_dir, [str(tmp_path / "out.csv")], split="all")
    assert imported["n_samples"] == own["n_samples"]
    for key in ("contact_accuracy", "rmse_force_N", "rmse_x_mm", "rmse_y_mm"):
        assert abs(imported[key] - own[key]) <= 0.02 * abs(own[key]), (key, own[key],
                                                                        imported[key])


#: A training set-up whose result follows its labels rather than the optimiser's chance path:
#: one draw per net, a small learning rate, no augmentation, the nets trained on the
#: recording as tared (the tracker's pass trains a contact net and a decision of its own, a
#: second path for label noise to move), and the mean over three seeds (docs/lab-import.md,
#: "A model trained on the import"; a single seed's force RMSE moves by 3 % when 20 mN of
#: white noise is added to the labels). The contact net reads the play operators, as it did
#: when the 2 % was measured: the force net trains where the contact net passes, and with a
#: contact net blind to them the aligned import's force RMSE read 2.3 % from the file's.
STABLE_TRAINING = {"epochs": 20, "restarts": 1, "weight_decay": 0.0, "hold_augment": 0.0,
                   "location_augment": 1.0, "learning_rate": 1e-4, "progress": False,
                   "track_calibration": False, "idle_pads": 0, "contact_plays": True}
STABLE_SEEDS = (0, 1, 2)
METRICS = ("contact_accuracy", "rmse_force_N", "rmse_x_mm", "rmse_y_mm")


def _mean_scores(ds, rows, reference_path, directory):
    """The metrics on the reference file's test presses, averaged over :data:`STABLE_SEEDS`,
    of models trained on ``ds`` restricted to ``rows``, each scored with the contact net's own
    decision: the decision over time rises past a far quantile of the margin at rest (and the
    CUSUM at a drift chosen on a grid), which two such short trainings place apart whatever
    their labels (it moved contact accuracy by 2-4 % between the import and the file)."""
    from dataclasses import replace

    from fbgforce.model import modeldir as fm
    from fbgforce.trainer.evaluate import evaluate
    from fbgforce.trainer.train import train

    scores = []
    for seed in STABLE_SEEDS:
        model = train([ds.subset(rows)], seed=seed, **STABLE_TRAINING)
        model.in_use = replace(model.in_use, contact_on_margin=0.0, contact_off_margin=0.0,
                               contact_rise_samples=1, contact_cusum_h=0.0, contact_cusum_k=0.0,
                               contact_cusum_lo=0.0, contact_cusum_hi=0.0)
        fm.save(model, directory / f"m{seed}")
        ev = evaluate(directory / f"m{seed}", [reference_path], split="test")
        scores.append([ev[key] for key in METRICS])
    return dict(zip(METRICS, np.mean(scores, axis=0)))


@pytest.fixture(scope="module")
def trained_on_the_simulators_file(small_dataset_path, tmp_path_factory):
    """The simulator's file, its lab logs imported with the clock found, with the clock
    10 ms late and with both clocks in Unix seconds, the rows they all number alike, and the mean scores of models trained on
    the simulator's file (those rows)."""
    from unittest import mock

    directory = tmp_path_factory.mktemp("lab_training")
    ds = dataset.load(small_dataset_path)
    write_lab_logs(ds, directory, rate_hz=500, offset_s=0.1, drift_ppm=80, jitter_s=1e-4)
    _import(directory, out=str(directory / "aligned.csv"))
    align = stagelog.align

    def late(*args, **kwargs):
        found = align(*args, **kwargs)
        found.offset_s += 0.010
        return found

    with mock.patch.object(li, "align", late):
        _import(directory, out=str(directory / "late.csv"))
    _import(_epoch_clocks(directory, directory / "epoch_logs"),
            out=str(directory / "epoch.csv"))
    imports = {name: dataset.load(directory / f"{name}.csv")
               for name in ("aligned", "late", "epoch")}
    # The same rows in the same order for every model: the split is by press and the
    # shuffle by row, so a sample numbered into the next press by one file and not the other
    # would reorder every batch (they lie at press boundaries, 200 of 15,620).
    rows = np.logical_and.reduce([imp.press_id == ds.press_id for imp in imports.values()])
    scores = _mean_scores(ds, rows, small_dataset_path, directory / "own")
    return imports, rows, scores, directory


@pytest.mark.parametrize("name,tolerance,within", [
    ("aligned", 0.02, True), ("late", 0.02, False),
    pytest.param("epoch", 0.03, True, marks=pytest.mark.slow)])
@pytest.mark.slow
def test_a_model_trained_on_the_import_scores_like_one_trained_on_the_simulators_file(
        trained_on_the_simulators_file, small_dataset_path, name, tolerance, within):
    """The issue's goal as written: models trained on the imported dataset score within 2 %
    of models trained on the simulator's own file, every metric, on the same test presses.
    With the stage clock 10 ms late the same comparison fails (so it can). The same logs
    with both clocks in Unix seconds (``epoch``) import to a dataset whose models score within
    3 % (the goal for epoch clocks; measured 1.2 % in force RMSE, the rest within 0.8 %: the
    epoch's 0.24 µs float64 steps move the fitted clock by microseconds, and the trainer's
    path amplifies such label changes, docs/lab-import.md)."""
    imports, rows, own, directory = trained_on_the_simulators_file
    scores = _mean_scores(imports[name], rows, small_dataset_path, directory / name)
    off = {key: abs(scores[key] - own[key]) / abs(own[key]) for key in METRICS}
    assert (max(off.values()) <= tolerance) == within, (own, scores)
