"""Tests of `armfit simulate` and of the raw-trial writer (armfit.io.rawwrite)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from armfit.cli.main import cli
from armfit.errors import EXIT_CANTCREAT, EXIT_USAGE, OutputError, UsageError
from armfit.io.rawwrite import trial_filename, write_trial
from armfit.io.trials import TrialSource, open_trials, parse_name, read_trial
from armfit.simulation import StudyConfig, plan_study, simulate_trial

SMALL = ["--subjects", "1", "--axes", "xz", "--grips", "1,3", "--duration", "20,21"]


def _run(runner, *args):
    return runner.invoke(cli, ["simulate", *args])


def _read(folder: Path) -> dict[str, object]:
    """Every trial of a study folder, read by the data contract's reader."""
    return {Path(t.meta.source).name: t for t in open_trials([folder])}


@pytest.fixture(scope="module")
def study(tmp_path_factory):
    """A small study written by the CLI (seed 4), with its --json summary."""
    from click.testing import CliRunner
    out = tmp_path_factory.mktemp("sim") / "study"
    res = CliRunner().invoke(cli, ["simulate", "-o", str(out), *SMALL, "--seed", "4",
                                   "--json"])
    assert res.exit_code == 0, res.output
    return out, json.loads(res.stdout)


def test_writes_named_files_truth_beside_and_json(study):
    out, summary = study
    names = sorted(p.name for p in out.iterdir())
    expected = sorted(f"sub-01_axis-{a}_grip-{g}N.parquet" for a in "xz" for g in (1, 3))
    assert names == expected
    assert summary["trials"] == 4 and sorted(summary["files"]) == expected
    truth_path = out.parent / "study.truth.json"
    assert summary["truth"] == str(truth_path)
    assert not (out / "study.truth.json").exists()
    truth = json.loads(truth_path.read_text())
    assert truth["seed"] == 4 and truth["options"]["grips"] == "1,3"
    assert [(t["axis"], t["grip_N"]) for t in truth["trials"]] == [
        ("x", 1.0), ("x", 3.0), ("z", 1.0), ("z", 3.0)]
    # No temporary files are left beside the study.
    assert sorted(p.name for p in out.parent.iterdir()) == ["study", "study.truth.json"]


def test_files_follow_the_contract_and_match_the_truth(study):
    # The contract's own reader accepts every file; durations and identity agree with the
    # truth file; 20–21 s at 1 kHz.
    out, _ = study
    truth = json.loads((out.parent / "study.truth.json").read_text())
    trials = _read(out)
    assert len(trials) == 4
    for t in truth["trials"]:
        trial = trials[f"sub-01_axis-{t['axis']}_grip-{t['grip_N']:g}N.parquet"]
        assert trial.meta.n_samples == t["n_samples"]
        assert 20000 <= trial.meta.n_samples <= 21000
        assert trial.meta.fs == 1000.0 and trial.meta.subject == "01"
        assert np.abs(trial.f).max() <= 5.0


def test_same_seed_gives_identical_files_other_seed_differs(study, runner, tmp_path):
    out, _ = study
    assert _run(runner, "-o", str(tmp_path / "again"), *SMALL, "--seed", "4").exit_code == 0
    assert _run(runner, "-o", str(tmp_path / "other"), *SMALL, "--seed", "5").exit_code == 0
    first, again, other = _read(out), _read(tmp_path / "again"), _read(tmp_path / "other")
    for name, trial in first.items():
        np.testing.assert_array_equal(trial.pos, again[name].pos)
        np.testing.assert_array_equal(trial.force, again[name].force)
        np.testing.assert_array_equal(trial.grip, again[name].grip)
        assert not np.array_equal(trial.force, other[name].force)


def test_refuses_to_overwrite_without_flag(study, runner, tmp_path):
    out = tmp_path / "s"
    args = ["-o", str(out), "--subjects", "1", "--axes", "y", "--grips", "2",
            "--duration", "20,20"]
    assert _run(runner, *args).exit_code == 0
    before = (out / "sub-01_axis-y_grip-2N.parquet").read_bytes()
    res = _run(runner, *args, "--seed", "9")
    assert res.exit_code == EXIT_CANTCREAT
    assert "exists; pass --overwrite" in res.stderr
    assert (out / "sub-01_axis-y_grip-2N.parquet").read_bytes() == before
    res = _run(runner, *args, "--seed", "9", "--overwrite")
    assert res.exit_code == 0
    assert (out / "sub-01_axis-y_grip-2N.parquet").read_bytes() != before
    assert json.loads((tmp_path / "s.truth.json").read_text())["seed"] == 9


@pytest.mark.parametrize("args, text", [
    (["--effect", "bogus=1"], "unknown effect 'bogus'"),
    (["--effect", "delay=abc"], "'abc' is not a number"),
    (["--effect", "delay=5"], "outside the physical range"),
    (["--effect-axes", "z"], "--effect-axes needs at least one --effect"),
    (["--effect", "delay=0.01", "--effect-axes", "w"], "distinct letters of xyz"),
    (["--grips", "1.5"], "rows of Table I"),
    (["--duration", "30,20"], "0 < MIN <= MAX"),
    (["--axes", "xq"], "distinct letters of xyz"),
])
def test_bad_options_exit_2_with_one_line(runner, tmp_path, args, text):
    res = _run(runner, "-o", str(tmp_path / "s"), "--subjects", "1", "--duration", "20",
               *args)
    assert res.exit_code == EXIT_USAGE
    assert text in res.stderr
    assert len(res.stderr.strip().splitlines()) == 1 and "Traceback" not in res.stderr
    assert not (tmp_path / "s").exists() and not (tmp_path / "s.truth.json").exists()


