"""Tests of `armfit plot`: each figure kind from files, output checks and user errors.

Inputs are the small study of test_figures (Table I models with a seeded error) written
in the file formats `armfit plot` reads: spectra Parquet, parameters CSV, Wu CSV (the
paper's Table III).
"""

from __future__ import annotations

from pathlib import Path

import pytest
from test_figures import TABLE_COLS, params_table, study_spectra, table1

from armfit.cli.main import cli
from armfit.data import paper_table
from armfit.errors import EXIT_CANTCREAT, EXIT_DATAERR, EXIT_NOINPUT, EXIT_USAGE
from armfit.io.artifacts import write_params
from armfit.spectra import Spectra


@pytest.fixture(scope="module")
def files(tmp_path_factory) -> dict[str, Path]:
    d = tmp_path_factory.mktemp("plotin")
    out = {"spectra": d / "spectra.parquet", "grip": d / "grip.csv",
           "nominal": d / "nominal.csv", "delay": d / "delay.csv", "wu": d / "wu.csv"}
    Spectra.from_frame(study_spectra(("x", "y")), meta={}).write(out["spectra"])
    write_params(params_table(table1()), out["grip"])
    write_params(params_table(table1(), effects={"delay.delay_s": 0.002},
                              effect_name="delay"), out["delay"])
    write_params(params_table(paper_table("nominal").rename(columns=TABLE_COLS)),
                 out["nominal"])
    paper_table("uncertainty").to_csv(out["wu"], index=False)
    return out


MAGIC = {".png": b"\x89PNG", ".pdf": b"%PDF-", ".svg": b"<?xml"}


def run(runner, *args):
    return runner.invoke(cli, ["plot", *map(str, args)])


def test_bode(runner, files, tmp_path):
    out = tmp_path / "fig5.png"
    r = run(runner, "bode", files["spectra"], "--model", files["grip"], "-o", out)
    assert r.exit_code == 0, r.output
    assert out.read_bytes().startswith(MAGIC[".png"])
    assert f"wrote {out}" in r.stderr


def test_bode_one_axis_quartiles_no_model(runner, files, tmp_path):
    out = tmp_path / "fig5y.svg"
    r = run(runner, "bode", files["spectra"], "--axis", "y", "--spread", "quartiles",
            "--no-trials", "-o", out)
    assert r.exit_code == 0, r.output
    assert out.read_bytes().startswith(MAGIC[".svg"])


def test_residual_with_second_model_and_bands(runner, files, tmp_path):
    out = tmp_path / "res.pdf"
    r = run(runner, "residual", files["spectra"], "--model", files["grip"], "--model2",
            files["delay"], "--band", "x=8:12", "--band", "20:30", "-o", out)
    assert r.exit_code == 0, r.output
    assert out.read_bytes().startswith(MAGIC[".pdf"])
    # Automatic bands (no --band) on the nominal model against the medians.
    out2 = tmp_path / "res2.png"
    r = run(runner, "residual", files["spectra"], "--model", files["nominal"], "-o", out2)
    assert r.exit_code == 0, r.output


def test_uncertainty(runner, files, tmp_path):
    out = tmp_path / "fig6.pdf"
    r = run(runner, "uncertainty", files["spectra"], "--nominal", files["nominal"],
            "--weights", files["wu"], "-o", out)
    assert r.exit_code == 0, r.output
    assert out.read_bytes().startswith(MAGIC[".pdf"])


def test_literature_default_and_file(runner, files, tmp_path):
    r = run(runner, "literature", "-o", tmp_path / "fig7.svg")
    assert r.exit_code == 0, r.output
    r = run(runner, "literature", "--model", files["grip"], "--axis", "y", "--grip", "2",
            "-o", tmp_path / "fig7y.png")
    assert r.exit_code == 0, r.output
    # Table I has grips 1, 2 and 3 N only.
    r = run(runner, "literature", "--model", files["grip"], "--grip", "5",
            "-o", tmp_path / "none.png")
    assert r.exit_code == EXIT_USAGE
    assert "no x row with grip 5 N (grips: 1, 2, 3)" in r.stderr


