"""Column maps and MATLAB files: a lab's own columns and units read into armfit's SI columns.

Expected values come from the units' definitions (1 lbf = 4.4482216152605 N, 1 in =
0.0254 m exactly; an arc is angle × lever, a force at a lever is torque / lever), applied
here with numpy to the samples written, and from the files each test writes itself
(scipy.io.savemat for MATLAB v4/v5, h5py with MATLAB's 512-byte header for v7.3).
"""

from __future__ import annotations

import json
import math
import sys

import numpy as np
import pyarrow.parquet as pq
import pytest

from armfit.cli.main import cli
from armfit.errors import BadInputError
from armfit.io.colmap import ColumnMap, read_column_map
from armfit.io.trials import (
    DATASET_TRIALS_KEY,
    TrialSource,
    dataset_metadata,
    dataset_sources,
    read_trial,
)

FS = 1000.0
N = 30000          # 30 s at 1 kHz: estimate's 0.1 Hz needs 2 segments of 10 s


def _signals(seed: int = 0) -> dict[str, np.ndarray]:
    """A trial's signals in SI units: time (s), force (N), position (m)."""
    rng = np.random.default_rng(seed)
    t = np.arange(N) / FS
    f = rng.normal(0.0, 1.5, N)
    x = 0.01 * np.sin(2 * np.pi * 0.5 * t) + 1e-4 * rng.normal(size=N)
    return {"t": t, "f": f, "x": x}


def _csv(path, cols: dict[str, np.ndarray]) -> None:
    names = list(cols)
    rows = np.column_stack([cols[n] for n in names])
    path.write_text(",".join(names) + "\n"
                    + "\n".join(",".join(repr(float(v)) for v in r) for r in rows) + "\n")


def _ingest(runner, *args):
    return runner.invoke(cli, ["ingest", *map(str, args)])


def _dataset_columns(path) -> dict[str, np.ndarray]:
    table = pq.read_table(path)
    return {c: table.column(c).to_numpy() for c in table.column_names}


def _one_line(text: str, folder=None) -> str:
    """The one error line of stderr (besides the notes of the maps), with ``folder/``
    removed from the paths (a file named by a manifest is named by its full path)."""
    lines = [ln for ln in text.splitlines() if ln.strip() and " (column map " not in ln]
    assert len(lines) == 1, text
    return lines[0] if folder is None else lines[0].replace(f"{folder}/", "")


def _notes(text: str, folder) -> list[str]:
    """The notes of the column maps on stderr, ``folder/`` removed from the paths."""
    return [ln.replace(f"{folder}/", "") for ln in text.splitlines() if " (column map " in ln]


# ---------------------------------------------------------------------------
# Units: each row's conversion against the unit's definition
# ---------------------------------------------------------------------------

# quantity, unit, extra cells (gain, lever_m, sign), SI per source unit (the definition)
UNIT_CASES = [
    ("time_s", "ms", ("", "", ""), 1e-3),
    ("time_s", "us", ("", "", ""), 1e-6),
    ("time_s", "µs", ("", "", ""), 1e-6),
    ("time_s", "counts", ("0.0005", "", ""), 5e-4),
    ("pos_x_m", "cm", ("", "", ""), 1e-2),
    ("pos_x_m", "mm", ("", "", ""), 1e-3),
    ("pos_x_m", "um", ("", "", ""), 1e-6),
    ("pos_x_m", "in", ("", "", ""), 0.0254),                  # exact, by definition
    ("pos_x_m", "rad", ("", "0.1", ""), 0.1),                 # arc = angle × lever
    ("pos_x_m", "deg", ("", "0.25", ""), math.pi / 180 * 0.25),
    ("pos_x_m", "V", ("0.002", "", ""), 0.002),               # m per V
    ("pos_x_m", "counts", ("1e-6", "", "-1"), -1e-6),
    ("force_x_N", "mN", ("", "", ""), 1e-3),
    ("force_x_N", "kN", ("", "", ""), 1e3),
    ("force_x_N", "lbf", ("", "", ""), 4.4482216152605),      # 0.45359237 kg × 9.80665
    ("force_x_N", "N*m", ("", "0.1", ""), 10.0),              # force = torque / lever
    ("force_x_N", "N·m", ("", "0.05", ""), 20.0),
    ("force_x_N", "Nm", ("", "0.2", "-1"), -5.0),
    ("force_x_N", "V", ("35.15", "", ""), 35.15),             # N per V
    ("force_x_N", "N", ("", "", "-1"), -1.0),
    ("grip_N", "lbf", ("", "", ""), 4.4482216152605),
]


@pytest.mark.parametrize("quantity, unit, extra, factor", UNIT_CASES)
def test_each_unit_converts_by_its_definition(tmp_path, quantity, unit, extra, factor):
    others = {"time_s": "time_s,t,s", "force_x_N": "force_x_N,f,N", "pos_x_m": "pos_x_m,x,m"}
    others.pop(quantity, None)
    gain, lever, sign = extra
    text = ("quantity,source,unit,gain,lever_m,sign\n" + "\n".join(others.values())
            + f"\n{quantity},src,{unit},{gain},{lever},{sign}\n")
    (tmp_path / "m.csv").write_text(text, encoding="utf-8")
    conv = read_column_map(tmp_path / "m.csv").get(quantity)
    raw = np.array([0.5, -2.0, 3.25])
    assert conv.factor == pytest.approx(factor, rel=1e-15)
    np.testing.assert_allclose(conv.apply(raw), raw * factor, rtol=1e-15)