def test_unstable_effect_leaves_no_partial_output(runner, tmp_path):
    # reflex 300 N/m, 40 ms destabilises the X-axis loop (see test_simulate). The Z trial
    # is written first (into the temporary folder); after the failure on X nothing of the
    # study or its truth may remain.
    res = _run(runner, "-o", str(tmp_path / "s"), "--subjects", "1", "--axes", "zx",
               "--grips", "1", "--duration", "20", "--effect",
               "reflex=gain_N_per_m:300,delay_s:0.04")
    assert res.exit_code == EXIT_USAGE
    assert "unstable" in res.stderr
    assert list(tmp_path.iterdir()) == []


def test_truth_option_and_truth_inside_study_refused(runner, tmp_path):
    res = _run(runner, "-o", str(tmp_path / "s"), "--subjects", "1", "--axes", "x",
               "--grips", "1", "--duration", "20", "--truth", str(tmp_path / "s" / "t.json"))
    assert res.exit_code == EXIT_USAGE and "outside the study folder" in res.stderr
    res = _run(runner, "-o", str(tmp_path / "s"), "--subjects", "1", "--axes", "x",
               "--grips", "1", "--duration", "20", "--truth", str(tmp_path / "t" / "k.json"),
               "--effect", "delay=0.012", "--effect-axes", "x")
    assert res.exit_code == 0, res.stderr
    truth = json.loads((tmp_path / "t" / "k.json").read_text())
    assert truth["effects"] == [{"name": "delay", "values": {"delay_s": 0.012},
                                 "axes": ["x"]}]


@pytest.mark.parametrize("fmt, units", [("csv", "m"), ("csv.gz", "mm"), ("parquet", "mm")])
def test_formats_and_units_round_trip(runner, tmp_path, fmt, units):
    # The same seed in Parquet/m and another format/unit: the contract reader gives the
    # same arrays. CSV keeps 9 decimals in m (1 nm, 1 nN) or 6 in mm, so allow 1e-9.
    common = ["--subjects", "1", "--axes", "y", "--grips", "2", "--duration", "20",
              "--seed", "2"]
    assert _run(runner, "-o", str(tmp_path / "ref"), *common).exit_code == 0
    res = _run(runner, "-o", str(tmp_path / "alt"), *common, "--format", fmt,
               "--units", units)
    assert res.exit_code == 0, res.stderr
    ext = {"csv": ".csv", "csv.gz": ".csv.gz", "parquet": ".parquet"}[fmt]
    alt_file = tmp_path / "alt" / f"sub-01_axis-y_grip-2N{ext}"
    assert alt_file.exists()
    if units == "mm" and fmt != "parquet":
        import gzip
        assert "pos_y_mm" in gzip.open(alt_file, "rt").readline()
    ref = next(iter(_read(tmp_path / "ref").values()))
    alt = next(iter(_read(tmp_path / "alt").values()))
    np.testing.assert_allclose(alt.pos, ref.pos, rtol=0, atol=1e-9)
    np.testing.assert_allclose(alt.force, ref.force, rtol=0, atol=1e-9)
    np.testing.assert_allclose(alt.grip, ref.grip, rtol=0, atol=1e-9)


def test_write_trial_names_columns_and_refuses_existing(tmp_path):
    cfg = StudyConfig(subjects=1, axes=("z",), grips_N=(3.0,), duration_s=(20.0, 20.0))
    trial = simulate_trial(plan_study(cfg)[0], cfg)
    name = trial_filename(trial.meta, "parquet")
    assert name == "sub-01_axis-z_grip-3N.parquet"
    assert parse_name(name) == ("01", "z", 3.0, None)
    path = write_trial(trial, tmp_path / name)
    import pyarrow.parquet as pq
    assert pq.read_schema(path).names == [
        "time_s", "force_x_N", "force_y_N", "force_z_N", "pos_x_m", "pos_y_m", "pos_z_m",
        "grip_N"]
    back = read_trial(TrialSource(str(path), "01", "z", 3.0))
    np.testing.assert_array_equal(back.pos, trial.pos)
    np.testing.assert_array_equal(back.force, trial.force)
    with pytest.raises(OutputError, match="exists; pass overwrite=True"):
        write_trial(trial, path)
    with pytest.raises(UsageError, match="cannot tell the format"):
        write_trial(trial, tmp_path / "trial.txt")


def test_help_lists_options(runner):
    res = runner.invoke(cli, ["simulate", "--help"])
    assert res.exit_code == 0
    for opt in ("--subjects", "--duration", "--noise", "--variability", "--drift",
                "--format", "--units", "--effect", "--effect-axes", "--truth",
                "--overwrite", "--json"):
        assert opt in res.output
