"""armfit.pipeline: the output-folder checks, compare.csv's layout, and that a stage
failing after others have written leaves no OUTDIR (or the old one untouched)."""

from __future__ import annotations

import multiprocessing as mp
import sys
import threading

import pytest
from click.testing import CliRunner

from armfit.cli.main import cli
from armfit.diagnosis import BandError, Comparison
from armfit.errors import ConvergenceError, OutputError
from armfit.pipeline import (
    COMPARE_COLUMNS,
    RunOptions,
    _import_meanwhile,
    check_outdir,
    compare_frame,
    run_pipeline,
)
from armfit.report import md_table


def _band(lo, hi, k):
    return BandError(lo, hi, rms_db=k, rms_deg=10 * k, rms_norm=100 * k, n_points=5)


def test_compare_frame_flattens_rows_per_band_base_first():
    rows = [
        Comparison("z", None, "median", "base+delay", _band(0.1, 30, 1.0),
                   (_band(0.1, 1, 2.0), _band(10, 30, 3.0)), (), {"delay.delay_s": 0.01}, 9),
        Comparison("x", None, "median", "base", _band(0.1, 30, 4.0), (_band(0.1, 1, 5.0),),
                   (), {}, 9),
        Comparison("z", None, "median", "base", _band(0.1, 30, 6.0), (), (), {}, 9),
    ]
    df = compare_frame(rows)
    assert tuple(df.columns) == COMPARE_COLUMNS
    # sorted by axis; within an axis the models keep their first-seen order
    # (base+delay came first in the input here)
    got = [tuple(r) for r in df[["axis", "model", "band", "rms_db", "rms_deg",
                                 "rms_norm"]].itertuples(index=False)]
    assert got == [("x", "base", "overall", 4.0, 40.0, 400.0),
                   ("x", "base", "0.1-1", 5.0, 50.0, 500.0),
                   ("z", "base+delay", "overall", 1.0, 10.0, 100.0),
                   ("z", "base+delay", "0.1-1", 2.0, 20.0, 200.0),
                   ("z", "base+delay", "10-30", 3.0, 30.0, 300.0),
                   ("z", "base", "overall", 6.0, 60.0, 600.0)]
    assert df["grip"].isna().all() and set(df["level"]) == {"median"}


def test_md_table_escapes_pipes():
    # markdown table syntax: a literal | inside a cell must be written \|
    assert md_table(["a", "b"], [["|Wu|", 1]]) == ["| a | b |", "|---|---|",
                                                   "| \\|Wu\\| | 1 |", ""]


def test_check_outdir_refusals(tmp_path):
    (tmp_path / "file").write_text("x")
    with pytest.raises(OutputError, match=r"file: exists and is not a folder"):
        check_outdir(tmp_path / "file", [], overwrite=True)
    (tmp_path / "raw").mkdir()
    with pytest.raises(OutputError, match=r"holds the input .*raw"):
        check_outdir(tmp_path, [tmp_path / "raw"], overwrite=True)
    with pytest.raises(OutputError, match=r"holds the input"):
        check_outdir(tmp_path / "raw", [tmp_path / "raw"], overwrite=True)
    with pytest.raises(OutputError, match=r"holds the input .*m\.csv"):
        check_outdir(tmp_path, [], manifest=tmp_path / "m.csv", overwrite=True)
    with pytest.raises(OutputError, match=r"exists; pass overwrite=True"):
        check_outdir(tmp_path / "raw", [tmp_path / "other"])
    assert check_outdir(tmp_path / "new", [tmp_path / "raw"]) == tmp_path / "new"


@pytest.fixture(scope="module")
def tiny_study(tmp_path_factory):
    """2 subjects, x and y axes, grips 1 and 2 N, 26 s trials (`armfit simulate`, seed 5)."""
    root = tmp_path_factory.mktemp("tiny")
    res = CliRunner().invoke(cli, ["simulate", "-o", str(root / "study"), "--subjects", "2",
                                   "--axes", "xy", "--grips", "1,2", "--duration", "26,26",
                                   "--seed", "5"])
    assert res.exit_code == 0, res.output
    return root / "study"


