"""`armfit ingest` through click's CliRunner: bad input, exit codes, outputs, options.

Exit codes are the documented ones (armfit/errors.py): 0 ok, 65 bad data, 66 nothing to
read, 73 output refused. Every bad-input case must leave no output (nor a temporary) behind.
"""

from __future__ import annotations

import json
import re

import numpy as np
import pytest

from armfit.cli.main import cli
from armfit.io.trials import dataset_metadata

NAME = "sub-01_axis-y_grip-2N"


def _ingest(runner, *args):
    return runner.invoke(cli, ["ingest", *map(str, args)])


def _as_text(col, bad_index, bad_text):
    """A numeric column as text cells, with one cell replaced."""
    cells = [repr(float(v)) for v in col]
    cells[bad_index] = bad_text
    return cells


def _truncate(path, keep_fraction=None, drop_bytes=None):
    data = path.read_bytes().rstrip(b"\n")
    cut = len(data) - drop_bytes if drop_bytes else int(len(data) * keep_fraction)
    path.write_bytes(data[:cut])


# Each case: file name, how to alter the good columns (or the written file), the
# expected message (file, column and row as the contract asks), and the exit code.
def _case_missing_column(c):
    del c["pos_y_m"]


def _case_non_numeric(c):
    c["force_y_N"] = _as_text(c["force_y_N"], 6, "abc")


def _case_nan_position(c):
    c["pos_y_m"][4] = np.nan


def _case_inf_force(c):
    c["force_y_N"][8] = np.inf


def _case_nan_time(c):
    c["time_s"][2] = np.nan


def _case_non_monotonic(c):
    c["time_s"][[9, 10]] = c["time_s"][[10, 9]]


def _case_non_uniform(c):
    c["time_s"][50:] += 0.005  # half a 10 ms period missing before row 51


def _case_short(c):
    for k in c:
        c[k] = c[k][:1000]  # 10 s at 100 Hz; 0.1 Hz needs 2 / 0.1 = 20 s


def _case_header_only(c):
    for k in c:
        c[k] = c[k][:0]


def _case_zero_force(c):
    c["force_y_N"][:] = 0.0


def _case_constant_force(c):
    c["force_y_N"][:] = 1.0


BAD_CASES = {
    "missing column": (f"{NAME}.csv", _case_missing_column,
                       r"column 'pos_y_m': missing required column"),
    "non-numeric": (f"{NAME}.csv", _case_non_numeric,
                    r"column 'force_y_N', row 7: non-numeric value 'abc'"),
    "non-numeric parquet": (f"{NAME}.parquet", _case_non_numeric,
                            r"column 'force_y_N', row 7: non-numeric value 'abc'"),
    "NaN position": (f"{NAME}.csv", _case_nan_position,
                     r"column 'pos_y_m', row 5: blank value"),
    "inf force": (f"{NAME}.parquet", _case_inf_force, r"column 'force_y_N', row 9: inf value"),
    "NaN time": (f"{NAME}.parquet", _case_nan_time,
                 r"column 'time_s', row 3: non-finite time"),
    "non-monotonic time": (f"{NAME}.csv", _case_non_monotonic,
                           r"column 'time_s', row 11: non-monotonic time"),
    "non-uniform time": (f"{NAME}.csv.gz", _case_non_uniform,
                         r"column 'time_s', row 51: non-uniform time"),
    "too short": (f"{NAME}.csv", _case_short,
                  r"too short: 10 s; .* 0.1 Hz needs at least 20 s \(two periods\)"),
    "header only": (f"{NAME}.csv", _case_header_only, r"no data rows after the header"),
    "zero force": (f"{NAME}.csv", _case_zero_force,
                   r"column 'force_y_N': force on the stimulated axis is zero throughout"),
    "constant force": (f"{NAME}.csv", _case_constant_force,
                       r"column 'force_y_N': .* is constant \(1 N\) throughout"),
}


@pytest.fixture(scope="module")
def good_columns(make_columns):
    return make_columns("y", fs=100.0, duration_s=25.0, seed=1)


def _assert_no_output(folder):
    leftovers = [p.name for p in folder.iterdir()]
    assert leftovers == [], leftovers


