"""Fault injection on the readers: raw trials, manifests, datasets and every file of numbers.

Each test makes the fault for real (a FIFO, a symbolic link to /dev/zero, a loop of links,
a tampered dataset footer, a Parquet column of text or decimals, a digit separator in a
cell) and checks how armfit ends: the documented exit code (armfit/errors.py: 65 bad
data, 66 input not found), one line naming the file, column and row, and with
``--skip-bad`` the bad trial listed and the good ones kept.

The expected values come from the contract (docs/formats.md, armfit/errors.py) or from the
fault itself (the row where a bad cell was written, the file a link leads to).
"""

from __future__ import annotations

import decimal
import gzip
import itertools
import json
import os
import re
import resource
import subprocess
from pathlib import Path

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.parquet as pq
import pytest
from click.testing import CliRunner
from faulttools import ARMFIT

import armfit
from armfit.cli.main import cli
from armfit.errors import EXIT_DATAERR, EXIT_NOINPUT, BadInputError
from armfit.io.trials import DATASET_TRIALS_KEY, dataset_metadata, read_manifest
from armfit.spectra import saturated

NAME = "sub-01_axis-y_grip-2N"


def invoke(*args):
    return CliRunner().invoke(cli, [str(a) for a in args])


def one_line(text: str) -> str:
    """The one error line of a run (no traceback)."""
    lines = [ln for ln in text.splitlines() if ln.strip()]
    assert "Traceback" not in text, text
    assert lines and lines[-1].startswith("armfit: error: "), text
    return lines[-1]


def ingest_json(*args):
    res = invoke("ingest", *args, "--json")
    return res, (json.loads(res.stdout) if res.exit_code == 0 else None)


def run_armfit(*args, timeout: float = 120.0):
    """armfit in a child process, its address space capped at 4 GiB (a reader that reads
    without bound ends with MemoryError instead of taking the machine)."""
    def cap():
        resource.setrlimit(resource.RLIMIT_AS, (4 << 30, 4 << 30))
    return subprocess.run([ARMFIT, *map(str, args)], capture_output=True, text=True,
                          timeout=timeout, preexec_fn=cap)


@pytest.fixture
def cols(make_columns):
    """Columns of a good 30 s trial at 100 Hz on axis y (grip 2 N)."""
    return make_columns("y", fs=100.0, duration_s=30.0, seed=3)


# ---------------------------------------------------------------------------
# The one parser of numbers
# ---------------------------------------------------------------------------

def test_arrow_reads_exactly_the_numbers_of_the_parser():
    from armfit.io.numbers import NUMBER_PATTERN
    # armfit.io.numbers converts a column of text with Arrow's cast and uses its pattern
    # to find a bad cell; the two must accept the same texts. Every text of up to 4
    # characters of digits, point, exponent, signs, separator and the letters of nan/inf,
    # and the spellings of nan and infinity.
    chars = "01.eE+-_n"
    texts = ["".join(t) for k in range(1, 5) for t in itertools.product(chars, repeat=k)]
    texts += ["nan", "NaN", "-nan", "inf", "-Inf", "+INF", "infinity", "-Infinity",
              "infinit", "nana", "1e500", "0.1e-400", "١", "²", "0x10", "1,5", "1d5"]
    rx = re.compile(NUMBER_PATTERN)
    for text in texts:
        try:
            pc.cast(pa.array([text]), pa.float64())
            arrow = True
        except pa.ArrowInvalid:
            arrow = False
        assert arrow == bool(rx.fullmatch(text)), text


@pytest.mark.parametrize("text, python", [
    ("1_5", 15.0), ("0_5", 5.0), ("١", 1.0), ("٣.٥", 3.5), (" 2_0 ", 20.0)])
def test_python_numbers_that_the_parser_refuses(text, python):
    from armfit.io.numbers import parse_number, parse_numbers
    # float() reads these (the value on the right); a reader of armfit must not
    assert float(text) == python
    with pytest.raises(ValueError, match="is not a number"):
        parse_number(text)
    with pytest.raises(BadInputError, match=r"f\.csv, column 'c', row 3: non-numeric"):
        parse_numbers(["1", "", text], file="f.csv", column="c")
    assert np.isnan(parse_numbers(["1", "", text], errors="coerce")).sum() == 2