def test_failing_stage_keeps_the_old_outdir_and_leaves_no_temporary(tiny_study, tmp_path,
                                                                      monkeypatch):
    """A fit-nominal that does not converge after three stages have written their files,
    with the diagnosis already running in worker processes: the error propagates, the
    workers are stopped, the existing OUTDIR is untouched (even with overwrite) and
    nothing else is left in its folder."""
    import armfit.api

    workers = []

    def no_convergence(*args, **kwargs):
        workers.append(len(mp.active_children()))
        raise ConvergenceError("the fit of axis x did not converge")

    monkeypatch.setattr(armfit.api, "fit_nominal", no_convergence)
    out = tmp_path / "out"
    out.mkdir()
    (out / "old.txt").write_text("previous results")
    seen = []
    with pytest.raises(ConvergenceError, match="did not converge"):
        run_pipeline([tiny_study], out, RunOptions(overwrite=True, jobs=2),
                     on_stage=lambda s: seen.append(s.name))
    assert seen == ["ingest", "estimate", "fit-grip"]
    assert [p.name for p in out.iterdir()] == ["old.txt"]
    assert (out / "old.txt").read_text() == "previous results"
    assert [p.name for p in tmp_path.iterdir()] == ["out"]
    assert workers[0] >= 2  # jobs=2 workers for the stages (and the diagnosis's) ...
    assert mp.active_children() == []  # ... and was stopped


def test_run_gives_the_same_bytes_with_one_or_two_jobs(tiny_study, tmp_path, monkeypatch):
    """With --jobs 2 one worker pool serves every stage (the estimate alongside the
    ingest, the diagnosis and per-trial fits in the background, figures drawn in the
    workers, the stability figure's sweeps computed there: this process's
    stability_sweep fails in that run); every file, figures and report included, is the
    same as with --jobs 1 (the report's command line names the output folder as given:
    the same name in another parent folder). The stability figure is drawn from the
    stability stage's own table (with --jobs 1, in this process, where the figures'
    stability_table fails)."""
    import armfit.figures

    def not_here(*args, **kwargs):
        raise AssertionError("the stability sweep was computed in the main process")

    def recomputed(*args, **kwargs):
        raise AssertionError("the stability figure recomputed the stability table")

    monkeypatch.setattr(armfit.figures, "stability_table", recomputed)
    outs = {}
    for jobs in (1, 2):
        if jobs == 2:
            monkeypatch.setattr(armfit.figures, "stability_sweep", not_here)
        (tmp_path / f"j{jobs}").mkdir()
        out = tmp_path / f"j{jobs}" / "out"
        result = run_pipeline([tiny_study], out, RunOptions(jobs=jobs))
        outs[jobs] = {name: (out / name).read_bytes() for name in result.files}
        report = outs[jobs]["report.md"].decode()
        assert f"-o {out} " in report  # the command as run, the folder as given
        for name in ("report.md", "report.html"):
            outs[jobs][name] = outs[jobs][name].decode().replace(str(out), "OUT").encode()
    assert sorted(outs[1]) == sorted(outs[2])
    assert any(name.endswith(".png") for name in outs[1])
    assert [n for n in outs[1] if outs[1][n] != outs[2][n]] == []
    assert mp.active_children() == []   # the pool is shut down with the run


def test_a_module_imported_meanwhile_is_loaded_and_a_failure_there_is_left_to_its_user(
        tmp_path, monkeypatch):
    """The run loads pandas in a thread while the grip fits run in the workers
    (:func:`armfit.pipeline._import_meanwhile`): the module is then in sys.modules, run
    once; a module that fails to import raises nothing in that thread (no traceback on
    stderr, which the thread's hook would print) and its first user gets the error."""
    (tmp_path / "armfit_probe_ok.py").write_text("LOADS = []\nLOADS.append(1)\n")
    (tmp_path / "armfit_probe_bad.py").write_text("raise ImportError('broken install')\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    uncaught = []
    monkeypatch.setattr(threading, "excepthook", uncaught.append)
    try:
        for name in ("armfit_probe_ok", "armfit_probe_bad"):
            _import_meanwhile(name).join(timeout=30)
        assert uncaught == []
        import armfit_probe_ok
        assert armfit_probe_ok.LOADS == [1]
        with pytest.raises(ImportError, match="broken install"):
            import armfit_probe_bad  # noqa: F401
    finally:
        sys.modules.pop("armfit_probe_ok", None)