@pytest.mark.parametrize("case", list(BAD_CASES))
def test_bad_input_cases(tmp_path, runner, write_trial, good_columns, case):
    name, alter, match = BAD_CASES[case]
    cols = {k: v.copy() for k, v in good_columns.items()}
    alter(cols)
    path = write_trial(tmp_path / "in" / name, cols)
    out_dir = tmp_path / "out"
    out_dir.mkdir()
    res = _ingest(runner, tmp_path / "in", "-o", out_dir / "trials.parquet")
    assert res.exit_code == 65, res.stderr
    line = res.stderr.strip()
    assert "\n" not in line and "Traceback" not in line  # one line, no traceback
    assert line.startswith(f"armfit: error: {path}")
    assert re.search(match, line), line
    _assert_no_output(out_dir)


@pytest.mark.parametrize("name, how, match", [
    (f"{NAME}.csv", dict(drop_bytes=40),
     r"row 2500: unreadable or truncated CSV file"),  # last of 2500 data rows cut short
    (f"{NAME}.csv.gz", dict(keep_fraction=0.5), r"unreadable or truncated"),
    (f"{NAME}.parquet", dict(keep_fraction=0.5), r"unreadable or truncated Parquet file"),
])
def test_truncated_files(tmp_path, runner, write_trial, good_columns, name, how, match):
    path = write_trial(tmp_path / "in" / name, good_columns)
    _truncate(path, **how)
    res = _ingest(runner, path, "-o", tmp_path / "t.parquet")
    assert res.exit_code == 65
    assert re.search(rf"^armfit: error: {re.escape(str(path))}.*{match}", res.stderr), \
        res.stderr
    assert not (tmp_path / "t.parquet").exists()


def test_empty_file(tmp_path, runner):
    path = tmp_path / f"{NAME}.csv"
    path.write_text("")
    res = _ingest(runner, path, "-o", tmp_path / "t.parquet")
    assert res.exit_code == 65
    assert f"{path}: unreadable file: it is empty" in res.stderr


def test_name_and_axis_errors(tmp_path, runner, write_trial, good_columns):
    odd = write_trial(tmp_path / "trial7.csv", good_columns)
    res = _ingest(runner, odd, "-o", tmp_path / "t.parquet")
    assert res.exit_code == 65
    assert f"{odd}: file name matches no pattern" in res.stderr
    bad_axis = write_trial(tmp_path / "d" / "sub-01_axis-w_grip-2N.csv", good_columns)
    res = _ingest(runner, tmp_path / "d", "-o", tmp_path / "t.parquet")
    assert res.exit_code == 65
    assert f"{bad_axis}: axis 'w' in the file name is not x, y or z" in res.stderr
    assert not (tmp_path / "t.parquet").exists()


def test_rate_mismatch_and_resample(tmp_path, runner, write_trial):
    a = write_trial(tmp_path / "in" / "sub-01_axis-y_grip-2N.csv", fs=100.0)
    b = write_trial(tmp_path / "in" / "sub-02_axis-y_grip-2N.csv", fs=200.0)
    out = tmp_path / "t.parquet"
    res = _ingest(runner, tmp_path / "in", "-o", out)
    assert res.exit_code == 65
    assert (f"{b}, column 'time_s': sampling rate 200 Hz differs from 100 Hz of {a}"
            in res.stderr)
    assert not out.exists()
    res = _ingest(runner, tmp_path / "in", "-o", out, "--resample")
    assert res.exit_code == 0, res.stderr
    assert f"{b}: resampled from 200 Hz to 100 Hz" in res.stderr
    assert [r["fs"] for r in dataset_metadata(out)] == [100.0, 100.0]


def test_duplicates_name_both_files(tmp_path, runner, write_trial, good_columns):
    a = write_trial(tmp_path / "in" / f"{NAME}.csv", good_columns)
    b = write_trial(tmp_path / "in" / f"{NAME}.parquet", good_columns)
    res = _ingest(runner, tmp_path / "in", "-o", tmp_path / "t.parquet")
    assert res.exit_code == 65
    assert f"{b}: duplicate trial (subject 01, axis y, grip 2 N, run -): also in {a}" \
        in res.stderr
    assert not (tmp_path / "t.parquet").exists()