@pytest.mark.parametrize("text", ["²", "³", "٣", "1_0", "+1", "1.0", "-1"])
def test_whole_numbers_are_ascii_digits(text):
    from armfit.io.numbers import parse_whole
    # str.isdigit() accepts superscripts and other scripts' digits; int() then fails or
    # reads another number
    with pytest.raises(ValueError, match="is not a whole number"):
        parse_whole(text)
    assert parse_whole("007") == 7 and parse_whole(3) == 3


def test_parser_keeps_numbers_and_blanks():
    from armfit.io.numbers import parse_numbers
    values = parse_numbers(pa.array(["1.5", " -2e-3 ", "", None, "NaN", ".5", "5."]))
    np.testing.assert_array_equal(values, [1.5, -2e-3, np.nan, np.nan, np.nan, 0.5, 5.0])
    dec = pa.array([decimal.Decimal("1.25"), None], type=pa.decimal128(6, 3))
    np.testing.assert_array_equal(parse_numbers(dec), [1.25, np.nan])
    np.testing.assert_array_equal(parse_numbers(pa.nulls(2)), [np.nan, np.nan])


# ---------------------------------------------------------------------------
# Digit separators and other scripts' digits, in every reader
# ---------------------------------------------------------------------------

@pytest.mark.parametrize("ext", ["parquet", "csv"])
@pytest.mark.parametrize("text", ["0_5", "1_5"])
def test_digit_separator_in_a_force_column(tmp_path, write_trial, cols, ext, text):
    cells = [repr(float(v)) for v in cols["force_y_N"]]
    cells[41] = text                            # data row 42
    cols["force_y_N"] = cells                   # a column of text
    path = write_trial(tmp_path / "in" / f"{NAME}.{ext}", cols)
    res = invoke("ingest", path, "-o", tmp_path / "t.parquet")
    assert res.exit_code == EXIT_DATAERR, res.output
    assert one_line(res.stderr).startswith(
        f"armfit: error: {path}, column 'force_y_N', row 42: non-numeric value '{text}'")
    with pytest.raises(BadInputError, match=r"column 'force_y_N', row 42"):
        armfit.read_trials(path)


def test_parquet_text_column_of_numbers_is_read_exactly(tmp_path, write_trial, cols):
    # numbers stored as text are numbers (the shortest repr of each float64)
    exact = cols["force_y_N"].copy()
    cols["force_y_N"] = [repr(float(v)) for v in exact]
    path = write_trial(tmp_path / f"{NAME}.parquet", cols)
    (trial,) = armfit.read_trials(path).trials
    np.testing.assert_array_equal(trial.f, exact)


@pytest.mark.parametrize("grip", ["1_5", "١"])
def test_digit_separator_in_a_manifest_grip(tmp_path, write_trial, cols, grip):
    write_trial(tmp_path / "t.csv", cols)
    manifest = tmp_path / "m.csv"
    manifest.write_text(f"file,subject,axis,grip_N\nt.csv,01,y,{grip}\n")
    res = invoke("ingest", "--manifest", manifest, "-o", tmp_path / "t.parquet")
    assert res.exit_code == EXIT_DATAERR, res.output
    assert f"{manifest}, column 'grip_N', row 1: grip '{grip}'" in one_line(res.stderr)


def test_other_scripts_digits_in_a_file_name(tmp_path, write_trial, cols):
    # '\d' matched '٣' and float() read it as 3 N
    path = write_trial(tmp_path / "sub-01_axis-y_grip-٣N.csv", cols)
    res = invoke("ingest", path, "-o", tmp_path / "t.parquet")
    assert res.exit_code == EXIT_DATAERR, res.output
    assert "grip '٣N' in the file name is not a number" in one_line(res.stderr)


@pytest.fixture(scope="module")
def spectra_and_nominal(tmp_path_factory, small_study):
    root = tmp_path_factory.mktemp("readers")
    spectra = root / "spectra.parquet"
    assert invoke("estimate", small_study, "-o", spectra).exit_code == 0
    nominal = root / "nominal.csv"
    assert invoke("fit-nominal", spectra, "-o", nominal).exit_code == 0
    return spectra, nominal


