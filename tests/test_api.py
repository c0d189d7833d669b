"""The public Python API: the example of docs/api.md, and results equal to the CLI's files."""

from __future__ import annotations

import os
import re
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

import armfit
from armfit.cli.main import cli

REPO = Path(__file__).resolve().parents[1]
STUDY = REPO / "sample_data" / "study"


@pytest.fixture(scope="module")
def spectra() -> armfit.Spectra:
    return armfit.estimate(STUDY)


def test_exports():
    for name in ("read_trials", "estimate", "fit_grip", "fit_nominal", "fit_uncertainty",
                 "compare", "diagnose", "simulate", "run", "Effect", "Param", "EFFECTS",
                 "Spectra"):
        assert hasattr(armfit, name), name
        assert getattr(armfit, name).__doc__, f"{name} has no docstring"


def test_the_diagnosis_package_and_the_diagnose_stage_are_apart():
    # the engine is the package armfit.diagnosis; armfit.diagnose and armfit.compare stay
    # the API's stage functions (armfit.api) after every module of the package is loaded
    import importlib
    import pkgutil
    import types

    import armfit.api
    import armfit.diagnosis as engine

    for mod in pkgutil.iter_modules(engine.__path__):
        importlib.import_module(f"armfit.diagnosis.{mod.name}")
    assert isinstance(engine, types.ModuleType) and hasattr(engine, "__path__")
    assert armfit.diagnose is armfit.api.diagnose
    assert armfit.compare is armfit.api.compare
    # the engine's own names differ from the stages': diagnose_axes, compare_models
    assert not hasattr(engine, "diagnose")
    assert isinstance(engine.compare, types.ModuleType)     # its submodule compare.py
    assert callable(engine.diagnose_axes) and callable(engine.compare_models)


def test_spectra_hold_the_study_once(spectra):
    # sample_data/study: 4 subjects x 3 axes x 3 grips = 36 trials, one file each (its README)
    trials = spectra.select(level="trial", kind="measured")
    assert len(trials) == 36
    assert len(spectra.select(level="trial", kind="derived", axis="z")) == 12
    assert len(spectra.select(level="mean", kind="measured")) == 9       # axis x grip
    assert len(spectra.select(level="median", kind="measured")) == 3     # axis
    assert trials.h.shape == (36, spectra.freq_hz.size) and trials.present.all()
    one = spectra.select(axis="y", grip=3.0, level="mean", kind="measured")
    assert one.key("grip_N")[0] == 3.0 and one.key("n")[0] == 4      # 4 subjects
    # the long table round-trips exactly
    back = armfit.Spectra.from_frame(spectra.to_frame(), meta=spectra.meta)
    assert back.to_frame().equals(spectra.to_frame())
    np.testing.assert_array_equal(back.h, spectra.h)


def test_results_write_the_files_of_the_commands(spectra, tmp_path):
    runner = CliRunner()
    spectra.write(tmp_path / "api_spectra.parquet")
    res = runner.invoke(cli, ["-q", "estimate", str(STUDY), "-o",
                              str(tmp_path / "cli_spectra.parquet")])
    assert res.exit_code == 0, res.output
    assert (tmp_path / "api_spectra.parquet").read_bytes() == \
        (tmp_path / "cli_spectra.parquet").read_bytes()
    m = armfit.fit_nominal(spectra)
    m.write(tmp_path / "api_nominal.csv")
    res = runner.invoke(cli, ["-q", "fit-nominal", str(tmp_path / "cli_spectra.parquet"),
                              "-o", str(tmp_path / "cli_nominal.csv")])
    assert res.exit_code == 0, res.output
    assert (tmp_path / "api_nominal.csv").read_bytes() == \
        (tmp_path / "cli_nominal.csv").read_bytes()
    # the frame holds the file's numbers (10 significant digits in the file)
    cols = ["Ma", "k1", "k2", "b1", "b2"]
    from_file = armfit.read_model(tmp_path / "cli_nominal.csv").to_frame()[cols]
    np.testing.assert_allclose(m.to_frame()[cols].to_numpy(float),
                               from_file.to_numpy(float), rtol=1e-9)
    with pytest.raises(armfit.OutputError, match="exists; pass overwrite=True"):
        m.write(tmp_path / "api_nominal.csv")


def _python_blocks(path: Path) -> list[str]:
    return re.findall(r"```python\n(.*?)```", path.read_text(encoding="utf-8"), flags=re.S)


def test_docs_api_example_runs_first(spectra, monkeypatch, capsys):
    blocks = _python_blocks(REPO / "docs" / "api.md")
    first = blocks[0]
    assert "armfit.estimate(\"sample_data/study\")" in first
    monkeypatch.chdir(REPO)
    # the first block as written, with the estimate already made above (same call)
    monkeypatch.setattr(armfit, "estimate", lambda *a, **k: spectra)
    namespace: dict = {}
    exec(compile(first, "docs/api.md", "exec"), namespace)  # noqa: S102
    d, m = namespace["d"], namespace["m"]
    frame = d.to_frame()
    assert list(frame["axis"]) == ["x", "y", "z"]          # one row per axis
    assert list(m.to_frame().columns[1:6]) == ["Ma", "k1", "k2", "b1", "b2"]
    out = capsys.readouterr().out
    assert "verdict" in out and "Ma" in out
    assert os.getcwd() == str(REPO)
