"""The rig's excitation as a trial column: ref_<a>_N (a commanded force) or ref_<a>_m (a
reference trajectory), in raw files, column maps and the canonical dataset
(docs/formats.md, "Raw trial files" and "Column maps")."""

from __future__ import annotations

import json

import numpy as np
import pyarrow.parquet as pq
import pytest
import scipy.io

from armfit.cli.main import cli
from armfit.io.trials import DATASET_COLUMNS, TrialSource, read_trial
from armfit.spectra import Spectra

FS = 1000.0


def _columns(make_columns, ref: dict[str, np.ndarray] | None = None) -> dict:
    cols = make_columns("x", fs=FS, duration_s=25.0, seed=3)
    cols.update(ref or {})
    return cols


def _one_error(stderr: str) -> str:
    lines = [ln for ln in stderr.splitlines() if ln.startswith("armfit: error:")]
    assert len(lines) == 1, stderr
    return lines[0]


def test_a_reference_column_is_read_with_its_name(tmp_path, make_columns, write_trial):
    cols = _columns(make_columns)
    cols["ref_x_N"] = cols["force_x_N"] + 0.25          # the commanded force, N
    cols["ref_y_N"] = cols["force_y_N"]                 # another axis's: not the trial's
    path = write_trial(tmp_path / "sub-01_axis-x_grip-2N.parquet", cols)
    trial = read_trial(TrialSource(str(path), "01", "x", 2.0), f_min_hz=0.1)
    assert trial.meta.reference == "ref_x_N"
    np.testing.assert_array_equal(trial.ref, cols["ref_x_N"])


@pytest.mark.parametrize(("change", "column", "says"), [
    (lambda c: c.update(ref_x_m=c["pos_x_m"]), "ref_x_m", "both ref_x_N and ref_x_m"),
    (lambda c: c.__setitem__("ref_x_N", np.full(c["ref_x_N"].size, 1.5)), "ref_x_N",
     "the reference is constant (1.5) throughout"),
    (lambda c: c["ref_x_N"].__setitem__(99, np.nan), "ref_x_N", "row 100: blank value"),
])
def test_a_bad_reference_is_one_line_naming_file_and_column(tmp_path, make_columns,
                                                             write_trial, runner, change,
                                                             column, says):
    cols = _columns(make_columns)
    cols["ref_x_N"] = cols["force_x_N"].copy()
    change(cols)
    path = write_trial(tmp_path / "sub-01_axis-x_grip-2N.csv", cols)
    res = runner.invoke(cli, ["ingest", str(path), "-o", str(tmp_path / "d.parquet")])
    assert res.exit_code == 65
    line = _one_error(res.stderr)
    assert f"{path}, column '{column}'" in line and says in line


def _stage(tmp_path):
    """A positioning stage in MATLAB: time t, position qm (m), the controller's output
    vir (V, 35.15 N/V) and the reference trajectory qg (m); the manifest names it."""
    rng = np.random.default_rng(7)
    t = np.arange(30000) / FS
    qg = 0.1 + 0.01 * np.sin(2 * np.pi * 0.3 * t) + 1e-4 * np.cumsum(rng.normal(0, 0.03,
                                                                                 t.size))
    vir = 5.0 * (qg - np.roll(qg, 3)) + rng.normal(0.0, 0.01, t.size)
    qm = qg + 1e-5 * rng.standard_normal(t.size)
    scipy.io.savemat(tmp_path / "stage.mat", {"t": t[:, None], "vir": vir[:, None],
                                               "qm": qm[:, None], "qg": qg[:, None]})
    (tmp_path / "manifest.csv").write_text("file,subject,axis,grip_N\nstage.mat,s1,x,0\n")
    return tmp_path / "manifest.csv", qg


MAP = "quantity,source,unit,gain\ntime_s,t,s,\nforce_x_N,vir,V,35.15\npos_x_m,qm,m,\n"


def test_a_map_gives_the_reference_and_the_dataset_keeps_it(tmp_path, runner):
    manifest, qg = _stage(tmp_path)
    (tmp_path / "map.csv").write_text(MAP + "ref_x_m,qg,m,\n")
    res = runner.invoke(cli, ["ingest", "--manifest", str(manifest), "--map",
                              str(tmp_path / "map.csv"), "-o", str(tmp_path / "d.parquet")])
    assert res.exit_code == 0, res.output
    assert "ref_x_m = qg (m)" in res.stderr
    d = pq.read_table(tmp_path / "d.parquet")
    assert d.column_names == ["trial", *DATASET_COLUMNS, "ref"]
    np.testing.assert_array_equal(d.column("ref").to_numpy(), qg)   # read back bit for bit
    (record,) = json.loads(pq.read_metadata(tmp_path / "d.parquet").metadata[b"armfit.trials"])
    assert record["reference"] == "ref_x_m"
    # the dataset and the raw file through its map give the same spectra
    for name, inputs in (("raw", ["--manifest", str(manifest), "--map",
                                  str(tmp_path / "map.csv")]),
                         ("dataset", [str(tmp_path / "d.parquet")])):
        res = runner.invoke(cli, ["estimate", *inputs, "-o", str(tmp_path / f"{name}.parquet"),
                                  "--fmin", "0.5"])
        assert res.exit_code == 0, res.output
    raw, ds = (Spectra.read(tmp_path / f"{n}.parquet") for n in ("raw", "dataset"))
    assert raw.select(kind="measured", level="trial").values_of("method") == {"ref"}
    np.testing.assert_array_equal(raw.h, ds.h)


def test_a_dataset_without_references_has_the_columns_it_always_had(tmp_path, write_trial,
                                                                    runner):
    write_trial(tmp_path / "raw" / "sub-01_axis-x_grip-2N.csv", fs=FS, duration_s=25.0)
    res = runner.invoke(cli, ["ingest", str(tmp_path / "raw"), "-o", str(tmp_path / "d.parquet")])
    assert res.exit_code == 0, res.output
    assert pq.read_schema(tmp_path / "d.parquet").names == ["trial", *DATASET_COLUMNS]
    (record,) = json.loads(pq.read_metadata(tmp_path / "d.parquet").metadata[b"armfit.trials"])
    assert "reference" not in record


def test_a_map_with_two_references_for_one_axis_is_refused(tmp_path, runner):
    manifest, _ = _stage(tmp_path)
    (tmp_path / "map.csv").write_text(MAP + "ref_x_m,qg,m,\nref_x_N,vir,V,35.15\n")
    res = runner.invoke(cli, ["ingest", "--manifest", str(manifest), "--map",
                              str(tmp_path / "map.csv"), "-o", str(tmp_path / "d.parquet")])
    assert res.exit_code == 65
    assert _one_error(res.stderr) == (
        f"armfit: error: {tmp_path / 'map.csv'}, column 'quantity', row 5: both ref_x_N "
        "(row 5) and ref_x_m (row 4) are given: a trial's reference is a commanded force "
        "or a reference position, not both")