def test_digit_separator_in_a_params_band(spectra_and_nominal, tmp_path):
    spectra, nominal = spectra_and_nominal
    df = pd.read_csv(nominal, dtype=str, keep_default_na=False)
    df.loc[0, "band_lo_hz"] = "0_1"             # float() reads 1.0 Hz
    bad = tmp_path / "nominal.csv"
    df.to_csv(bad, index=False)
    res = invoke("compare", spectra, "--model", bad, "--json")
    assert res.exit_code == EXIT_DATAERR, res.output
    assert f"{bad}, column 'band_lo_hz', row 1: non-numeric value '0_1'" \
        in one_line(res.stderr)


def test_digit_separator_in_a_spectra_table(spectra_and_nominal, tmp_path):
    spectra, _ = spectra_and_nominal
    table = pq.read_table(spectra)
    re_text = pc.cast(table.column("re"), pa.string()).to_pylist()
    re_text[4] = "1_5"                          # row 5; float() reads 15 m/N
    i = table.column_names.index("re")
    bad = tmp_path / "spectra.parquet"
    pq.write_table(table.set_column(i, "re", pa.array(re_text)), bad)
    res = invoke("fit-nominal", bad, "-o", tmp_path / "n.csv")
    assert res.exit_code == EXIT_DATAERR, res.output
    assert f"{bad}, column 're', row 5: non-numeric value '1_5'" in one_line(res.stderr)


def test_digit_separator_in_a_wu_summary(tmp_path):
    # the band of a Wu file comes from its summary beside it; '0_01' was read as 1 Hz
    wu = tmp_path / "wu.csv"
    table3 = Path(armfit.__file__).parent / "data" / "table3_uncertainty_weights.csv"
    wu.write_text(table3.read_text())
    (tmp_path / "wu_summary.csv").write_text(
        "axis,weight,target,band_lo_hz,band_hi_hz\nx,fitted,wmax,0_01,30\n")
    res = invoke("stability", "nominal", "--weights", wu)
    assert res.exit_code == EXIT_DATAERR, res.output
    assert "wu_summary.csv, column 'band_lo_hz', row 1: non-numeric value '0_01'" \
        in one_line(res.stderr)


# ---------------------------------------------------------------------------
# Datasets whose metadata was tampered with
# ---------------------------------------------------------------------------

@pytest.fixture
def dataset(tmp_path, write_trial):
    for k in range(3):
        write_trial(tmp_path / "raw" / f"sub-0{k + 1}_axis-y_grip-2N.csv", fs=100.0,
                    duration_s=25.0, seed=10 + k)
    out = tmp_path / "trials.parquet"
    assert invoke("ingest", tmp_path / "raw", "-o", out).exit_code == 0
    return out


def _retag(src: Path, dst: Path, text: str) -> Path:
    """``src`` written again, row group by row group, with ``text`` as its trials'
    metadata."""
    pf = pq.ParquetFile(src)
    kv = dict(pf.metadata.metadata or {})
    with pq.ParquetWriter(dst, pf.schema_arrow.remove_metadata()) as w:
        for i in range(pf.num_row_groups):
            w.write_table(pf.read_row_group(i))
        kv[DATASET_TRIALS_KEY.encode()] = text.encode()
        w.add_key_value_metadata({k.decode(): v.decode() for k, v in kv.items()
                                  if k.startswith(b"armfit")})
    return dst


def _records(path: Path) -> list[dict]:
    return json.loads(pq.read_metadata(path).metadata[DATASET_TRIALS_KEY.encode()])


def _tamper(records, case):
    if case == "fewer records":
        return json.dumps(records[:2])
    if case == "invalid JSON":
        return json.dumps(records)[:-5]
    if case == "no fs":
        del records[1]["fs"]
    elif case == "axis w":
        records[1]["axis"] = "w"
    elif case == "fs as text with a separator":
        records[1]["fs"] = "1_00"
    elif case == "grip as text with a separator":
        records[1]["grip_N"] = "1_5"
    elif case == "run a superscript":
        records[1]["run"] = "²"
    elif case == "trial out of order":
        records[1]["trial"] = 2
    elif case == "a list, not an object":
        records[1] = [1, 2]
    return json.dumps(records)