def test_force_limit_is_a_warning(tmp_path, runner, write_trial, good_columns):
    cols = {k: v.copy() for k, v in good_columns.items()}
    cols["force_y_N"][99] = -9.5  # over the PHANToM Premium 1.5's 8.5 N at row 100
    path = write_trial(tmp_path / f"{NAME}.csv", cols)
    res = _ingest(runner, path, "-o", tmp_path / "t.parquet")
    assert res.exit_code == 0, res.stderr
    assert (f"warning: {path}, column 'force_y_N', row 100: |force| reaches the device "
            "limit 8.5 N in 1 sample(s)") in res.stderr
    res = _ingest(runner, path, "-o", tmp_path / "u.parquet", "--force-limit", "10")
    assert "the device limit" not in res.stderr
    res = runner.invoke(cli, ["-q", "ingest", str(path), "-o", str(tmp_path / "v.parquet")])
    assert res.exit_code == 0 and res.stderr == ""  # -q silences warnings and messages


def test_f_min_option_sets_the_length_rule(tmp_path, runner, write_trial, good_columns):
    cols = {k: v[:1000] for k, v in good_columns.items()}  # 10 s
    path = write_trial(tmp_path / f"{NAME}.csv", cols)
    # 2 / 0.2 Hz = 10 s: the 10 s trial now just reaches the lowest frequency.
    res = _ingest(runner, path, "-o", tmp_path / "t.parquet", "--fmin", "0.2")
    assert res.exit_code == 0, res.stderr


def test_nothing_found_and_missing_path(tmp_path, runner):
    (tmp_path / "empty").mkdir()
    res = _ingest(runner, tmp_path / "empty", "-o", tmp_path / "t.parquet")
    assert res.exit_code == 66
    assert "no trial files found" in res.stderr
    res = _ingest(runner, tmp_path / "absent", "-o", tmp_path / "t.parquet")
    assert res.exit_code == 66
    assert f"{tmp_path / 'absent'}: no such file or folder" in res.stderr


@pytest.fixture(scope="module")
def study(tmp_path_factory, write_trial, make_columns):
    """Two good trials, a bad one (NaN force at row 3) and a non-trial file."""
    root = tmp_path_factory.mktemp("study")
    write_trial(root / "sub-01_axis-x_grip-1N.csv", seed=1)
    write_trial(root / "nested" / "sub-02_axis-z_grip-3N_run-2.parquet", seed=2)
    bad = make_columns("y", seed=3)
    bad["force_y_N"][2] = np.nan
    write_trial(root / "sub-03_axis-y_grip-2N.csv", bad)
    (root / "notes.txt").write_text("not a trial")
    return root


def test_skip_bad_json(tmp_path, runner, study):
    out = tmp_path / "t.parquet"
    res = _ingest(runner, study, "-o", out, "--skip-bad", "--json")
    assert res.exit_code == 0, res.stderr
    summary = json.loads(res.stdout)
    assert summary["trials"] == 2 and summary["output"] == str(out)
    assert summary["skipped"] == [{
        "file": str(study / "sub-03_axis-y_grip-2N.csv"),
        "reason": "column 'force_y_N', row 3: blank value (or NaN); force and position must be "
                  "finite numbers"}]
    items = summary["items"]
    assert [(i["subject"], i["axis"], i["grip_N"], i["run"]) for i in items] == [
        ("01", "x", 1.0, None), ("02", "z", 3.0, 2)]
    # trial_columns defaults: 25 s at 100 Hz.
    assert [(i["fs"], i["n_samples"], i["duration_s"]) for i in items] == [(100.0, 2500, 25.0)] * 2
    assert summary["ignored"] == [str(study / "notes.txt")]
    assert f"skipped {study / 'sub-03_axis-y_grip-2N.csv'}: column 'force_y_N'" in res.stderr
    # When every trial is bad there is nothing to write: exit 65, the first reason shown.
    res = _ingest(runner, study / "sub-03_axis-y_grip-2N.csv", "-o", tmp_path / "w.parquet",
                  "--skip-bad")
    assert res.exit_code == 65 and not (tmp_path / "w.parquet").exists()
    assert "every trial was bad (1 skipped, the first" in res.stderr
    # Without --skip-bad the bad trial stops the run and nothing is written.
    res = _ingest(runner, study, "-o", tmp_path / "u.parquet")
    assert res.exit_code == 65 and not (tmp_path / "u.parquet").exists()


