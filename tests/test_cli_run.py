"""`armfit run`: the whole pipeline on a small simulated study with a known hidden effect.

The study (made once per module with `armfit simulate`): 2 subjects × axes x and z × grips
1, 2, 3 N, 26 s trials at 1 kHz (the shortest that holds four 10 s derived-dynamics
segments at 0.1 Hz), seed 3, and a pure output delay of 12 ms on the z axis only. The
pipeline runs twice in the whole module: once with figures and --json (snapshotted to
memory), once more with --overwrite --no-figures into the same folder.
"""

from __future__ import annotations

import html
import io
import json
import re
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from click.testing import CliRunner

from armfit import __version__
from armfit.cli.main import cli
from armfit.diagnosis import BANDS
from armfit.models.params import model_from_params, read_params
from armfit.spectra import Spectra

TRUE_DELAY_S = 0.012  # the simulator's --effect delay=0.012 on z (its known truth)

#: Every file a run of this study must write (delay adopted on z: the base model's tables
#: kept as *_base).
TABLES = ("compare.csv", "grip_params.csv", "nominal_params.csv", "grip_params_base.csv",
          "nominal_params_base.csv", "adoption.csv", "wu.csv", "wu_summary.csv",
          "wu_wmax.csv", "trial_params.csv", "stability.csv", "certificate.csv")
EXPECTED = set(TABLES) | {
    "trials.parquet", "spectra.parquet", "grip_params.tex", "nominal_params.tex", "wu.tex",
    "grip_params_base.tex", "nominal_params_base.tex",
    "diagnosis.json", "report.md", "report.html", "figures/bode.png", "figures/uncertainty.png",
    "figures/literature.png", "figures/residual_x.png", "figures/residual_z.png",
    "figures/stability.png"}


def _invoke(*args: str):
    return CliRunner().invoke(cli, list(args))


def _snapshot(folder: Path) -> dict[str, bytes]:
    return {p.relative_to(folder).as_posix(): p.read_bytes()
            for p in sorted(folder.rglob("*")) if p.is_file()}