@pytest.mark.parametrize("case, message", [
    ("fewer records", "lists 2 trial(s) but the file holds 3 row group(s)"),
    ("invalid JSON", f"metadata '{DATASET_TRIALS_KEY}' is not valid JSON"),
    ("no fs", "trial 1: no 'fs'"),
    ("axis w", "trial 1: axis 'w' is not x, y or z"),
    ("fs as text with a separator", "trial 1: 'fs' is '1_00', not a sampling rate"),
    ("grip as text with a separator", "trial 1: 'grip_N' is '1_5', not a non-negative"),
    ("run a superscript", "trial 1: 'run' is '²', not a whole number"),
    ("trial out of order", "trial 1: 'trial' is 2"),
    ("a list, not an object", "trial 1: the record is list, not an object"),
])
def test_tampered_dataset_metadata(dataset, tmp_path, case, message):
    bad = _retag(dataset, tmp_path / "bad.parquet", _tamper(_records(dataset), case))
    for command in ("estimate", "ingest"):
        res = invoke(command, bad, "-o", tmp_path / f"{command}.parquet")
        assert res.exit_code == EXIT_DATAERR, (command, res.output)
        line = one_line(res.stderr)
        assert line.startswith(f"armfit: error: {bad}: ") and message in line, line
    with pytest.raises(BadInputError, match=re.escape(message)):
        armfit.read_trials(bad)


def test_untampered_dataset_reads_as_written(dataset):
    records = dataset_metadata(dataset)
    assert [r["trial"] for r in records] == [0, 1, 2]
    assert all(r["fs"] == 100.0 and r["n_samples"] == 2500 for r in records)


# ---------------------------------------------------------------------------
# Manifest rows outside the PATHs
# ---------------------------------------------------------------------------

def test_manifest_row_outside_the_paths_is_read(tmp_path, write_trial):
    folder, outside = tmp_path / "folder", tmp_path / "outside"
    write_trial(folder / "t1.csv", axis="y", seed=1)
    write_trial(folder / "t2.csv", axis="y", seed=2)
    write_trial(outside / "t3.csv", axis="y", seed=3)
    manifest = folder / "m.csv"
    manifest.write_text("file,subject,axis,grip_N\nt1.csv,01,y,2\nt2.csv,02,y,2\n"
                        "../outside/t3.csv,03,y,2\n")
    res, out = ingest_json(folder, "--manifest", manifest, "-o", tmp_path / "t.parquet")
    assert res.exit_code == 0, res.output
    # every row of the manifest is a trial (docs/formats.md), in the PATHs or not
    assert out["trials"] == 3 and out["skipped"] == []
    assert [i["subject"] for i in out["items"]] == ["01", "02", "03"]
    assert out["items"][2]["source"] == str((outside / "t3.csv").resolve())
    trials = armfit.read_trials(folder, manifest=manifest)
    assert [t.meta.subject for t in trials.trials] == ["01", "02", "03"]


def test_manifest_row_outside_the_paths_that_is_missing(tmp_path, write_trial):
    folder = tmp_path / "folder"
    write_trial(folder / "t1.csv", axis="y")
    manifest = folder / "m.csv"
    manifest.write_text("file,subject,axis,grip_N\nt1.csv,01,y,2\n../gone/t3.csv,03,y,2\n")
    res = invoke("ingest", folder, "--manifest", manifest, "-o", tmp_path / "t.parquet")
    assert res.exit_code == EXIT_NOINPUT
    assert "column 'file', row 2" in one_line(res.stderr)


# ---------------------------------------------------------------------------
# Saturation: one rule, |F| >= limit
# ---------------------------------------------------------------------------

def test_force_clipped_at_the_limit_is_saturation(tmp_path, write_trial, cols):
    f = cols["force_y_N"]
    f[100:140] = 8.5                            # a plateau exactly at the 8.5 N default
    path = write_trial(tmp_path / f"{NAME}.csv", cols)
    res = invoke("ingest", path, "-o", tmp_path / "t.parquet")
    assert res.exit_code == 0, res.output
    assert (f"warning: {path}, column 'force_y_N', row 101: |force| reaches the device "
            "limit 8.5 N in 40 sample(s)") in res.stderr
    res = invoke("estimate", path, "-o", tmp_path / "s.parquet", "--json")
    assert res.exit_code == 0, res.output
    assert json.loads(res.stdout)["flagged_trial_rows"]["saturation"] > 0
    # the one rule behind both
    from armfit.io.trials import saturated_samples
    assert saturated_samples(f, 8.5).sum() == 40 and saturated(f, 8.5)
    assert not saturated(np.nextafter(8.5, 0) * np.sign(f), 8.5)


# ---------------------------------------------------------------------------
# Symbolic links, FIFOs, devices
# ---------------------------------------------------------------------------