def test_verbose_lists_ignored_and_shows_traceback(tmp_path, runner, study):
    res = runner.invoke(cli, ["-v", "ingest", str(study), "-o", str(tmp_path / "t.parquet"),
                              "--skip-bad"])
    assert res.exit_code == 0
    assert f"ignored (not a trial name): {study / 'notes.txt'}" in res.stderr
    res = runner.invoke(cli, ["-v", "ingest", str(study), "-o", str(tmp_path / "u.parquet")])
    assert res.exit_code == 65 and "Traceback" in res.stderr
    res = _ingest(runner, study, "-o", tmp_path / "u.parquet")
    assert "Traceback" not in res.stderr


def test_overwrite_and_output_is_input(tmp_path, runner, study):
    out = tmp_path / "t.parquet"
    out.write_text("precious")
    res = _ingest(runner, study, "-o", out, "--skip-bad")
    assert res.exit_code == 73
    assert "exists; pass --overwrite" in res.stderr and out.read_text() == "precious"
    res = _ingest(runner, study, "-o", out, "--skip-bad", "--overwrite")
    assert res.exit_code == 0 and len(dataset_metadata(out)) == 2
    # The dataset can be an input, but not also the output.
    res = _ingest(runner, out, "-o", out, "--overwrite")
    assert res.exit_code == 73 and "output path is also an input" in res.stderr
    res = _ingest(runner, out, "-o", tmp_path / "copy.parquet", "--json")
    assert res.exit_code == 0
    assert [i["source"] for i in json.loads(res.stdout)["items"]] == [
        str(study / "sub-01_axis-x_grip-1N.csv"),
        str(study / "nested" / "sub-02_axis-z_grip-3N_run-2.parquet")]


def test_manifest(tmp_path, runner, write_trial):
    write_trial(tmp_path / "raw" / "first.csv", axis="x", seed=1)
    write_trial(tmp_path / "raw" / "sub-09_axis-x_grip-1N.parquet", axis="z", seed=2)
    manifest = tmp_path / "manifest.csv"
    manifest.write_text("file,subject,axis,grip_N,run\n"
                        "raw/first.csv,A,x,1,\n"
                        "raw/sub-09_axis-x_grip-1N.parquet,B,z,2.5,4\n")
    res = _ingest(runner, "-o", tmp_path / "t.parquet", "--manifest", manifest, "--json")
    assert res.exit_code == 0, res.stderr
    items = json.loads(res.stdout)["items"]
    # The manifest's identity wins over the file name (axis z, not x).
    assert [(i["subject"], i["axis"], i["grip_N"], i["run"]) for i in items] == [
        ("A", "x", 1.0, None), ("B", "z", 2.5, 4)]
    manifest.write_text("file,subject,axis,grip_N\nraw/first.csv,A,v,1\n")
    res = _ingest(runner, "-o", tmp_path / "u.parquet", "--manifest", manifest)
    assert res.exit_code == 65
    assert f"{manifest}, column 'axis', row 1: axis 'v' is not x, y or z" in res.stderr
    assert not (tmp_path / "u.parquet").exists()


def test_usage_errors(tmp_path, runner, study):
    res = _ingest(runner, "-o", tmp_path / "t.parquet")
    assert res.exit_code == 2
    res = _ingest(runner, study, "-o", tmp_path / "t.csv")
    assert res.exit_code == 2 and "ingest writes .parquet; not .csv" in res.stderr
    res = _ingest(runner, study, "-o", tmp_path / "t.parquet", "--fmin", "0")
    assert res.exit_code == 2



def test_a_second_manifest_is_refused(tmp_path, runner):
    """Two --manifest options: exit 2 (a usage error, docs/cli.md) naming both files, and
    no output written, rather than the second silently replacing the first."""
    for name in ("m1.csv", "m2.csv"):
        (tmp_path / name).write_text("file,subject,axis,grip_N\n", encoding="utf-8")
    out = tmp_path / "t.parquet"
    r = _ingest(runner, "--manifest", tmp_path / "m1.csv", "--manifest", tmp_path / "m2.csv",
                "-o", out)
    assert r.exit_code == 2
    assert "m1.csv" in r.output and "m2.csv" in r.output and "Traceback" not in r.output
    assert not out.exists()