def test_conversions_are_described_in_words(tmp_path):
    # the text echoed on stderr and kept in the dataset: gain, unit factor, lever, sign
    (tmp_path / "m.csv").write_text(
        "quantity,source,unit,gain,lever_m,sign\ntime_s,t,ms,,,\nforce_x_N,vir,V,35.15,,\n"
        "pos_x_m,ang,deg,,0.1,-1\nforce_y_N,tq,N*m,,0.1,\npos_y_m,qm,m,,,\n")
    cmap = read_column_map(tmp_path / "m.csv")
    assert cmap.describe() == (
        "time_s = 0.001 s/ms × t (ms); force_x_N = 35.15 N/V × vir (V); "
        "pos_x_m = −0.0174532925199433 rad/deg × ang (deg) × 0.1 m; "
        "force_y_N = tq (N*m) / 0.1 m; pos_y_m = qm (m)")


def test_a_map_survives_its_json_form(tmp_path):
    (tmp_path / "m.csv").write_text("quantity,source,unit,gain,value\nrate_Hz,,kHz,,2\n"
                                    "force_z_N,V1,V,10\npos_z_m,enc:2,counts,1e-5\n")
    cmap = read_column_map(tmp_path / "m.csv")
    assert cmap.rate_Hz == 2000.0                       # 2 kHz
    assert cmap.get("pos_z_m").name == "enc" and cmap.get("pos_z_m").column == 2
    back = ColumnMap.from_dict(json.loads(json.dumps(cmap.to_dict())), where="test")
    assert back == cmap


# ---------------------------------------------------------------------------
# Bad maps: one line naming the map, its column and row, and what was expected
# ---------------------------------------------------------------------------

GOOD = {"time": "time_s,t,s", "force": "force_x_N,f,N", "pos": "pos_x_m,x,m"}
HEAD = "quantity,source,unit,gain,lever_m,sign,value"

BAD_MAPS = [
    ("unknown quantity", [HEAD, GOOD["time"], GOOD["force"], GOOD["pos"], "velocity_x,v,m"],
     "map.csv, column 'quantity', row 4: unknown quantity 'velocity_x'; expected one of "
     "rate_Hz, time_s, force_x_N, force_y_N, force_z_N, pos_x_m, pos_y_m, pos_z_m, grip_N, "
     "ref_x_N, ref_x_m, ref_y_N, ref_y_m, ref_z_N, ref_z_m"),
    ("twice", [HEAD, GOOD["time"], GOOD["force"], GOOD["pos"], "force_x_N,g,N"],
     "map.csv, column 'quantity', row 4: force_x_N is given twice (also row 2); which one "
     "is meant cannot be known"),
    ("time and rate", [HEAD, GOOD["time"], GOOD["force"], GOOD["pos"], "rate_Hz,,Hz,,,,1000"],
     "map.csv, column 'quantity', row 4: both time_s (row 1) and rate_Hz (row 4) are given; "
     "give one: the time column, or the rate of a file without one"),
    ("no time", [HEAD, GOOD["force"], GOOD["pos"]],
     "map.csv, column 'quantity': no time_s row and no rate_Hz row; expected the time "
     "column (time_s,<source>,<unit>) or the sampling rate of a file without one (rate_Hz "
     "with the rate in the value column)"),
    ("no force", [HEAD, GOOD["time"], GOOD["pos"]],
     "map.csv, column 'quantity': the map gives no force or no position; expected a "
     "force_<a>_N and a pos_<a>_m row for the stimulated axis"),
    ("V without gain", [HEAD, GOOD["time"], "force_x_N,vir,V", GOOD["pos"]],
     "map.csv, column 'gain', row 2: unit V needs a gain: the SI units of force_x_N per V "
     "(e.g. N/V)"),
    ("negative gain", [HEAD, GOOD["time"], "force_x_N,vir,V,-35", GOOD["pos"]],
     "map.csv, column 'gain', row 2: '-35' is not a positive number (SI units per raw "
     "unit; give the direction in the sign column)"),
    ("gain of a known unit", [HEAD, GOOD["time"], "force_x_N,f,N,2", GOOD["pos"]],
     "map.csv, column 'gain', row 2: a gain is given for unit N, whose conversion is known; "
     "a gain applies to a raw signal (V, counts); give the direction in the sign column"),
    ("not a force", [HEAD, GOOD["time"], "force_x_N,f,kg", GOOD["pos"]],
     "map.csv, column 'unit', row 2: unit 'kg' cannot give force_x_N; expected a force unit "
     "(N, mN, kN, lbf), a torque (N*m) with lever_m, or a raw signal (V, counts) with a "
     "gain in N per unit"),
    ("not a length", [HEAD, GOOD["time"], GOOD["force"], "pos_x_m,x,N"],
     "map.csv, column 'unit', row 3: unit 'N' cannot give pos_x_m; expected a length unit "
     "(m, cm, mm, um, in), an angle (rad, deg) with lever_m, or a raw signal (V, counts) "
     "with a gain in m per unit"),
    ("angle without lever", [HEAD, GOOD["time"], GOOD["force"], "pos_x_m,ang,rad"],
     "map.csv, column 'lever_m', row 3: unit rad needs lever_m, the lever arm in m (the arc "
     "length is angle × lever)"),
    ("lever of a length", [HEAD, GOOD["time"], GOOD["force"], "pos_x_m,x,mm,,0.1"],
     "map.csv, column 'lever_m', row 3: lever_m is given for unit mm; a lever applies only "
     "to an angle (rad, deg) or a torque (N*m)"),
    ("bad sign", [HEAD, GOOD["time"], "force_x_N,f,N,,,2", GOOD["pos"]],
     "map.csv, column 'sign', row 2: '2' is not a sign; expected 1 or -1 (blank: 1)"),
    ("rate with a source", [HEAD, "rate_Hz,fs,Hz,,,,1000", GOOD["force"], GOOD["pos"]],
     "map.csv, column 'source', row 1: rate_Hz takes no source; give the sampling rate in "
     "the value column"),
    ("rate without value", [HEAD, "rate_Hz,,Hz", GOOD["force"], GOOD["pos"]],
     "map.csv, column 'value', row 1: no value for rate_Hz; expected the sampling rate "
     "(e.g. 1000)"),
    ("time unit of a rate", [HEAD, "rate_Hz,,s,,,,1000", GOOD["force"], GOOD["pos"]],
     "map.csv, column 'unit', row 1: unit 's' is not a rate; expected Hz or kHz, with the "
     "rate in the value column"),
    ("matrix column 0", [HEAD, GOOD["time"], "force_x_N,io:0,N", GOOD["pos"]],
     "map.csv, column 'source', row 2: column 0 of io: matrix columns count from 1, as in "
     "MATLAB (io:1 is the first)"),
    ("MATLAB's comma", ["quantity,source,unit", GOOD["time"], "force_x_N,io(:,2),N",
                        GOOD["pos"]],
     "map.csv, row 2: 4 cells for 3 columns of the header (the comma of a source io(:,…) "
     "splits it: name a matrix column as io:k)"),
    ("unknown map column", ["quantity,source,unit,lever", GOOD["time"]],
     "map.csv, column 'lever': unknown map column 'lever'; expected the columns quantity, "
     "source, unit, gain, lever_m, sign, value (the first three required)"),
    ("no unit column", ["quantity,source", "time_s,t"],
     "map.csv, column 'unit': missing map column; expected the columns quantity,source,"
     "unit[,gain][,lever_m][,sign][,value]"),
]