def test_symlinked_trial_file_in_a_folder(tmp_path, write_trial, cols):
    raw, elsewhere = tmp_path / "raw", tmp_path / "elsewhere"
    write_trial(raw / "sub-01_axis-y_grip-2N.csv", cols)
    target = write_trial(elsewhere / "data.csv", cols)
    link = raw / "sub-02_axis-y_grip-2N.csv"
    link.symlink_to(target)
    # as a symlinked folder (docs/formats.md): not followed, exit 66, or skipped
    res = invoke("ingest", raw, "-o", tmp_path / "t.parquet")
    assert res.exit_code == EXIT_NOINPUT, res.output
    assert f"{link}: symlinked file (to {target}), not followed" in one_line(res.stderr)
    res, out = ingest_json(raw, "-o", tmp_path / "t.parquet", "--skip-bad")
    assert res.exit_code == 0 and out["trials"] == 1
    assert out["skipped"][0]["file"] == str(link)
    # given as an input of its own it is read, and the file it leads to is recorded
    res, out = ingest_json(link, "-o", tmp_path / "u.parquet")
    assert res.exit_code == 0, res.output
    assert out["items"][0]["source"] == str(target.resolve())
    assert dataset_metadata(tmp_path / "u.parquet")[0]["source"] == str(target.resolve())


def test_fifo_named_like_a_trial_is_refused_unopened(tmp_path, write_trial, cols):
    raw = tmp_path / "raw"
    write_trial(raw / "sub-01_axis-y_grip-2N.csv", cols)
    fifo = raw / "sub-02_axis-y_grip-2N.csv"
    os.mkfifo(fifo)
    # in a child process: opening the FIFO would block it for ever
    res = run_armfit("ingest", raw, "-o", tmp_path / "t.parquet", timeout=60)
    assert res.returncode == EXIT_DATAERR, res.stderr
    assert f"{fifo}: not a regular file but a FIFO (named pipe)" in one_line(res.stderr)
    res = run_armfit("ingest", raw, "-o", tmp_path / "t.parquet", "--skip-bad", "--json",
                     timeout=60)
    assert res.returncode == 0, res.stderr
    out = json.loads(res.stdout)
    assert out["trials"] == 1 and [s["file"] for s in out["skipped"]] == [str(fifo)]
    res = run_armfit("estimate", fifo, "-o", tmp_path / "s.parquet", timeout=60)
    assert res.returncode == EXIT_DATAERR and "not a regular file" in res.stderr


def test_fifo_listed_in_a_manifest(tmp_path):
    os.mkfifo(tmp_path / "t.csv")
    manifest = tmp_path / "m.csv"
    manifest.write_text("file,subject,axis,grip_N\nt.csv,01,y,2\n")
    res = run_armfit("ingest", "--manifest", manifest, "-o", tmp_path / "t.parquet",
                     timeout=60)
    assert res.returncode == EXIT_DATAERR, res.stderr
    assert "not a regular file but a FIFO (named pipe)" in one_line(res.stderr)


def test_manifest_that_is_a_fifo(tmp_path):
    manifest = tmp_path / "m.csv"
    os.mkfifo(manifest)
    res = run_armfit("ingest", "--manifest", manifest, "-o", tmp_path / "t.parquet",
                     timeout=60)
    assert res.returncode == EXIT_DATAERR, res.stderr
    assert f"{manifest}: not a regular file but a FIFO (named pipe)" in one_line(res.stderr)


def test_link_to_dev_zero(tmp_path, write_trial, cols):
    zero = tmp_path / f"{NAME}.csv"
    zero.symlink_to("/dev/zero")
    res = run_armfit("ingest", zero, "-o", tmp_path / "t.parquet", timeout=60)
    assert res.returncode == EXIT_DATAERR, res.stderr
    assert f"{zero}: not a regular file but a character device" in one_line(res.stderr)
    good = write_trial(tmp_path / "g" / "sub-02_axis-y_grip-2N.csv", cols)
    res = run_armfit("ingest", zero, good, "-o", tmp_path / "t.parquet", "--skip-bad",
                     timeout=60)
    assert res.returncode == 0, res.stderr
    assert f"skipped {zero}: not a regular file" in res.stderr


