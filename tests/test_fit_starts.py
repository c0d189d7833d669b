"""armfit.models.params.fit_starts: the base parameters of a params file of base-model
fits, read without pandas, for the diagnosis's starts.

The reference is armfit's one params reader, read_params (pandas' read_csv and every
check of a params file): on a file fit_starts reads, its values must be read_params's to
the bit, and ModelFit.read_starts' table read_params's DataFrame; any file read_params
refuses, fit_starts must leave to it (None). Checked on the files fit-grip and
fit-nominal write, on random plain files, and on every single-cell fault of a list."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from conftest import modules_after

import armfit
from armfit.api import ModelFit
from armfit.errors import ArmfitError
from armfit.io.schema import PARAMS_BASE, params_columns
from armfit.models.arm import BASE_PARAMS
from armfit.models.params import fit_starts, read_params


def _same_as_read_params(path: Path) -> None:
    starts = fit_starts(path)
    assert starts is not None
    table = read_params(path)
    assert starts.grip == ("grip_N" in table.columns)
    assert len(starts.rows) == len(table)
    for row, (_, ref) in zip(starts.rows, table.iterrows(), strict=True):
        assert row["axis"] == ref["axis"]
        for n in (*PARAMS_BASE, *(("grip_N",) if starts.grip else ())):
            assert row[n] == ref[n] and isinstance(row[n], float), n   # to the bit
    lazy, eager = ModelFit.read_starts(path), ModelFit.read(path)
    assert lazy.which == eager.which
    pd.testing.assert_frame_equal(lazy.table, eager.table, check_exact=True)


def test_the_files_fit_grip_and_fit_nominal_write(grip, nominal):
    for path in (grip, nominal):
        _same_as_read_params(path)


def _random_file(path: Path, rng, grip: bool) -> Path:
    """A params file of base-model fits as fit-grip / fit-nominal write it (pandas'
    to_csv, 10 significant digits), values anywhere inside the physical ranges (log-
    uniform, bounds included)."""
    rows = []
    for axis in "xyz":
        for g in ((1.0, 2.0, 3.5) if grip else (None,)):
            row = {"axis": axis, **({"grip_N": g} if grip else {})}
            for q in BASE_PARAMS:
                v = float(np.exp(rng.uniform(np.log(q.lower), np.log(q.upper))))
                row[q.name] = rng.choice([v, q.lower, q.upper], p=[0.8, 0.1, 0.1])
                row[f"{q.name}_lo"], row[f"{q.name}_hi"] = v * 0.9, v * 1.1
            row.update(rms_db=rng.uniform(0, 3), rms_deg=rng.uniform(0, 30),
                       rms_norm=rng.uniform(0, 5), band_lo_hz=0.1, band_hi_hz=30.0,
                       n_points=100, cost="complex", converged=bool(rng.integers(2)),
                       mp_kg=rng.uniform(0.01, 1.0), effects="", at_bound="")
            rows.append(row)
    frame = pd.DataFrame(rows, columns=params_columns(PARAMS_BASE, grip=grip))
    frame.to_csv(path, index=False, float_format="%.10g")
    return path


@pytest.mark.parametrize("grip", [True, False])
def test_random_plain_files_are_read_as_read_params_reads_them(grip, tmp_path):
    rng = np.random.default_rng(7)
    for i in range(20):
        _same_as_read_params(_random_file(tmp_path / f"p{i}.csv", rng, grip))


def _rows(path: Path) -> list[list[str]]:
    with open(path, newline="") as fh:
        return list(csv.reader(fh))


def _write(path: Path, rows: list[list[str]]) -> Path:
    with open(path, "w", newline="") as fh:
        csv.writer(fh, lineterminator="\n").writerows(rows)
    return path


#: Single-cell values put in every cell of a plain file in turn: values out of range,
#: not numbers, or written in forms the fast reader does not vouch for.
CELL_FAULTS = ["", "nan", "NA", "inf", "-1", "0", "1e400", "abc", " 1", "+1", "1,5",
               "1e-400", "X", " x", "delay", "30000.5", "1001", "True"]


def test_no_file_read_params_refuses_is_read(grip, nominal, tmp_path):
    """Single-cell faults in every column of the grip and nominal files, and faults of the layout:
    where read_params refuses the file, fit_starts gives None; where it reads it,
    fit_starts gives None or read_params's values."""
    refused = read = 0
    for src in (grip, nominal):
        rows = _rows(src)
        cases = []
        for c in range(len(rows[0])):        # every column, a third of the faults each
            for k, v in enumerate(CELL_FAULTS):
                if k % 3 == c % 3:
                    bad = [list(x) for x in rows]
                    bad[1 + (k + c) % (len(rows) - 1)][c] = v
                    cases.append(bad)
        cases += [rows + [rows[1]],                                   # a second row
                  [rows[0] + ["extra"]] + [x + ["1"] for x in rows[1:]],
                  [[c for c in x[:-2]] + x[-1:] for x in rows],         # a column less
                  [rows[0]] + [rows[1][:-1]] + rows[2:],                # a short row
                  rows[:1] + [[]] + rows[1:],                           # a blank line
                  [["\ufeff" + rows[0][0]] + rows[0][1:]] + rows[1:],   # a BOM
                  [rows[0][:-1] + [rows[0][1]]] + rows[1:]]             # a repeated name
        for i, bad in enumerate(cases):
            path = _write(tmp_path / f"f{i}.csv", bad)
            try:
                read_params(path)
            except ArmfitError:
                refused += 1
                assert fit_starts(path) is None, bad
                continue
            read += 1
            if fit_starts(path) is not None:
                _same_as_read_params(path)
    assert refused > 50 and read > 50      # both kinds were met


def test_a_file_with_effects_or_per_trial_rows_is_left_to_read_params(tmp_path):
    # an adopted model's grip file (a delay column) and fit-trials' per-trial file
    rng = np.random.default_rng(1)
    plain = _random_file(tmp_path / "g.csv", rng, grip=True)
    frame = pd.read_csv(plain)
    frame["delay.delay_s"], frame["delay.delay_s_lo"], frame["delay.delay_s_hi"] = \
        0.012, 0.011, 0.013
    frame["effects"] = "delay"
    frame.to_csv(tmp_path / "delay.csv", index=False, float_format="%.10g")
    assert fit_starts(tmp_path / "delay.csv") is None
    read_params(tmp_path / "delay.csv")            # a file read_params reads
    frame = pd.read_csv(plain)
    frame.insert(1, "subject", "01")
    frame.to_csv(tmp_path / "trials.csv", index=False, float_format="%.10g")
    assert fit_starts(tmp_path / "trials.csv") is None
    assert fit_starts(tmp_path / "missing.csv") is None


def test_diagnose_reads_a_plain_grip_file_without_pandas(spectra, grip, tmp_path):
    # the command's diagnosis equals the Python API's given read_params's DataFrame
    out = tmp_path / "d.json"
    loaded = modules_after(["-q", "diagnose", str(spectra), "--model", str(grip), "-o",
                            str(out), "--max-steps", "1"])
    assert "armfit.diagnosis.search" in loaded and "pandas" not in loaded
    ref = armfit.diagnose(spectra, ModelFit(read_params(grip), "grip"), max_steps=1)
    assert json.loads(out.read_text()) == json.loads(json.dumps(ref.to_dict()))
