"""CLI tests of `armfit effects`, `armfit compare` and `armfit diagnose`.

The study is simulated with a known hidden effect (a 12 ms delay on the X axis, the
simulator's truth), so the expected verdict is known.
"""

from __future__ import annotations

import json

import pytest

from armfit.cli.main import cli
from armfit.models.effects import EFFECTS


@pytest.fixture(scope="module")
def study(tmp_path_factory):
    from click.testing import CliRunner
    runner = CliRunner()
    d = tmp_path_factory.mktemp("cli_diag")
    steps = [
        ["simulate", "-o", str(d / "raw"), "--subjects", "2", "--axes", "x", "--duration",
         "30,35", "--seed", "5", "--effect", "delay=0.012"],
        ["estimate", str(d / "raw"), "-o", str(d / "spectra.parquet")],
        ["fit-grip", str(d / "spectra.parquet"), "-o", str(d / "grip.csv")],
        ["fit-nominal", str(d / "spectra.parquet"), "-o", str(d / "nominal.csv")],
    ]
    for args in steps:
        res = runner.invoke(cli, args)
        assert res.exit_code == 0, (args, res.output)
    return d


def test_effects_lists_the_library(runner):
    res = runner.invoke(cli, ["effects", "--json"])
    assert res.exit_code == 0
    doc = json.loads(res.stdout)
    assert [e["effect"] for e in doc["effects"]] == list(EFFECTS)
    delay = doc["effects"][0]
    assert delay["params"][0]["name"] == "delay_s" and delay["params"][0]["unit"] == "s"
    table = runner.invoke(cli, ["effects"])
    assert table.exit_code == 0 and "device-damping" in table.stdout


def test_diagnose_json_schema_and_verdict(runner, study):
    res = runner.invoke(cli, ["diagnose", str(study / "spectra.parquet"), "--model",
                              str(study / "grip.csv"), "--json"])
    assert res.exit_code == 0, res.output
    doc = json.loads(res.stdout)
    x = doc["axes"]["x"]
    assert set(doc["axes"]) == {"x"}
    assert x["missing_effect"] == "delay"                    # the simulator's truth
    first = x["candidates"][0]
    assert first["effect"] == "delay" and first["significant"] is True
    assert first["params"]["delay_s"] == pytest.approx(0.012, abs=1e-3)
    assert first["rms_db_after"] <= first["rms_db_before"]
    for key in ("effect", "params", "rms_db_before", "rms_db_after", "score", "significant"):
        assert all(key in c for c in x["candidates"])
    scores = [c["score"] for c in x["candidates"] if c["rms_norm_after"] is not None]
    assert scores == sorted(scores, reverse=True)             # best first
    # the stepwise keys: delay found, the error falls to within the noise
    assert x["missing_effects"][0]["effect"] == "delay"
    assert len(x["error_steps"]) == 1 + len(x["missing_effects"])
    assert x["adequate"] is True and x["error_steps"][-1] <= 1.5
    assert x["error_steps"][0] > x["error_steps"][-1]


def test_diagnose_writes_json_file_and_refuses_overwrite(runner, study):
    out = study / "diag.json"
    args = ["diagnose", str(study / "spectra.parquet"), "--model", str(study / "grip.csv"),
            "--effect", "delay", "-o", str(out)]
    res = runner.invoke(cli, args)
    assert res.exit_code == 0, res.output
    assert json.loads(out.read_text())["axes"]["x"]["missing_effect"] == "delay"
    assert "verdict: adequate after adding delay" in res.stdout
    assert "stepwise search" in res.stdout
    again = runner.invoke(cli, args)
    assert again.exit_code == 73 and "--overwrite" in again.stderr


def test_compare_table_and_effect(runner, study):
    res = runner.invoke(cli, ["compare", str(study / "spectra.parquet"), "--model",
                              str(study / "nominal.csv"), "--effect", "delay", "--json"])
    assert res.exit_code == 0, res.output
    doc = json.loads(res.stdout)
    assert doc["level"] == "median"                           # nominal fits → median
    base, ext = doc["rows"]
    assert base["model"] == "base" and ext["model"] == "base+delay"
    assert [b["lo_hz"] for b in base["bands"]] == [0.1, 1.0, 3.0, 10.0]
    # the user watches the error fall: phase error at least halved with the delay
    assert ext["overall"]["rms_deg"] < 0.5 * base["overall"]["rms_deg"]
    assert base["failing"] and "phase lags" in base["failing"][-1]["description"]
    table = runner.invoke(cli, ["compare", str(study / "spectra.parquet"), "--model",
                                str(study / "grip.csv")])
    assert table.exit_code == 0
    assert "fails" in table.stdout and "10–30 Hz" in table.stdout


@pytest.mark.parametrize("args,code,text", [
    (["compare", "{s}", "--model", "{d}/missing.csv"], 66, "no such params file"),
    (["compare", "{s}", "--model", "{d}/grip.csv", "--band", "3:1"], 2, "0 < LO < HI"),
    (["compare", "{s}", "--model", "{d}/grip.csv", "--level", "median"], 2, "grip fits"),
    (["diagnose", "{s}", "--model", "{d}/grip.csv", "--effect", "spring"], 2,
     "unknown effect 'spring'"),
    (["diagnose", "{d}/grip.csv", "--model", "{d}/grip.csv"], 65, "not a readable"),
])
def test_user_errors(runner, study, args, code, text):
    args = [a.format(s=study / "spectra.parquet", d=study) for a in args]
    res = runner.invoke(cli, args)
    assert res.exit_code == code, res.output
    assert text in res.stderr and "Traceback" not in res.stderr