def test_dangling_link_and_loop(tmp_path, write_trial, cols):
    raw = tmp_path / "raw"
    write_trial(raw / "sub-01_axis-y_grip-2N.csv", cols)
    loop_a, loop_b = raw / "sub-02_axis-y_grip-2N.csv", raw / "sub-03_axis-y_grip-2N.csv"
    loop_a.symlink_to(loop_b)
    loop_b.symlink_to(loop_a)
    dangling = raw / "sub-04_axis-y_grip-2N.csv"
    dangling.symlink_to(tmp_path / "gone.csv")
    res = invoke("ingest", raw, "-o", tmp_path / "t.parquet")
    assert res.exit_code == EXIT_NOINPUT, res.output
    res, out = ingest_json(raw, "-o", tmp_path / "t.parquet", "--skip-bad")
    assert res.exit_code == 0, res.output
    assert out["trials"] == 1
    assert sorted(s["file"] for s in out["skipped"]) == sorted(
        map(str, (loop_a, loop_b, dangling)))
    # given as inputs of their own: links are followed, and lead nowhere
    res = invoke("ingest", loop_a, "-o", tmp_path / "u.parquet")
    assert res.exit_code == EXIT_NOINPUT
    assert f"{loop_a}: a loop of symbolic links" in one_line(res.stderr)
    res = invoke("ingest", dangling, "-o", tmp_path / "u.parquet")
    assert res.exit_code == EXIT_NOINPUT
    assert f"{dangling}: a dangling symbolic link" in one_line(res.stderr)
    res = invoke("ingest", loop_a, raw / "sub-01_axis-y_grip-2N.csv", "-o",
                 tmp_path / "u.parquet", "--skip-bad")
    assert res.exit_code == 0 and f"skipped {loop_a}: a loop of symbolic links" in res.stderr


def test_manifest_row_that_is_a_loop(tmp_path):
    (tmp_path / "a.csv").symlink_to(tmp_path / "b.csv")
    (tmp_path / "b.csv").symlink_to(tmp_path / "a.csv")
    manifest = tmp_path / "m.csv"
    manifest.write_text("file,subject,axis,grip_N\na.csv,01,y,2\n")
    assert len(read_manifest(manifest)) == 1
    res = invoke("ingest", "--manifest", manifest, "-o", tmp_path / "t.parquet")
    assert res.exit_code == EXIT_NOINPUT, res.output
    assert "a loop of symbolic links" in one_line(res.stderr)


# ---------------------------------------------------------------------------
# Superscript runs: exit 65, skippable
# ---------------------------------------------------------------------------

def test_superscript_run_in_a_file_name(tmp_path, write_trial, cols):
    raw = tmp_path / "raw"
    write_trial(raw / "sub-01_axis-y_grip-2N.csv", cols)
    bad = write_trial(raw / "sub-01_axis-y_grip-2N_run-².csv", cols)
    res = invoke("ingest", raw, "-o", tmp_path / "t.parquet")
    assert res.exit_code == EXIT_DATAERR, res.output
    assert f"{bad}: run '²' in the file name is not a whole number" in one_line(res.stderr)
    res, out = ingest_json(raw, "-o", tmp_path / "t.parquet", "--skip-bad")
    assert res.exit_code == 0 and out["trials"] == 1
    assert [s["file"] for s in out["skipped"]] == [str(bad)]


def test_superscript_run_in_a_manifest(tmp_path, write_trial, cols):
    write_trial(tmp_path / "t.csv", cols)
    manifest = tmp_path / "m.csv"
    manifest.write_text("file,subject,axis,grip_N,run\nt.csv,01,y,2,²\n")
    res = invoke("ingest", "--manifest", manifest, "-o", tmp_path / "t.parquet")
    assert res.exit_code == EXIT_DATAERR, res.output
    assert f"{manifest}, column 'run', row 1: run '²' is not a whole number" \
        in one_line(res.stderr)


# ---------------------------------------------------------------------------
# Time in ms
# ---------------------------------------------------------------------------

@pytest.mark.parametrize("command", ["ingest", "estimate", "run"])
def test_time_in_ms_is_bad_data_with_a_hint(tmp_path, write_trial, make_columns, command):
    cols = make_columns("y", fs=1000.0, duration_s=25.0, seed=4)
    cols["time_s"] = cols["time_s"] * 1000.0    # ms: the rate reads 1 Hz
    path = write_trial(tmp_path / f"{NAME}.csv", cols)
    res = invoke(command, path, "-o", tmp_path / "out.parquet")
    assert res.exit_code == EXIT_DATAERR, res.output
    line = one_line(res.stderr)
    assert f"{path}, column 'time_s': sampling rate 1 Hz" in line
    # the lowest rate of docs/formats.md: 100 Hz
    assert "below 100 Hz" in line and "is time in ms?" in line
    assert "--fmax" not in line