def test_same_input_same_bytes_and_overwrite(runner, files, tmp_path):
    out = tmp_path / "fig6.svg"
    args = ("uncertainty", files["spectra"], "--nominal", files["nominal"], "-o", out)
    assert run(runner, *args).exit_code == 0
    first = out.read_bytes()
    r = run(runner, *args)
    assert r.exit_code == EXIT_CANTCREAT
    assert "exists; pass --overwrite" in r.stderr
    assert out.read_bytes() == first
    assert run(runner, *args, "--overwrite").exit_code == 0
    assert out.read_bytes() == first  # byte-identical on a second write


def test_unknown_extension(runner, files, tmp_path):
    out = tmp_path / "fig5.jpg"
    r = run(runner, "bode", files["spectra"], "-o", out)
    assert r.exit_code == EXIT_USAGE
    assert "plot bode writes .png, .svg or .pdf; not .jpg" in r.stderr
    assert "Traceback" not in r.output + r.stderr
    assert not out.exists()


def test_missing_input(runner, tmp_path):
    r = run(runner, "bode", tmp_path / "nope.parquet", "-o", tmp_path / "a.png")
    assert r.exit_code == EXIT_NOINPUT
    assert "nope.parquet: no such spectra file" in r.stderr


def test_params_missing_column_and_bad_number(runner, files, tmp_path):
    bad = tmp_path / "bad.csv"
    params_table(table1()).drop(columns=["b2"]).to_csv(bad, index=False)
    r = run(runner, "bode", files["spectra"], "--model", bad, "-o", tmp_path / "a.png")
    assert r.exit_code == EXIT_DATAERR
    assert f"{bad}, column 'b2': missing column" in r.stderr
    p = params_table(table1())
    p["k1"] = p["k1"].astype(object)
    p.loc[4, "k1"] = "n/a"
    p.to_csv(bad, index=False)
    r = run(runner, "bode", files["spectra"], "--model", bad, "-o", tmp_path / "a.png")
    assert r.exit_code == EXIT_DATAERR
    assert f"{bad}, column 'k1', row 5: parameter must be a positive number" in r.stderr
    assert not (tmp_path / "a.png").exists()


def test_spectra_not_parquet_or_missing_column(runner, files, tmp_path):
    r = run(runner, "bode", files["grip"], "-o", tmp_path / "a.png")
    assert r.exit_code == EXIT_DATAERR
    assert f"{files['grip']}: not a readable Parquet spectra file" in r.stderr
    sp = tmp_path / "s.parquet"
    study_spectra(("x",)).drop(columns=["se_db"]).to_parquet(sp)  # no se_db column
    r = run(runner, "bode", sp, "-o", tmp_path / "a.png")
    assert r.exit_code == EXIT_DATAERR
    assert f"{sp}, column 'se_db': missing column" in r.stderr


def test_axis_absent_from_spectra(runner, files, tmp_path):
    r = run(runner, "bode", files["spectra"], "--axis", "z", "-o", tmp_path / "a.png")
    assert r.exit_code == EXIT_DATAERR
    assert f"{files['spectra']}, column 'axis': no measured responses for axis z" in r.stderr


def test_weights_bad_kind(runner, files, tmp_path):
    wu = tmp_path / "wu.csv"
    t = paper_table("uncertainty")
    t.loc[2, "kind"] = "zeros"
    t.to_csv(wu, index=False)
    r = run(runner, "uncertainty", files["spectra"], "--nominal", files["nominal"],
            "--weights", wu, "-o", tmp_path / "a.png")
    assert r.exit_code == EXIT_DATAERR
    assert f"{wu}, column 'kind', row 3: expected one of gain, zero, pole, got 'zeros'" \
        in r.stderr


@pytest.mark.parametrize("band", ["8-12", "x=12:8", "q=1:2", "a:b", "x:8:12"])
def test_bad_band(runner, files, tmp_path, band):
    r = run(runner, "residual", files["spectra"], "--model", files["grip"], "--band", band,
            "-o", tmp_path / "a.png")
    assert r.exit_code == EXIT_USAGE
    assert f"--band {band!r}" in r.stderr