@pytest.mark.parametrize("case, lines, message", BAD_MAPS, ids=[c[0] for c in BAD_MAPS])
def test_a_bad_map_is_one_line_naming_map_column_and_row(runner, tmp_path, monkeypatch,
                                                         case, lines, message):
    monkeypatch.chdir(tmp_path)
    s = _signals()
    _csv(tmp_path / "sub-01_axis-x_grip-1N.csv", {"t": s["t"], "f": s["f"], "x": s["x"]})
    (tmp_path / "map.csv").write_text("\n".join(lines) + "\n", encoding="utf-8")
    res = _ingest(runner, "sub-01_axis-x_grip-1N.csv", "--map", "map.csv", "-o", "d.parquet")
    assert res.exit_code == 65, res.output
    assert _one_line(res.stderr) == f"armfit: error: {message}"
    assert not (tmp_path / "d.parquet").exists()


def test_a_missing_map_is_a_missing_input(runner, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    _csv(tmp_path / "sub-01_axis-x_grip-1N.csv", _signals())
    res = _ingest(runner, "sub-01_axis-x_grip-1N.csv", "--map", "nope.csv", "-o", "d.parquet")
    assert res.exit_code == 66
    assert _one_line(res.stderr) == "armfit: error: nope.csv: no such column map file"


def test_a_map_without_the_stimulated_axis_names_map_and_trial(runner, tmp_path,
                                                                monkeypatch):
    monkeypatch.chdir(tmp_path)
    _csv(tmp_path / "sub-01_axis-y_grip-1N.csv", _signals())
    (tmp_path / "map.csv").write_text("quantity,source,unit\ntime_s,t,s\nforce_x_N,f,N\n"
                                      "pos_x_m,x,m\n")
    res = _ingest(runner, "sub-01_axis-y_grip-1N.csv", "--map", "map.csv", "-o", "d.parquet")
    assert res.exit_code == 65
    assert _one_line(res.stderr) == (
        "armfit: error: sub-01_axis-y_grip-1N.csv: the column map map.csv has no row for "
        "force_y_N, the force on the stimulated axis y (it gives force_x_N, pos_x_m); add a "
        "row force_y_N,<source>,<unit>")


def test_map_given_twice_is_a_usage_error(runner, tmp_path):
    res = runner.invoke(cli, ["ingest", "x.csv", "--map", "a.csv", "--map", "b.csv", "-o",
                              str(tmp_path / "d.parquet")])
    assert res.exit_code == 2
    assert "given 2 times (a.csv, b.csv)" in res.stderr


# ---------------------------------------------------------------------------
# CSV and Parquet files in a lab's own columns and units
# ---------------------------------------------------------------------------

LAB_MAP = ("quantity,source,unit,gain,lever_m,sign\n"
           "time_s,Time [ms],ms,,,\nforce_x_N,F (mN),mN,,,-1\npos_x_m,X,mm,,,\n"
           "grip_N,Grip,lbf,,,\n")


def _lab_file(path, s, *, grip=True):
    cols = {"Time [ms]": s["t"] * 1000.0, "F (mN)": -s["f"] * 1000.0, "X": s["x"] * 1000.0}
    if grip:
        cols["Grip"] = np.full(N, 2.0 / 4.4482216152605)     # 2 N in lbf
    _csv(path, cols)


def test_a_lab_csv_becomes_armfits_si_columns(runner, tmp_path, monkeypatch):
    # the dataset holds the SI values of the definitions: ms/1000, -mN/1000, mm/1000, lbf
    monkeypatch.chdir(tmp_path)
    s1, s2 = _signals(1), _signals(2)
    _lab_file(tmp_path / "lab_a.csv", s1)
    _lab_file(tmp_path / "lab_b.csv", s2)
    (tmp_path / "lab.csv").write_text(LAB_MAP)
    (tmp_path / "manifest.csv").write_text("file,subject,axis,grip_N\nlab_a.csv,01,x,2\n"
                                           "lab_b.csv,02,x,2\n")
    res = _ingest(runner, "--manifest", "manifest.csv", "--map", "lab.csv", "-o", "d.parquet")
    assert res.exit_code == 0, res.stderr
    # one line for the map, not one per file
    assert _notes(res.stderr, tmp_path) == [(
        "armfit: lab_a.csv and 1 more file(s) (column map lab.csv): time_s = 0.001 s/ms × "
        "Time [ms] (ms); force_x_N = −0.001 N/mN × F (mN) (mN); pos_x_m = 0.001 m/mm × X "
        "(mm); grip_N = 4.4482216152605 N/lbf × Grip (lbf)")]
    cols = _dataset_columns(tmp_path / "d.parquet")
    np.testing.assert_allclose(cols["force_x_N"][:N], s1["f"], rtol=1e-14, atol=1e-15)
    np.testing.assert_allclose(cols["pos_x_m"][:N], s1["x"], rtol=1e-14, atol=1e-18)
    np.testing.assert_allclose(cols["grip_N"][N:], 2.0, rtol=1e-14)
    assert np.isnan(cols["force_y_N"]).all()
    meta = dataset_metadata(tmp_path / "d.parquet")
    assert [m["fs"] for m in meta] == [FS, FS]
    # provenance: the map's rows as written and its conversions, per trial
    raw = json.loads(pq.read_metadata(tmp_path / "d.parquet").metadata[
        DATASET_TRIALS_KEY.encode()])
    assert raw[0]["column_map"]["file"] == "lab.csv"
    assert raw[0]["column_map"]["rows"][1] == {"quantity": "force_x_N", "source": "F (mN)",
                                               "unit": "mN", "sign": "-1"}
    assert raw[0]["column_map"]["conversions"].startswith("time_s = 0.001 s/ms")


def test_a_dataset_keeps_the_map_when_read_again(runner, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    _lab_file(tmp_path / "sub-01_axis-x_grip-2N.csv", _signals(3))
    (tmp_path / "lab.csv").write_text(LAB_MAP)
    assert _ingest(runner, "sub-01_axis-x_grip-2N.csv", "--map", "lab.csv", "-o",
                   "d.parquet").exit_code == 0
    trial = read_trial(dataset_sources(tmp_path / "d.parquet")[0])
    assert trial.meta.column_map == read_column_map("lab.csv")
    # a dataset ingested again keeps the record (its trials are SI already)
    res = _ingest(runner, "d.parquet", "-o", "d2.parquet")
    assert res.exit_code == 0, res.stderr
    assert "column map" not in res.stderr
    assert dataset_metadata("d2.parquet")[0]["column_map"] == read_column_map("lab.csv")


def test_a_native_file_with_no_map_has_no_map_record(runner, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    s = _signals()
    _csv(tmp_path / "sub-01_axis-x_grip-1N.csv",
         {"time_s": s["t"], "force_x_N": s["f"], "pos_x_m": s["x"]})
    assert _ingest(runner, "sub-01_axis-x_grip-1N.csv", "-o", "d.parquet").exit_code == 0
    raw = json.loads(pq.read_metadata("d.parquet").metadata[DATASET_TRIALS_KEY.encode()])
    assert "column_map" not in raw[0]


def test_a_file_without_time_uses_the_maps_rate(runner, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    s = _signals()
    _csv(tmp_path / "box.csv", {"V1": s["f"], "V2": s["x"]})
    (tmp_path / "m.csv").write_text("quantity,source,unit,gain,value\n"
                                    "rate_Hz,,Hz,,1000\nforce_x_N,V1,V,1\npos_x_m,V2,V,1\n")
    (tmp_path / "manifest.csv").write_text("file,subject,axis,grip_N,map\nbox.csv,b,x,0,m.csv\n")
    res = _ingest(runner, "--manifest", "manifest.csv", "-o", "d.parquet", "--json")
    assert res.exit_code == 0, res.stderr
    item = json.loads(res.stdout)["items"][0]
    assert (item["fs"], item["t0_s"], item["n_samples"]) == (FS, 0.0, N)
    assert item["column_map"] == "m.csv"
    assert "time_s = sample index / 1000 Hz" in res.stderr


def test_a_rate_below_100_hz_is_refused(runner, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    s = _signals()
    _csv(tmp_path / "box.csv", {"V1": s["f"], "V2": s["x"]})
    (tmp_path / "m.csv").write_text("quantity,source,unit,gain,value\n"
                                    "rate_Hz,,Hz,,50\nforce_x_N,V1,V,1\npos_x_m,V2,V,1\n")
    (tmp_path / "manifest.csv").write_text("file,subject,axis,grip_N\nbox.csv,b,x,0\n")
    res = _ingest(runner, "--manifest", "manifest.csv", "--map", "m.csv", "-o", "d.parquet")
    assert res.exit_code == 65
    assert _one_line(res.stderr, tmp_path) == (
        "armfit: error: box.csv: sampling rate 50 Hz (rate_Hz of the column map m.csv) is "
        "below 100 Hz, implausible for a haptic device")


@pytest.mark.parametrize("case, expected", [
    ("nan", "armfit: error: lab.csv, column 'F (mN)', row 5: blank value (or NaN); force "
            "and position must be finite numbers (force_x_N = −0.001 N/mN × F (mN) (mN), "
            "column map lab_map.csv row 2)"),
    ("jitter", "armfit: error: lab.csv, column 'Time [ms]', row 11: non-uniform time: "
               "interval 0.0015 s vs period 0.001 s (jitter over 1 % of the period; dropped "
               "or repeated samples?) (time_s = 0.001 s/ms × Time [ms] (ms), column map "
               "lab_map.csv row 1)"),
    ("missing", "armfit: error: lab.csv, column 'X': no such column, named by the column "
                "map for pos_x_m (map row 3); the file's columns: Time [ms], F (mN), Pos"),
    ("constant", "armfit: error: lab.csv, column 'F (mN)': force on the stimulated axis is "
                 "zero throughout: no excitation (force_x_N = −0.001 N/mN × F (mN) (mN), "
                 "column map lab_map.csv row 2)"),
])
def test_checks_after_conversion_name_the_source_column(runner, tmp_path, monkeypatch,
                                                        case, expected):
    monkeypatch.chdir(tmp_path)
    s = _signals()
    cols = {"Time [ms]": s["t"] * 1000.0, "F (mN)": -s["f"] * 1000.0, "X": s["x"] * 1000.0}
    if case == "nan":
        cols["F (mN)"][4] = np.nan
    elif case == "jitter":
        cols["Time [ms]"][10:] += 0.5           # half a period late from data row 11
    elif case == "missing":
        cols["Pos"] = cols.pop("X")
    else:
        cols["F (mN)"][:] = 0.0
    _csv(tmp_path / "lab.csv", cols)
    (tmp_path / "lab_map.csv").write_text(LAB_MAP.replace("grip_N,Grip,lbf,,,\n", ""))
    (tmp_path / "manifest.csv").write_text("file,subject,axis,grip_N,map\n"
                                           "lab.csv,01,x,1,lab_map.csv\n")
    res = _ingest(runner, "--manifest", "manifest.csv", "-o", "d.parquet")
    assert res.exit_code == 65, res.stderr
    assert _one_line(res.stderr, tmp_path) == expected


def test_saturation_warning_names_the_source_column(runner, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    s = _signals()
    s["f"][6] = 9.0                               # 9 N ≥ the 8.5 N device limit, row 7
    _csv(tmp_path / "lab.csv", {"Time [ms]": s["t"] * 1000.0, "F (mN)": -s["f"] * 1000.0,
                                "X": s["x"] * 1000.0})
    (tmp_path / "m.csv").write_text(LAB_MAP.replace("grip_N,Grip,lbf,,,\n", ""))
    (tmp_path / "manifest.csv").write_text("file,subject,axis,grip_N\nlab.csv,01,x,1\n")
    res = _ingest(runner, "--manifest", "manifest.csv", "--map", "m.csv", "-o", "d.parquet")
    assert res.exit_code == 0, res.stderr
    assert (f"warning: {tmp_path}/lab.csv, column 'F (mN)' (force_x_N), row 7: |force| reaches the "
            "device limit 8.5 N in 1 sample(s)") in res.stderr


def test_a_parquet_file_with_a_map_per_manifest_row(runner, tmp_path, monkeypatch):
    # two maps: a row's own, and --map for the row without one; the file names follow
    # no pattern (the manifest names them)
    import pyarrow as pa
    monkeypatch.chdir(tmp_path)
    s1, s2 = _signals(4), _signals(5)
    pq.write_table(pa.table({"tick": np.arange(N), "F": s1["f"], "ang": s1["x"] / 0.1}),
                   tmp_path / "a.parquet")
    _csv(tmp_path / "b.csv", {"t": s2["t"], "f": s2["f"], "x": s2["x"]})
    (tmp_path / "a_map.csv").write_text("quantity,source,unit,gain,lever_m\n"
                                        "time_s,tick,counts,0.001,\nforce_x_N,F,N,,\n"
                                        "pos_x_m,ang,rad,,0.1\n")
    (tmp_path / "b_map.csv").write_text("quantity,source,unit\ntime_s,t,s\nforce_x_N,f,N\n"
                                        "pos_x_m,x,m\n")
    (tmp_path / "manifest.csv").write_text("file,subject,axis,grip_N,map\n"
                                           "a.parquet,01,x,1,a_map.csv\nb.csv,02,x,1,\n")
    res = _ingest(runner, "--manifest", "manifest.csv", "--map", "b_map.csv", "-o",
                  "d.parquet")
    assert res.exit_code == 0, res.stderr
    assert _notes(res.stderr, tmp_path) == [
        "armfit: a.parquet (column map a_map.csv): time_s = 0.001 s/count × tick (counts); "
        "force_x_N = F (N); pos_x_m = ang (rad) × 0.1 m",
        "armfit: b.csv (column map b_map.csv): time_s = t (s); force_x_N = f (N); "
        "pos_x_m = x (m)"]
    cols = _dataset_columns("d.parquet")
    np.testing.assert_allclose(cols["pos_x_m"][:N], s1["x"], rtol=1e-14, atol=1e-18)
    np.testing.assert_allclose(cols["force_x_N"][N:], s2["f"], rtol=0, atol=0)


def test_an_output_never_replaces_a_map(runner, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    _csv(tmp_path / "sub-01_axis-x_grip-1N.csv", _signals())
    (tmp_path / "m.csv").write_text("quantity,source,unit\ntime_s,t,s\nforce_x_N,f,N\n"
                                    "pos_x_m,x,m\n")
    before = (tmp_path / "m.csv").read_bytes()
    res = runner.invoke(cli, ["estimate", "sub-01_axis-x_grip-1N.csv", "--map", "m.csv",
                              "-o", "s.parquet", "--csv", "m.csv", "--overwrite"])
    assert res.exit_code == 73
    assert "m.csv: output path is also an input" in res.stderr
    (tmp_path / "manifest.csv").write_text("file,subject,axis,grip_N,map\n"
                                           "sub-01_axis-x_grip-1N.csv,01,x,1,m.csv\n")
    res = runner.invoke(cli, ["estimate", "--manifest", "manifest.csv", "-o", "s.parquet",
                              "--csv", "m.csv", "--overwrite"])
    assert res.exit_code == 73
    assert "m.csv: a column map named by the manifest manifest.csv" in res.stderr
    assert (tmp_path / "m.csv").read_bytes() == before


def test_estimate_through_a_map_equals_estimate_of_the_si_file(runner, tmp_path,
                                                               monkeypatch):
    # the same trial written in SI columns and in a lab's units gives the same spectra
    monkeypatch.chdir(tmp_path)
    s = _signals(7)
    _csv(tmp_path / "sub-01_axis-x_grip-1N.csv",
         {"time_s": s["t"], "force_x_N": s["f"], "pos_x_m": s["x"]})
    (tmp_path / "lab").mkdir()
    _lab_file(tmp_path / "lab" / "sub-01_axis-x_grip-1N.csv", s, grip=False)
    (tmp_path / "m.csv").write_text(LAB_MAP.replace("grip_N,Grip,lbf,,,\n", ""))
    assert runner.invoke(cli, ["estimate", "sub-01_axis-x_grip-1N.csv", "-o", "a.parquet",
                               "--csv", "a.csv"]).exit_code == 0
    res = runner.invoke(cli, ["estimate", "lab", "--map", "m.csv", "-o", "b.parquet",
                              "--csv", "b.csv"])
    assert res.exit_code == 0, res.stderr
    a = np.genfromtxt("a.csv", delimiter=",", names=True, dtype=None, encoding="utf-8")
    b = np.genfromtxt("b.csv", delimiter=",", names=True, dtype=None, encoding="utf-8")
    np.testing.assert_allclose(b["mag_db"], a["mag_db"], rtol=0, atol=1e-9)
    np.testing.assert_allclose(b["phase_deg"], a["phase_deg"], rtol=0, atol=1e-9)


# ---------------------------------------------------------------------------
# MATLAB files
# ---------------------------------------------------------------------------

MAT_MAP = ("quantity,source,unit,gain,lever_m\ntime_s,t,s,,\nforce_x_N,io:2,N*m,,0.1\n"
           "pos_x_m,io:1,rad,,0.1\n")


def _mat_manifest(tmp_path, name: str, map_name: str = "m.csv") -> None:
    (tmp_path / map_name).write_text(MAT_MAP)
    (tmp_path / "manifest.csv").write_text(f"file,subject,axis,grip_N,map\n"
                                           f"{name},AV,x,1,{map_name}\n")


def _expected(s):
    # io(:,1) angle in rad, io(:,2) torque in N·m; lever 0.1 m
    return s["x"] / 0.1 * 0.1, s["f"] * 0.1 / 0.1


@pytest.mark.parametrize("fmt", ["5", "4"])
def test_a_matlab_file_is_read_through_its_map(runner, tmp_path, monkeypatch, fmt):
    import scipy.io
    monkeypatch.chdir(tmp_path)
    s = _signals(8)
    # t as a row vector (1×n), io an n×2 matrix [angle, torque]
    scipy.io.savemat(tmp_path / "rec.mat", {"t": s["t"][None, :],
                                            "io": np.column_stack([s["x"] / 0.1,
                                                                   s["f"] * 0.1])},
                     format=fmt)
    _mat_manifest(tmp_path, "rec.mat")
    res = _ingest(runner, "--manifest", "manifest.csv", "-o", "d.parquet")
    assert res.exit_code == 0, res.stderr
    cols = _dataset_columns("d.parquet")
    x, f = _expected(s)
    np.testing.assert_allclose(cols["pos_x_m"], x, rtol=1e-14, atol=1e-18)
    np.testing.assert_allclose(cols["force_x_N"], f, rtol=1e-14, atol=1e-15)


def _write_v73(path, variables: dict[str, np.ndarray], classes: dict[str, str] | None = None):
    """A MATLAB v7.3 file as MATLAB writes it: HDF5 after a 512-byte user block whose
    first 128 bytes are MATLAB's header, every array stored transposed (column-major)."""
    import h5py
    with h5py.File(path, "w", userblock_size=512) as fh:
        for name, value in variables.items():
            ds = fh.create_dataset(name, data=np.asarray(value).T)
            ds.attrs["MATLAB_class"] = np.bytes_((classes or {}).get(name, "double"))
            if (classes or {}).get(name, "double") not in ("double",):
                ds.attrs["MATLAB_object_decode"] = np.int32(3)
    header = b"MATLAB 7.3 MAT-file, Platform: GLNXA64, Created on: Mon Jan  1 00:00:00 2024 "
    header += b"HDF5 schema 1.00 ."
    block = header.ljust(116, b" ") + b"\0" * 8 + b"\x00\x02IM"
    with open(path, "r+b") as fh:
        fh.write(block.ljust(512, b"\0"))


def test_a_matlab_v73_file_is_read_with_h5py_and_transposed_back(runner, tmp_path,
                                                                  monkeypatch):
    monkeypatch.chdir(tmp_path)
    s = _signals(9)
    io = np.column_stack([s["x"] / 0.1, s["f"] * 0.1])        # n×2 in MATLAB
    _write_v73(tmp_path / "rec.mat", {"t": s["t"][:, None], "io": io})
    import h5py
    with h5py.File(tmp_path / "rec.mat", "r") as fh:
        assert fh["io"].shape == (2, N)                        # stored transposed
    assert (tmp_path / "rec.mat").read_bytes()[:10] == b"MATLAB 7.3"
    _mat_manifest(tmp_path, "rec.mat")
    res = _ingest(runner, "--manifest", "manifest.csv", "-o", "d.parquet")
    assert res.exit_code == 0, res.stderr
    cols = _dataset_columns("d.parquet")
    x, f = _expected(s)
    np.testing.assert_allclose(cols["pos_x_m"], x, rtol=1e-14, atol=1e-18)
    np.testing.assert_allclose(cols["force_x_N"], f, rtol=1e-14, atol=1e-15)
    assert dataset_metadata("d.parquet")[0]["fs"] == FS


def test_a_v73_file_without_h5py_says_how_to_install_it(runner, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    s = _signals()
    _write_v73(tmp_path / "rec.mat", {"t": s["t"], "io": np.column_stack([s["x"], s["f"]])})
    _mat_manifest(tmp_path, "rec.mat")
    monkeypatch.setitem(sys.modules, "h5py", None)            # import h5py fails
    res = _ingest(runner, "--manifest", "manifest.csv", "-o", "d.parquet")
    assert res.exit_code == 1
    assert _one_line(res.stderr, tmp_path) == (
        "armfit: error: rec.mat: a MATLAB v7.3 file is HDF5 and needs h5py: pip install "
        "armfit[hdf5]")


def test_matlab_class_objects_are_refused_in_one_line(runner, tmp_path, monkeypatch):
    # a v7.3 MCOS object: MATLAB_class names the class, MATLAB_object_decode marks it
    monkeypatch.chdir(tmp_path)
    _write_v73(tmp_path / "rec.mat", {"t": np.arange(N) / FS,
                                      "io": np.zeros((6, 1), np.uint32)},
               classes={"io": "nldat"})
    _mat_manifest(tmp_path, "rec.mat")
    res = _ingest(runner, "--manifest", "manifest.csv", "-o", "d.parquet")
    assert res.exit_code == 65
    assert _one_line(res.stderr, tmp_path) == (
        "armfit: error: rec.mat: variable 'io' holds MATLAB class objects (nldat) that "
        "cannot be read outside MATLAB; in MATLAB save plain arrays instead, e.g. "
        "io = double(io); save('file.mat', 'io', '-v7')")


@pytest.mark.parametrize("variables, map_row, message", [
    ({"io": np.zeros((N, 2))}, "force_x_N,io,N",
     "rec.mat, column 'io': variable 'io' is a 30000×2 matrix; name one of its columns, "
     "io:1 to io:2"),
    ({"io": np.zeros((N, 2))}, "force_x_N,io:3,N",
     "rec.mat, column 'io:3': variable 'io' has 2 column(s), not 3"),
    ({"io": np.zeros((N, 2))}, "force_x_N,tq,N",
     "rec.mat, column 'tq': no variable 'tq' in the file; it holds ang, io, t"),
    ({"tq": "text"}, "force_x_N,tq,N",
     "rec.mat, column 'tq': variable 'tq' is text, not a numeric array; save the signal as "
     "a numeric vector (double)"),
    ({"tq": np.arange(N - 1.0)}, "force_x_N,tq,N",
     "rec.mat, column 'tq': 29999 samples, but t has 30000; the signals of a trial have "
     "one length"),
])
def test_matlab_variables_that_are_no_signal(runner, tmp_path, monkeypatch, variables,
                                             map_row, message):
    import scipy.io
    monkeypatch.chdir(tmp_path)
    scipy.io.savemat(tmp_path / "rec.mat", {"t": np.arange(N) / FS,
                                            "ang": np.ones(N), **variables})
    (tmp_path / "m.csv").write_text(f"quantity,source,unit\ntime_s,t,s\n{map_row}\n"
                                    "pos_x_m,ang,m\n")
    (tmp_path / "manifest.csv").write_text("file,subject,axis,grip_N\nrec.mat,AV,x,1\n")
    res = _ingest(runner, "--manifest", "manifest.csv", "--map", "m.csv", "-o", "d.parquet")
    assert res.exit_code == 65, res.stderr
    assert _one_line(res.stderr, tmp_path) == f"armfit: error: {message}"


def test_a_matlab_file_without_a_map_is_refused(runner, tmp_path, monkeypatch):
    import scipy.io
    monkeypatch.chdir(tmp_path)
    scipy.io.savemat(tmp_path / "sub-01_axis-x_grip-1N.mat", {"t": np.arange(N) / FS})
    res = _ingest(runner, ".", "-o", "d.parquet")
    assert res.exit_code == 65
    assert _one_line(res.stderr) == (
        "armfit: error: sub-01_axis-x_grip-1N.mat: a MATLAB file has no column names armfit "
        "knows: a column map is needed (--map FILE, or the manifest's column 'map') to say "
        "which variables hold time, force and position")


def test_not_a_matlab_file(tmp_path):
    (tmp_path / "rec.mat").write_bytes(b"hello, not MATLAB\n" * 20)
    (tmp_path / "m.csv").write_text(MAT_MAP)
    src = TrialSource(str(tmp_path / "rec.mat"), "AV", "x", 1.0,
                      column_map=read_column_map(tmp_path / "m.csv"))
    with pytest.raises(BadInputError, match=r"rec.mat: unreadable MATLAB file: "):
        read_trial(src)


def test_reading_a_native_estimate_loads_no_matlab_reader(tmp_path):
    # the MATLAB readers are imported only for a .mat file
    import subprocess
    s = _signals()
    _csv(tmp_path / "sub-01_axis-x_grip-1N.csv", {"t": s["t"], "f": s["f"], "x": s["x"]})
    (tmp_path / "m.csv").write_text("quantity,source,unit\ntime_s,t,s\nforce_x_N,f,N\n"
                                    "pos_x_m,x,m\n")
    code = ("import sys, json\nfrom armfit.cli.main import cli\n"
            f"try:\n    cli(['-q', 'estimate', {str(tmp_path / 'sub-01_axis-x_grip-1N.csv')!r},"
            f" '--map', {str(tmp_path / 'm.csv')!r}, '-o', {str(tmp_path / 's.parquet')!r}],"
            " prog_name='armfit')\nexcept SystemExit as e:\n    assert not e.code, e.code\n"
            "print(json.dumps(sorted(sys.modules)), file=sys.stderr)")
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True)
    loaded = set(json.loads(res.stderr.strip().splitlines()[-1]))
    assert "armfit.io.colmap" in loaded
    assert not loaded & {"scipy.io", "h5py", "armfit.io.matlab"}


def test_resample_reads_the_rates_through_the_maps(runner, tmp_path, monkeypatch):
    # two files without time, at 1000 Hz and 500 Hz by their maps: the most common rate
    # (a tie: the first file's) is the reference, the other is resampled to it
    monkeypatch.chdir(tmp_path)
    s = _signals(6)
    _csv(tmp_path / "fast.csv", {"V1": s["f"], "V2": s["x"]})
    _csv(tmp_path / "slow.csv", {"V1": s["f"][::2], "V2": s["x"][::2]})
    for rate in (1000, 500):
        (tmp_path / f"m{rate}.csv").write_text(
            f"quantity,source,unit,gain,value\nrate_Hz,,Hz,,{rate}\nforce_x_N,V1,V,1,\n"
            "pos_x_m,V2,V,1,\n")
    (tmp_path / "manifest.csv").write_text("file,subject,axis,grip_N,map\n"
                                           "fast.csv,01,x,1,m1000.csv\n"
                                           "slow.csv,02,x,1,m500.csv\n")
    res = _ingest(runner, "--manifest", "manifest.csv", "-o", "d.parquet", "--resample")
    assert res.exit_code == 0, res.stderr
    assert "slow.csv: resampled from 500 Hz to 1000 Hz" in res.stderr
    meta = dataset_metadata("d.parquet")
    assert [(m["fs"], m["n_samples"]) for m in meta] == [(FS, N), (FS, N)]
    assert meta[1]["column_map"] == read_column_map("m500.csv")