# ---------------------------------------------------------------------------
# Headers, compression, duplicates, grips, decimals
# ---------------------------------------------------------------------------

@pytest.mark.parametrize("ext", ["csv", "parquet"])
def test_blanks_around_column_names(tmp_path, write_trial, cols, ext):
    spaced = {(k if k == "time_s" else f" {k}"): v for k, v in cols.items()}
    path = write_trial(tmp_path / f"{NAME}.{ext}", spaced)
    (trial,) = armfit.read_trials(path).trials
    np.testing.assert_array_equal(trial.f, cols["force_y_N"])
    res = invoke("ingest", path, "-o", tmp_path / "t.parquet")
    assert res.exit_code == 0, res.output


def test_upper_case_csv_gz_is_decompressed(tmp_path, write_trial, cols):
    path = write_trial(tmp_path / f"{NAME}.csv.gz", cols)
    upper = path.rename(tmp_path / f"{NAME}.CSV.GZ")
    with gzip.open(upper, "rt") as fh:      # it is gzip indeed
        assert "time_s" in fh.readline()
    res, out = ingest_json(upper, "-o", tmp_path / "t.parquet")
    assert res.exit_code == 0, res.output
    assert out["items"][0]["n_samples"] == 3000


@pytest.mark.parametrize("command", ["ingest", "estimate"])
def test_good_copy_is_not_a_duplicate_of_an_unreadable_one(tmp_path, write_trial, cols,
                                                           command):
    bad_cols = dict(cols)
    bad_cols["force_y_N"] = [repr(float(v)) for v in cols["force_y_N"]]
    bad_cols["force_y_N"][6] = "abc"
    bad = write_trial(tmp_path / "a" / f"{NAME}.csv", bad_cols)
    good = write_trial(tmp_path / "b" / f"{NAME}.parquet", cols)
    res = invoke(command, tmp_path / "a", tmp_path / "b", "-o", tmp_path / "o.parquet",
                 "--skip-bad", "--json")
    assert res.exit_code == 0, res.output
    out = json.loads(res.stdout)
    assert out["trials"] == 1
    assert [s["file"] for s in out["skipped"]] == [str(bad)]
    assert "duplicate" not in res.stderr and str(good) not in json.dumps(out["skipped"])
    # two good copies: the later one is still the duplicate
    write_trial(tmp_path / "c" / f"{NAME}.csv", cols)
    res = invoke(command, tmp_path / "b", tmp_path / "c", "-o", tmp_path / "p.parquet",
                 "--skip-bad")
    assert res.exit_code == 0 and "duplicate trial" in res.stderr


def test_all_null_grip_column_agrees_with_all_blank_csv(tmp_path, write_trial, cols):
    # a grip sample that is missing is a blank cell or NaN (docs/formats.md): a column of
    # nothing but missing samples is a grip sensor that recorded nothing, in either format
    cols["grip_N"] = [None] * len(cols["time_s"])
    pq_path = write_trial(tmp_path / "p" / f"{NAME}.parquet", cols)
    assert pq.read_schema(pq_path).field("grip_N").type == pa.null()
    csv_path = write_trial(tmp_path / "c" / f"{NAME}.csv", cols)
    for path in (pq_path, csv_path):
        res = invoke("ingest", path, "-o", path.with_name("t.parquet"))
        assert res.exit_code == 0, res.output
        (trial,) = armfit.read_trials(path).trials
        assert np.isnan(trial.grip).all()


def test_decimal_parquet_column_is_a_number(tmp_path, cols):
    table = pa.table({k: pa.array(v) for k, v in cols.items()})
    rounded = np.round(cols["force_y_N"], 6)
    dec = pa.array([decimal.Decimal(f"{v:.6f}") for v in rounded], type=pa.decimal128(12, 6))
    path = tmp_path / f"{NAME}.parquet"
    pq.write_table(table.set_column(table.column_names.index("force_y_N"), "force_y_N", dec),
                   path)
    res = invoke("ingest", path, "-o", tmp_path / "t.parquet")
    assert res.exit_code == 0, res.output
    (trial,) = armfit.read_trials(path).trials
    np.testing.assert_array_equal(trial.f, rounded)