@pytest.fixture(scope="module")
def study(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("run")
    res = _invoke("simulate", "-o", str(root / "study"), "--subjects", "2", "--axes", "xz",
                  "--duration", "26,26", "--seed", "3", "--effect", f"delay={TRUE_DELAY_S}",
                  "--effect-axes", "z")
    assert res.exit_code == 0, res.output
    return root / "study"


@pytest.fixture(scope="module")
def first(study):
    """The first run (figures on, --json, 2 jobs): its result and every file's bytes."""
    out = study.parent / "out"
    res = _invoke("run", str(study), "-o", str(out), "--jobs", "2", "--json")
    assert res.exit_code == 0, res.stderr
    return res, _snapshot(out), out


@pytest.fixture(scope="module")
def second(first, study):
    """The same study again into the same folder: --overwrite --no-figures, 1 job."""
    _, _, out = first
    res = _invoke("run", str(study), "-o", str(out), "--overwrite", "--no-figures")
    assert res.exit_code == 0, res.stderr
    return res, _snapshot(out)


def test_run_writes_every_expected_file(first):
    res, files, out = first
    assert set(files) == EXPECTED
    doc = json.loads(res.stdout)
    # the --json summary lists exactly what is on disk
    assert sorted(doc["files"]) == sorted(files)
    assert doc["outdir"] == str(out) and doc["trials"] == 12  # 2 subjects x 2 axes x 3 grips
    for name in EXPECTED:
        if name.endswith(".png"):
            assert files[name][:8] == b"\x89PNG\r\n\x1a\n"  # the PNG signature (RFC 2083)
    # nothing but OUTDIR was left beside it (no temporary folder)
    assert sorted(p.name for p in out.parent.iterdir()) == ["out", "study", "study.truth.json"]


def test_stage_lines_and_json_timings(first):
    res, _, _ = first
    stages = ["ingest", "estimate", "fit-grip", "fit-nominal", "diagnose", "adopt",
              "fit-uncertainty", "fit-trials", "stability", "figures", "compare",
              "residuals", "drawing", "report"]
    lines = [ln for ln in res.stderr.splitlines()
             if re.match(r"^[a-z-]+: \d+\.\d s — ", ln)]
    assert [ln.split(":")[0] for ln in lines] == stages
    doc = json.loads(res.stdout)
    assert list(doc["timings_s"]) == stages
    assert all(v >= 0 for v in doc["timings_s"].values()) and doc["total_s"] > 0
    # the stages' times add up to the total (each from the end of the stage before), to
    # the rounding of 14 values to 1 ms and the instants between the last stage and the end
    assert abs(sum(doc["timings_s"].values()) - doc["total_s"]) < 0.05


def test_diagnosis_names_the_simulated_effect_and_adopts_it(first):
    res, files, _ = first
    doc = json.loads(res.stdout)
    # simulator's truth: a delay on z only, the paper's model on x
    assert doc["diagnosis"]["z"]["missing_effect"] == "delay"
    assert doc["diagnosis"]["x"]["missing_effect"] is None
    assert doc["refitted"] == {"delay": ["z"]}
    assert doc["adoption"]["axes"]["z"]["effects"] == ["delay"]
    assert doc["adoption"]["axes"]["x"]["effects"] == []
    diag = json.loads(files["diagnosis.json"])
    assert {a: d["verdict"] for a, d in diag["axes"].items()} == \
        {a: d["verdict"] for a, d in doc["diagnosis"].items()}
    adopted = pd.read_csv(io.BytesIO(files["nominal_params.csv"]), keep_default_na=False)
    z = adopted[adopted["axis"] == "z"].iloc[0]
    x = adopted[adopted["axis"] == "x"].iloc[0]
    assert z["effects"] == "delay" and x["effects"] == ""
    # the delay is held at the diagnosis's joint fit, which recovers the simulated 12 ms
    # within 10 %: a delay is 2*pi*f*tau rad of phase, 130 deg at 30 Hz, against a phase
    # noise of a few degrees per grid point
    joint = diag["axes"]["z"]["missing_effects"][0]["params"]["delay_s"]
    assert float(z["delay.delay_s"]) == pytest.approx(joint, rel=1e-9)
    assert joint == pytest.approx(TRUE_DELAY_S, rel=0.10)
    assert z["held"] == "delay.delay_s"
    # fitted over the band the diagnosis used (the whole grid), not the paper's z band
    assert float(z["band_hi_hz"]) == pytest.approx(diag["axes"]["z"]["band_hz"][1])
    # every trial of z carries the same held delay; x's trials the base model
    trials = pd.read_csv(io.BytesIO(files["trial_params.csv"]), keep_default_na=False)
    tz = trials[trials["axis"] == "z"]
    assert (tz["effects"] == "delay").all()
    assert np.allclose(tz["delay.delay_s"].astype(float), joint, rtol=1e-9)
    assert (trials[trials["axis"] == "x"]["effects"] == "").all()
    # the base model's tables are the paper's 5-parameter model
    base = pd.read_csv(io.BytesIO(files["nominal_params_base.csv"]), keep_default_na=False)
    assert set(base["effects"]) == {""}


def test_compare_csv_matches_the_residuals_of_the_nominal_models(first):
    _, _, out = first
    comp = pd.read_csv(out / "compare.csv", keep_default_na=False)
    assert list(comp.columns) == ["axis", "grip", "level", "model", "band", "rms_db",
                                  "rms_deg", "rms_norm"]
    bands = ["overall"] + [f"{lo:g}-{hi:g}" for lo, hi in BANDS]
    keys = list(zip(comp["axis"], comp["model"], comp["band"], strict=True))
    assert keys == ([("x", "base", b) for b in bands] + [("z", "base", b) for b in bands]
                    + [("z", "base+delay", b) for b in bands])
    assert set(comp["level"]) == {"median"} and set(comp["grip"]) == {""}
    # analytic check of the overall rows: RMS over the row's fit band (band_lo_hz to
    # band_hi_hz, stored to 10 digits) of 20 log10|H_med / H_CL| (dB) and of
    # angle(H_med / H_CL) (deg), H_CL of eq. 4 at the row's parameters
    spectra = Spectra.read(out / "spectra.parquet").to_frame()
    for axis, model_file in (("x", "nominal_params_base.csv"),
                             ("z", "nominal_params_base.csv"), ("z", "nominal_params.csv")):
        row = read_params(out / model_file).set_index("axis").loc[axis]
        model, theta = model_from_params({**row.to_dict(), "axis": axis})
        med = spectra[(spectra["level"] == "median") & (spectra["kind"] == "measured")
                      & (spectra["axis"] == axis)].sort_values("freq_hz")
        f = med["freq_hz"].to_numpy()
        med = med[(f >= row["band_lo_hz"] * (1 - 1e-9)) & (f <= row["band_hi_hz"] * (1 + 1e-9))]
        h = med["re"].to_numpy() + 1j * med["im"].to_numpy()
        ratio = h / model.response(med["freq_hz"].to_numpy(), theta)
        rms_db = np.sqrt(np.mean((20 * np.log10(np.abs(ratio))) ** 2))
        rms_deg = np.sqrt(np.mean(np.degrees(np.angle(ratio)) ** 2))
        label = "base" if model_file == "nominal_params_base.csv" else "base+delay"
        got = comp[(comp["axis"] == axis) & (comp["model"] == label)
                   & (comp["band"] == "overall")].iloc[0]
        # CSV keeps 10 significant digits
        assert got["rms_db"] == pytest.approx(rms_db, rel=1e-8)
        assert got["rms_deg"] == pytest.approx(rms_deg, rel=1e-8)
        # ... and its "× noise" is the params file's: the same noise model on the same bins
        assert got["rms_norm"] == pytest.approx(float(row["rms_norm"]), rel=1e-8)
    # with the true effect modelled the error goes where a delay shows most, 10-30 Hz
    # (the base model's overall row covers only its fit band below 10 Hz): at least halved
    z = comp[(comp["axis"] == "z") & (comp["band"] == "10-30")].set_index("model")
    assert z.loc["base+delay", "rms_norm"] < 0.5 * z.loc["base", "rms_norm"]


def test_tables_equal_those_of_the_subcommands(first, tmp_path):
    """The pipeline's tables are byte-identical to fit-grip / fit-nominal /
    fit-uncertainty run by hand on the spectra it wrote: the base tables without
    effects, the adopted ones with the delay held on z at the value adoption.csv
    records, over the diagnosis's band."""
    _, files, out = first
    spectra = str(out / "spectra.parquet")
    adoption = pd.read_csv(out / "adoption.csv", keep_default_na=False).set_index("axis")
    held = adoption.loc["z", "held"]            # "delay.delay_s=<value>"
    value = held.split("=", 1)[1]
    effect = ["--effect", f"z:delay={value}", "--band", "z=0.1:30"]
    for args, written in (
            (["fit-grip", spectra, "-o", str(tmp_path / "g.csv")],
             {"g.csv": "grip_params_base.csv"}),
            (["fit-nominal", spectra, "-o", str(tmp_path / "n.csv")],
             {"n.csv": "nominal_params_base.csv"}),
            (["fit-grip", spectra, "-o", str(tmp_path / "ga.csv"), *effect],
             {"ga.csv": "grip_params.csv"}),
            (["fit-nominal", spectra, "-o", str(tmp_path / "na.csv"), *effect],
             {"na.csv": "nominal_params.csv"}),
            (["fit-uncertainty", spectra, "--nominal", str(out / "nominal_params.csv"), "-o",
              str(tmp_path / "wu.csv")],
             {"wu.csv": "wu.csv", "wu_summary.csv": "wu_summary.csv",
              "wu_wmax.csv": "wu_wmax.csv"})):
        res = _invoke(*args)
        assert res.exit_code == 0, res.stderr
        for mine, theirs in (written or {}).items():
            assert (tmp_path / mine).read_bytes() == files[theirs], theirs


def test_trial_fits_and_stability_equal_those_of_the_subcommands(first, tmp_path):
    """trial_params.csv is `armfit fit-trials` on the run's spectra, stability.csv is
    `armfit stability trial_params.csv` at the defaults (byte for byte), and the report
    states the population minimum of K_max per axis as a sentence."""
    _, files, out = first
    adoption = pd.read_csv(out / "adoption.csv", keep_default_na=False).set_index("axis")
    value = adoption.loc["z", "held"].split("=", 1)[1]
    res = _invoke("fit-trials", str(out / "spectra.parquet"), "-o", str(tmp_path / "t.csv"),
                  "--effect", f"z:delay={value}", "--band", "z=0.1:30")
    assert res.exit_code == 0, res.stderr
    assert (tmp_path / "t.csv").read_bytes() == files["trial_params.csv"]
    res = _invoke("stability", str(out / "trial_params.csv"), "-o", str(tmp_path / "s.csv"))
    assert res.exit_code == 0, res.stderr
    assert (tmp_path / "s.csv").read_bytes() == files["stability.csv"]
    table = pd.read_csv(io.BytesIO(files["stability.csv"]))
    assert len(table) == 12
    report = files["report.md"].decode()
    for axis in ("x", "z"):
        kmin = table.loc[table["axis"] == axis, "k_max_N_per_m"].min()
        assert (f"A 1 kHz device with 1 sample(s) of delay renders walls up to "
                f"{kmin / 1e3:.3g} kN/m on {axis.upper()} for every subject") in report


def test_report_states_every_stage_and_the_diagnosis(first):
    _, files, _ = first
    report = files["report.md"].decode()
    diag = json.loads(files["diagnosis.json"])
    assert f"armfit {__version__}" in report
    for stage in ("ingest", "estimate", "fit-grip", "fit-nominal", "fit-uncertainty",
                  "diagnose", "adopt", "fit-trials", "stability", "compare", "figures"):
        assert f"**{stage}**" in report
    for heading in ("Table I", "Table II", "Table III", "## Diagnosis", "### Axis X",
                    "### Axis Z"):
        assert heading in report
    for d in diag["axes"].values():
        assert f"**Verdict:** {d['verdict']}." in report
        for fb in d["failing_bands"]:
            assert fb["description"] in report
    # the stepwise table: the base model's row, then the delay's, with their errors
    z = diag["axes"]["z"]
    assert "Stepwise search" in report
    for i, st in enumerate(z["steps"]):
        assert (f"| {i} | {st['effect'] or 'base model'} |") in report
        assert f"| {st['rms_db']:.2f} | {st['rms_deg']:.1f} | {st['rms_norm']:.2f} |" in report
    for fig in (f for f in EXPECTED if f.startswith("figures/")):
        assert f"]({fig})" in report
    # it opens with the adopted model: delay on z, x the base model
    head = report[:report.index("## What was done")]
    assert "## Adopted model" in head
    assert "Z: adopted delay" in head and "X: base model (nothing adopted)" in head
    assert "`nominal_params_base.csv`" in report
    # deterministic: no timings or dates in the report
    assert not re.search(r"\d+\.\d+ s\b|\b20\d\d-\d\d-\d\d", report)


def test_second_run_gives_identical_tables_and_no_figures(first, second):
    _, files1, _ = first
    res, files2 = second
    for name in (*TABLES, "grip_params.tex", "nominal_params.tex", "wu.tex",
                 "grip_params_base.tex", "nominal_params_base.tex",
                 "diagnosis.json", "spectra.parquet", "trials.parquet"):
        assert files2[name] == files1[name], name
    # --no-figures: the replaced folder has no figures (it was replaced, not merged)
    assert set(files2) == EXPECTED - {f for f in EXPECTED if f.startswith("figures/")}
    report = files2["report.md"].decode()
    assert "skipped (`--no-figures`)" in report and "](figures/" not in report
    assert "residuals:" not in res.stderr and "figures:" not in res.stderr


def test_existing_outdir_is_refused_without_overwrite(study, tmp_path):
    out = tmp_path / "results"
    out.mkdir()
    (out / "keep.txt").write_text("mine")
    res = _invoke("run", str(study), "-o", str(out))
    assert res.exit_code == 73
    assert res.stderr.strip() == f"armfit: error: {out}: exists; pass --overwrite to replace it"
    assert (out / "keep.txt").read_text() == "mine"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["results"]


def test_outdir_holding_the_input_is_refused_even_with_overwrite(study, tmp_path):
    res = _invoke("run", str(study), "-o", str(study.parent), "--overwrite")
    assert res.exit_code == 73
    assert "holds the input" in res.stderr and "Traceback" not in res.stderr
    assert study.is_dir() and len(list(study.iterdir())) == 12


def test_too_short_trials_exit_65_and_leave_no_outdir(tmp_path):
    """20 s trials pass ingest (2/0.1 Hz = 20 s) but are too short for the derived
    dynamics' four 10 s segments: the run fails in the estimate stage, after ingest has
    written trials.parquet into the temporary folder, and leaves nothing behind."""
    study = tmp_path / "short"
    res = _invoke("simulate", "-o", str(study), "--subjects", "1", "--axes", "x",
                  "--grips", "1", "--duration", "20,20", "--seed", "4")
    assert res.exit_code == 0, res.output
    before = sorted(p.name for p in tmp_path.iterdir())
    res = _invoke("run", str(study), "-o", str(tmp_path / "out"))
    assert res.exit_code == 65
    assert res.stderr.startswith("ingest: ")  # the first stage had finished
    last = res.stderr.strip().splitlines()[-1]
    assert last.startswith(f"armfit: error: {study / 'sub-01_axis-x_grip-1N.parquet'}: too "
                           "short")
    assert sorted(p.name for p in tmp_path.iterdir()) == before


def test_bad_cell_exits_65_naming_file_column_row(tmp_path, write_trial, make_columns):
    cols = make_columns("x", fs=1000.0, duration_s=26.0)
    force = [repr(float(v)) for v in cols["force_x_N"]]
    force[4] = "n/a"  # data row 5
    cols["force_x_N"] = force
    bad = write_trial(tmp_path / "raw" / "sub-01_axis-x_grip-1N.csv", cols)
    res = _invoke("run", str(tmp_path / "raw"), "-o", str(tmp_path / "out"))
    assert res.exit_code == 65
    msg = res.stderr.strip().splitlines()[-1]
    assert msg.startswith(f"armfit: error: {bad}, column 'force_x_N', row 5: ")
    assert not (tmp_path / "out").exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["raw"]


def test_all_trials_bad_with_skip_bad_names_outdir_not_a_temporary(tmp_path, write_trial,
                                                                     make_columns):
    cols = make_columns("x", fs=1000.0, duration_s=26.0)
    cols["force_x_N"] = [repr(float(v)) for v in cols["force_x_N"]]
    cols["force_x_N"][1] = "abc"  # data row 2
    bad = write_trial(tmp_path / "raw" / "sub-01_axis-x_grip-1N.csv", cols)
    out = tmp_path / "out"
    res = _invoke("run", str(tmp_path / "raw"), "-o", str(out), "--skip-bad")
    assert res.exit_code == 65
    assert res.stderr.strip().splitlines()[-1] == (
        f"armfit: error: {out / 'trials.parquet'}: every trial was bad (1 skipped, the "
        f"first {bad}: column 'force_x_N', row 2: non-numeric value 'abc'; expected a "
        "number); nothing written")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["raw"]


def test_a_trial_ingest_skips_is_left_out_of_the_spectra_too(study, tmp_path):
    # with --skip-bad, a trial whose grip column holds an infinite value is left out by
    # ingest's read (an estimate reading the file itself does not check the grip
    # column): run estimates the trials ingest read, so spectra.parquet holds exactly
    # the trials trials.parquet holds, and the trial is listed once among the skipped
    import pyarrow as pa
    import pyarrow.parquet as pq

    from armfit.io.trials import dataset_sources
    raw = tmp_path / "raw"
    shutil.copytree(study, raw)
    files = sorted(raw.glob("*.parquet"))
    bad = files[1]
    table = pq.read_table(bad)
    grip = table.column("grip_N").to_numpy().copy()
    grip[5] = np.inf
    table = table.set_column(table.schema.get_field_index("grip_N"), "grip_N",
                             pa.array(grip))
    pq.write_table(table, bad)
    out = tmp_path / "out"
    res = _invoke("run", str(raw), "-o", str(out), "--skip-bad", "--no-figures", "--jobs",
                  "2", "--json")
    assert res.exit_code == 0, res.stderr
    got = json.loads(res.stdout)
    assert [s["file"] for s in got["skipped"]] == [str(bad)]
    keys = Spectra.read(out / "spectra.parquet", level="trial").keys
    estimated = set(zip(keys["subject"], keys["axis"], keys["grip_N"], strict=True))
    ingested = {(s.subject, s.axis, s.grip_N) for s in dataset_sources(out / "trials.parquet")}
    assert estimated == ingested and got["trials"] == len(ingested) == len(files) - 1


def test_no_input_is_a_usage_error(tmp_path):
    res = _invoke("run", "-o", str(tmp_path / "out"))
    assert res.exit_code == 2 and "give trial files" in res.stderr
    assert not (tmp_path / "out").exists()


def test_help_lists_the_pipelines_stages_in_order():
    """`armfit run --help` names the stages the pipeline runs (armfit.pipeline.STAGES), in
    their order, so the help cannot drift from the code."""
    from armfit.pipeline import STAGES
    r = CliRunner().invoke(cli, ["run", "--help"], terminal_width=200)
    assert r.exit_code == 0
    text = " ".join(r.output.split())
    listed = text.split("Stages, in order: ", 1)[1].split(".", 1)[0]
    assert [s.strip() for s in listed.split(",")] == list(STAGES)


@pytest.mark.skipif(shutil.which("chromium") is None, reason="Chromium not installed")
def test_report_html_loads_in_a_browser_without_errors_and_every_image_decodes(first,
                                                                                tmp_path):
    """report.html in headless Chromium (Debian's chromium): no console error, no script
    error, and every <img> loaded and decoded (naturalWidth > 0 once the page has loaded);
    as many images as report.md's figures. The page is checked through a copy with a probe
    script appended (report.html itself holds no script)."""
    _, files, _ = first
    page = files["report.html"].decode()
    assert "<script" not in page
    probe = """<script>
window.__errors = [];
window.addEventListener("error", e => window.__errors.push(String(e.message)), true);
window.addEventListener("load", () => {
  // after "load" every image has been fetched and decoded, or failed (naturalWidth 0)
  const w = [...document.images].map(i => (i.complete ? i.naturalWidth : 0));
  const out = document.createElement("pre");
  out.id = "probe";
  out.textContent = JSON.stringify({images: w, errors: window.__errors});
  document.body.appendChild(out);
});
</script>"""
    checked = tmp_path / "report.html"
    checked.write_text(page.replace("<body>", "<body>" + probe, 1))
    proc = subprocess.run(
        ["chromium", "--headless", "--no-sandbox", "--disable-gpu", "--enable-logging=stderr",
         "--v=0", "--virtual-time-budget=20000", "--dump-dom", checked.as_uri()],
        capture_output=True, text=True, timeout=180)
    found = re.search(r'<pre id="probe">(.*?)</pre>', proc.stdout, re.S)
    assert found, proc.stderr[-2000:]
    probe_out = json.loads(html.unescape(found.group(1)))
    n_figures = files["report.md"].decode().count("](figures/")
    # Figs. 5-7, the residuals of the two axes simulated (x, z) and the stability figure
    assert len(probe_out["images"]) == n_figures == 6
    assert all(w > 0 for w in probe_out["images"]), probe_out
    assert probe_out["errors"] == []
    console_errors = [ln for ln in proc.stderr.splitlines()
                      if "CONSOLE" in ln and checked.as_uri() in ln]
    assert console_errors == []