# ---------------------------------------------------------------------------
# Messages name the running command's own options
# ---------------------------------------------------------------------------

def test_too_short_names_each_commands_own_option(tmp_path, write_trial, make_columns):
    path = write_trial(tmp_path / f"{NAME}.csv", make_columns("y", duration_s=15.0))
    # one spelling, --fmin, in every command that reads raw trials
    expected = {"ingest": "; lower --fmin or drop the trial",
                "estimate": "; lower --fmin or drop the trial",
                "run": "; lower --fmin or drop the trial"}
    outputs = {"ingest": "t.parquet", "estimate": "s.parquet", "run": "out"}
    for command, hint in expected.items():
        res = invoke(command, path, "-o", tmp_path / outputs[command])
        assert res.exit_code == EXIT_DATAERR, (command, res.output)
        line = one_line(res.stderr)
        assert "needs at least 20 s (two periods)" in line
        assert line.endswith(hint), line


def test_rate_mismatch_names_resample_only_where_it_is(tmp_path, write_trial, make_columns):
    write_trial(tmp_path / "in" / "sub-01_axis-y_grip-2N.csv",
                make_columns("y", fs=200.0, duration_s=25.0))
    write_trial(tmp_path / "in" / "sub-02_axis-y_grip-2N.csv",
                make_columns("y", fs=100.0, duration_s=25.0))
    res = invoke("ingest", tmp_path / "in", "-o", tmp_path / "t.parquet")
    assert res.exit_code == EXIT_DATAERR
    assert one_line(res.stderr).endswith("pass --resample to resample to a common rate")
    res = invoke("run", tmp_path / "in", "-o", tmp_path / "out")
    assert res.exit_code == EXIT_DATAERR
    line = one_line(res.stderr)
    assert "differs from 200 Hz" in line and "--resample" not in line, line
    # a skipped trial's reason names no option either
    res = invoke("ingest", tmp_path / "in", "-o", tmp_path / "t.parquet", "--skip-bad")
    assert res.exit_code == 0
    assert re.search(r"skipped .*sub-02.*differs from 200 Hz of \S+\n", res.stderr), \
        res.stderr


def test_nested_command_names_its_own_flag():
    # `plot stability` is a command of the `plot` group: its --sample-time is named
    res = invoke("plot", "stability", "nominal", "--sample-time", "0", "-o", "never.png")
    assert res.exit_code == 2
    assert one_line(res.stderr) == ("armfit: error: --sample-time must be a period > 0 s, "
                                    "got 0.0")


@pytest.mark.parametrize("args, message", [
    (["estimate", "raw", "-o", "s.parquet", "--mp", "x=0_09"], "got 'x=0_09'"),
    (["fit-nominal", "none.parquet", "-o", "n.csv", "--band", "0_1:30"], "--band '0_1:30'"),
    (["simulate", "-o", "sim", "--duration", "2_6,26"], "--duration '2_6,26'"),
    (["simulate", "-o", "sim", "--effect", "delay=0_012"], "'0_012' is not a number"),
    (["fit-uncertainty", "none.parquet", "--nominal", "nominal", "-o", "w.csv", "--smooth",
      "1_0"], "--smooth '1_0'"),
    # options typed by click: float("0_1") is 1.0 and int("²") fails only in int()
    (["estimate", "raw", "-o", "s.parquet", "--fmin", "0_1"], "'0_1' is not a number"),
    (["simulate", "-o", "sim", "--fs", "1_000"], "'1_000' is not a number"),
    (["simulate", "-o", "sim", "--subjects", "٣"], "'٣' is not a whole number"),
    (["plot", "stability", "n.csv", "-o", "p.png", "--delay-samples", "²"],
     "'²' is not a whole number"),
    (["stability", "n.csv", "--sample-time", "1_0e-3"], "'1_0e-3' is not a number"),
])
def test_digit_separator_in_an_option_value(tmp_path, monkeypatch, args, message):
    # float() reads 0_09 as 0.09 and 0_1 as 1.0; a value of an option is read as a cell
    monkeypatch.chdir(tmp_path)
    res = invoke(*args)
    assert res.exit_code == 2, res.output
    assert message in res.stderr
