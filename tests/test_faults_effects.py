"""A user's effect code that misbehaves while armfit runs it: a term that is NaN between
the probe frequencies of the registration check, a term (or rational form) that raises,
and a file that prints on stdout — through the command line (``-j 1`` and ``-j 2``) and
the API.

Expected values come from the contract: the exit codes of armfit.errors (65 bad input,
also for an effects file whose code is wrong, docs/cli.md "Conventions"), the one-line
message naming the file, the effect and the exception (docs/methods.md, "Your own
effects"), ``--json`` on stdout holding only armfit's document, and the diagnosis
leaving a failed candidate out with its reason while the search goes on
(docs/formats.md, "Diagnosis JSON"). The frequency where the test effect is NaN is the
first bin of the spectra grid in its NaN band (3–4 Hz), read from the spectra file.
"""

from __future__ import annotations

import json
import sys
import textwrap
import threading
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

import armfit
from armfit.cli.main import cli
from armfit.errors import EXIT_DATAERR, EffectDefinitionError
from armfit.models.arm import ClosedLoopModel, Param
from armfit.models.effects import EFFECTS, PROBE_HZ, Effect, load_effect_file
from armfit.spectra import Spectra

HEADER = textwrap.dedent("""\
    import multiprocessing
    import numpy as np
    from armfit import Effect, Param
    from armfit.models.effects import PROBE_HZ


    def _off_probe(s):
        # True where s is not one of the registration check's probe frequencies
        f = np.abs(s) / (2 * np.pi)
        return ~np.isclose(f[..., None], PROBE_HZ, rtol=1e-9, atol=0.0).any(axis=-1)


    def _in_worker():
        return multiprocessing.current_process().name != "MainProcess"

    """)

#: Term bodies (``s``, ``values``): a device spring k, with a fault.
TERMS = {
    # a spring: the control
    "spring": "return values['k'] + 0.0 * s",
    # NaN between 3 and 4 Hz, except at the probe frequencies the loader checks
    "sneaky": ("f = np.abs(s) / (2 * np.pi)\n"
               "bad = (f > 3.0) & (f < 4.0) & _off_probe(s)\n"
               "return np.where(bad, np.nan, values['k'] + 0.0 * s)"),
    # the same, only in a worker process
    "sneaky-worker": ("f = np.abs(s) / (2 * np.pi)\n"
                      "bad = (f > 3.0) & (f < 4.0) & _off_probe(s) & _in_worker()\n"
                      "return np.where(bad, np.nan, values['k'] + 0.0 * s)"),
    # raises on any grid but the probe grid
    "raiser": ("if _off_probe(s).any():\n"
               "    return 1 / 0\n"
               "return values['k'] + 0.0 * s"),
    # the same, only in a worker process
    "raiser-worker": ("if _off_probe(s).any() and _in_worker():\n"
                      "    raise KeyError('stiffness')\n"
                      "return values['k'] + 0.0 * s"),
    # prints whenever it runs
    "printer": ("print('printed by the term')\n"
                "return values['k'] + 0.0 * s"),
}


def effect_file(path: Path, *names: str, kinds: tuple[str, ...] = (), prelude: str = "",
                rational: str | None = None) -> Path:
    """A user's effects file at ``path``: one device spring per name, each with the term
    of :data:`TERMS` ``kinds[i]`` (default: the name itself); ``prelude`` runs at import;
    ``rational`` the body of each effect's rational form (``values``, ``mp``)."""
    kinds = kinds or names
    parts = [HEADER, prelude, "\nEFFECTS = []\n"]
    for i, (name, kind) in enumerate(zip(names, kinds, strict=True)):
        extra = ""
        if rational is not None:
            parts.append(f"\ndef _rational{i}(values, mp):\n"
                         + textwrap.indent(rational, "    ") + "\n")
            extra = f", rational=_rational{i}"
        parts.append(f"\ndef _term{i}(s, values, mp):\n"
                     + textwrap.indent(TERMS[kind], "    ") + "\n")
        parts.append(f"EFFECTS.append(Effect(name={name!r}, stage='device', params=("
                     "Param('k', 'N/m', 0.01, 5000.0, 50.0, 'spring'),), "
                     f"term=_term{i}, null=(0.01,), summary='test'{extra}))\n")
    path.write_text("".join(parts))
    return path


def invoke(*args):
    result = CliRunner().invoke(cli, [str(a) for a in args])
    return result.exit_code, result.stdout, result.stderr


def one_line(err: str) -> str:
    """The only line on stderr (no traceback)."""
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert "Traceback" not in err and len(lines) == 1, err
    return lines[0]


@pytest.fixture(scope="module")
def study(tmp_path_factory, serial_spectra):
    """The small simulated study's spectra file and its grip fits (base model)."""
    root = tmp_path_factory.mktemp("effect-faults")
    serial_spectra.write(root / "spectra.parquet")
    armfit.fit_grip(serial_spectra).write(root / "grip.csv")
    return root


@pytest.fixture(scope="module")
def nan_hz(serial_spectra) -> float:
    """The first frequency of the spectra grid inside the sneaky term's NaN band."""
    f = np.unique(Spectra.of(serial_spectra).to_frame()["freq_hz"].to_numpy(float))
    return float(f[(f > 3.0) & (f < 4.0)][0])


def _nan_message(path: Path, name: str, hz: float) -> str:
    # the message of Effect.evaluate: file, effect, where (the effect's k there varies)
    return f"{path}: effect '{name}' is NaN at {hz:.4g} Hz (k="


# ---------------------------------------------------------------------------
# A term that is NaN between the probe frequencies
# ---------------------------------------------------------------------------

@pytest.mark.parametrize("command", ["fit-nominal", "fit-grip"])
def test_nan_term_between_probe_frequencies_is_refused(study, tmp_path, nan_hz, command):
    """The effect loads (finite on the probe grid), yet is NaN at a bin of the fitted
    band: exit 65 naming the file and the effect, no params file written (before: exit
    0, a fit marked converged with rms NaN)."""
    f = effect_file(tmp_path / "sneaky.py", "sneaky")
    out = tmp_path / "params.csv"
    code, stdout, err = invoke(command, study / "spectra.parquet", "-o", out,
                               "--effects", f, "--effect", "sneaky", "--json")
    assert code == EXIT_DATAERR, err
    assert one_line(err).startswith("armfit: error: " + _nan_message(f, "sneaky", nan_hz))
    assert stdout == "" and not out.exists()
    assert "sneaky" not in EFFECTS


def test_nan_term_in_worker_processes_is_refused(study, tmp_path, nan_hz):
    """fit-trials -j 2: the term is NaN only in the worker processes (the grip fits that
    start the trials run here and succeed), and the error crosses the process boundary
    as exit 65 with the same line; -j 1 with a term NaN everywhere, likewise (before:
    exit 0 with NaN fits)."""
    f = effect_file(tmp_path / "sneaky_worker.py", "sneaky", kinds=("sneaky-worker",))
    code, _, err = invoke("fit-trials", study / "spectra.parquet", "-o", tmp_path / "t.csv",
                          "--effects", f, "--effect", "sneaky", "-j", "2")
    assert code == EXIT_DATAERR, err
    assert one_line(err).startswith("armfit: error: " + _nan_message(f, "sneaky", nan_hz))
    g = effect_file(tmp_path / "sneaky.py", "sneaky")
    code, _, err = invoke("fit-trials", study / "spectra.parquet", "-o", tmp_path / "t.csv",
                          "--effects", g, "--effect", "sneaky", "-j", "1")
    assert code == EXIT_DATAERR, err
    assert one_line(err).startswith("armfit: error: " + _nan_message(g, "sneaky", nan_hz))
    assert not (tmp_path / "t.csv").exists()


def test_every_evaluation_of_the_model_refuses_a_nan_term(tmp_path, serial_spectra, nan_hz):
    """The one check sits where every model evaluates its effects (Effect.evaluate):
    the fitters, the response, the arm's response, the effects removed from data and
    from a derived arm all raise the same error; a NaN parameter value is not the term's
    fault (its response is NaN, as without effects)."""
    f = effect_file(tmp_path / "sneaky.py", "sneaky")
    (e,) = load_effect_file(f)
    try:
        with pytest.raises(EffectDefinitionError) as info:
            armfit.fit_nominal(serial_spectra, effects=["sneaky"])
        assert str(info.value).startswith(_nan_message(f, "sneaky", nan_hz))
        assert info.value.exit_code == EXIT_DATAERR
        m = ClosedLoopModel.for_axis("x", [e])
        theta = {"Ma": 0.3, "k1": 100.0, "k2": 500.0, "b1": 7.0, "b2": 5.0, "sneaky.k": 20.0}
        grid = np.array([1.0, nan_hz, 10.0])
        calls = [lambda: m.response(grid, theta), lambda: m.arm_response(grid, theta),
                 lambda: m.derived_arm_response(grid, theta),
                 lambda: m.remove_effects(grid, np.ones(3), {"sneaky.k": 20.0}),
                 lambda: m.arm_from_derived(grid, np.ones(3), theta)]
        for call in calls[:1] + calls[2:]:    # arm_response leaves device effects out
            with pytest.raises(EffectDefinitionError, match=r"is NaN at .* \(k=20\)"):
                call()
        assert np.all(np.isfinite(calls[1]()))
        # finite at the probe frequencies: the loader's check passed
        assert np.all(np.isfinite(m.response(PROBE_HZ, theta)))
        with np.errstate(all="ignore"):
            h = m.response(grid, {**theta, "sneaky.k": np.nan})
        assert np.all(np.isnan(h))
    finally:
        EFFECTS.unregister(["sneaky"])


def test_compare_and_fit_uncertainty_refuse_a_nan_term(study, tmp_path, serial_spectra,
                                                        nan_hz):
    """A params file fitted with a sound effect, read again with a file whose effect of
    the same name is NaN in the band: compare and fit-uncertainty exit 65 naming it
    (before: exit 0 with NaN errors and weights)."""
    good = effect_file(tmp_path / "good.py", "lab-spring", kinds=("spring",))
    load_effect_file(good)
    try:
        armfit.fit_nominal(serial_spectra, effects=["lab-spring"]).write(
            tmp_path / "nominal.csv")
    finally:
        EFFECTS.unregister(["lab-spring"])
    bad = effect_file(tmp_path / "bad.py", "lab-spring", kinds=("sneaky",))
    for args in (["compare", study / "spectra.parquet", "--model", tmp_path / "nominal.csv",
                  "--json"],
                 ["fit-uncertainty", study / "spectra.parquet", "--nominal",
                  tmp_path / "nominal.csv", "-o", tmp_path / "wu.csv"]):
        code, stdout, err = invoke(*args, "--effects", bad)
        assert code == EXIT_DATAERR, (args[0], err)
        assert one_line(err).startswith(
            "armfit: error: " + _nan_message(bad, "lab-spring", nan_hz)), args[0]
        assert stdout == ""
    assert not (tmp_path / "wu.csv").exists()


def test_diagnose_leaves_a_failing_candidate_out_and_goes_on(study, tmp_path, nan_hz):
    """diagnose with candidates that break (a NaN term, a raising term) and a sound one
    (delay): the broken ones are left out with their reason, the search goes on with
    delay, exit 0; -j 1 and -j 2 give the same document (before: the NaN candidate was
    fitted to NaN errors, the raising one ended the command with exit 1)."""
    f = effect_file(tmp_path / "broken.py", "sneaky", "raiser")
    args = ["diagnose", study / "spectra.parquet", "--model", study / "grip.csv",
            "--effects", f, "--effect", "sneaky", "--effect", "raiser", "--effect", "delay",
            "--max-steps", "1"]
    code, text, err = invoke(*args, "-j", "1", "-o", tmp_path / "d1.json")
    assert code == 0, err
    assert f"candidate sneaky left out: {_nan_message(f, 'sneaky', nan_hz)}" in text
    code, stdout, err = invoke(*args, "-j", "2", "--json")
    assert code == 0, err
    doc = json.loads(stdout)
    assert doc == json.loads((tmp_path / "d1.json").read_text())
    axis = doc["axes"]["x"]
    failed = {c["effect"]: c["reason"] for c in axis["failed_candidates"]}
    assert list(failed) == ["sneaky", "raiser"]
    assert failed["sneaky"].startswith(_nan_message(f, "sneaky", nan_hz))
    assert failed["raiser"] == (f"{f}: effect 'raiser' raised ZeroDivisionError: "
                                "division by zero (in its term)")
    assert [c["effect"] for c in axis["candidates"]] == ["delay"]


# ---------------------------------------------------------------------------
# A term (or rational form) that raises
# ---------------------------------------------------------------------------

def test_raising_term_during_a_fit_is_one_line_exit_65(study, tmp_path):
    """The user's term raises during the fit (not at load): exit 65, one line naming the
    file, the effect and the exception (before: exit 1, "internal error"); with -v the
    traceback shows the user's line."""
    f = effect_file(tmp_path / "raiser.py", "raiser")
    args = ["fit-nominal", study / "spectra.parquet", "-o", tmp_path / "p.csv",
            "--effects", f, "--effect", "raiser"]
    code, _, err = invoke(*args)
    assert code == EXIT_DATAERR, err
    assert one_line(err) == (f"armfit: error: {f}: effect 'raiser' raised "
                             "ZeroDivisionError: division by zero (in its term)")
    code, _, err = invoke("-v", *args)
    assert code == EXIT_DATAERR
    assert "Traceback" in err and f'File "{f}"' in err and "return 1 / 0" in err
    assert err.strip().splitlines()[-1].startswith(f"armfit: error: {f}: effect 'raiser'")
    assert not (tmp_path / "p.csv").exists()


def test_raising_term_in_worker_processes_is_one_line_exit_65(study, tmp_path,
                                                              monkeypatch):
    """fit-trials -j 2: the term raises only in the worker processes; the error reaches
    the command line as exit 65 and one line naming the file as it was given (the
    workers load it by its absolute path)."""
    f = effect_file(tmp_path / "raiser_worker.py", "raiser", kinds=("raiser-worker",))
    rel = Path(f.name)
    monkeypatch.chdir(tmp_path)
    result = CliRunner().invoke(cli, ["fit-trials", str(study / "spectra.parquet"), "-o",
                                      "t.csv", "--effects", str(rel), "--effect", "raiser",
                                      "-j", "2"])
    assert result.exit_code == EXIT_DATAERR, result.stderr
    assert one_line(result.stderr) == (f"armfit: error: {rel}: effect 'raiser' raised "
                                       "KeyError: 'stiffness' (in its term)")


def test_raising_term_at_load_shows_the_users_line_with_v(tmp_path):
    """A term that raises in the registration check: exit 65 and one line as before;
    with -v the traceback reaches the user's own line (before: cut off above it)."""
    f = tmp_path / "load_raiser.py"
    f.write_text(HEADER + textwrap.dedent("""\
        def _term(s, values, mp):
            return values["stiffness"] + 0.0 * s

        EFFECTS = [Effect(name="load-raiser", stage="device",
                          params=(Param("k", "N/m", 0.01, 5000.0, 50.0, "spring"),),
                          term=_term, null=(0.01,))]
        """))
    code, _, err = invoke("effects", "--effects", f)
    assert code == EXIT_DATAERR
    assert one_line(err) == (f"armfit: error: {f}: effect 'load-raiser' raised KeyError: "
                             "'stiffness' (in its term, at the typical values)")
    code, _, err = invoke("-v", "effects", "--effects", f)
    assert code == EXIT_DATAERR
    assert f'File "{f}"' in err and 'return values["stiffness"]' in err


def test_raising_rational_form_at_stability_names_the_file(tmp_path, serial_spectra):
    """The rational form passes at the values the loader checks but raises at the value
    the params file holds (stability is the only user of it): exit 65, one line naming
    the file (before: the effect only, not where it was defined)."""
    # raises unless k is one of the values the registration check uses (typical, null)
    rational = ("if values['k'] not in (50.0, 0.01):\n"
                "    raise ValueError('no form for this k')\n"
                "return values['k'], 1.0")
    good = effect_file(tmp_path / "spring.py", "lab-spring", kinds=("spring",),
                       rational=rational)
    load_effect_file(good)
    try:
        armfit.fit_nominal(serial_spectra, effects=["lab-spring=20"]).write(
            tmp_path / "nominal.csv")        # held at k = 20 N/m
    finally:
        EFFECTS.unregister(["lab-spring"])
    code, _, err = invoke("stability", tmp_path / "nominal.csv", "--effects", good,
                          "-o", tmp_path / "k.csv")
    assert code == EXIT_DATAERR, err
    assert one_line(err) == (f"armfit: error: {good}: effect 'lab-spring' raised "
                             "ValueError: no form for this k (in its rational)")


def _api_raiser(s, values, mp):
    if np.size(s) != PROBE_HZ.size:      # any grid but the registration check's
        raise ZeroDivisionError("from the API")
    return values["k"] + 0.0 * s


def test_raising_term_of_an_effect_made_in_python_names_its_source(serial_spectra):
    """An Effect built in a script (not registered from a file) that raises during a fit:
    EffectDefinitionError (exit 65) naming the file of its term, this test file (before:
    the bare ZeroDivisionError)."""
    e = Effect(name="api-raiser", stage="device",
               params=(Param("k", "N/m", 0.01, 5000.0, 50.0, "spring"),),
               term=_api_raiser, null=(0.01,))
    with pytest.raises(EffectDefinitionError) as info:
        armfit.fit_nominal(serial_spectra, effects=[e])
    assert str(info.value) == (f"{__file__}: effect 'api-raiser' raised ZeroDivisionError: "
                               "from the API (in its term)")
    assert isinstance(info.value.__cause__, ZeroDivisionError)


# ---------------------------------------------------------------------------
# A file that prints on stdout
# ---------------------------------------------------------------------------

PRINTS = "print('printed while loading')\n"


@pytest.mark.parametrize("jobs", ["1", "2"])
def test_prints_of_an_effects_file_leave_json_on_stdout_intact(study, tmp_path, jobs):
    """fit-trials --json with an effects file that prints at import and in its term,
    run here (-j 1) and in worker processes (-j 2): stdout is the JSON document alone,
    the prints go to stderr (before: they came first on stdout and broke the JSON)."""
    f = effect_file(tmp_path / "printer.py", "printer", prelude=PRINTS)
    code, stdout, err = invoke("fit-trials", study / "spectra.parquet", "-o",
                               tmp_path / "t.csv", "--effects", f, "--effect", "printer",
                               "-j", jobs, "--json")
    assert code == 0, err
    doc = json.loads(stdout)
    assert doc["command"] == "fit-trials" and len(doc["fits"]) == 4   # 2 subjects × 2 grips
    assert "printed" not in stdout
    assert "printed while loading" in err and "printed by the term" in err


def test_prints_in_diagnose_and_fit_nominal_json(study, tmp_path):
    """diagnose --json -j 2 (candidates fitted in workers) and fit-nominal --json with
    the printing file: stdout holds only the JSON document."""
    f = effect_file(tmp_path / "printer.py", "printer", prelude=PRINTS)
    code, stdout, err = invoke("fit-nominal", study / "spectra.parquet", "-o",
                               tmp_path / "n.csv", "--effects", f, "--effect", "printer",
                               "--json")
    assert code == 0, err
    assert json.loads(stdout)["command"] == "fit-nominal"
    assert "printed by the term" in err
    code, stdout, err = invoke("-q", "diagnose", study / "spectra.parquet", "--model",
                               study / "grip.csv", "--effects", f, "--effect", "printer",
                               "--max-steps", "1", "-j", "2", "--json")
    assert code == 0, err
    assert list(json.loads(stdout)["axes"]) == ["x"]
    assert "printed by the term" in err


def test_prints_go_to_stderr_and_other_threads_keep_stdout(tmp_path, capsys):
    """In Python: loading the file and running its term print on stderr; meanwhile another
    thread's print still reaches stdout, and stdout is restored afterwards."""
    f = effect_file(tmp_path / "printer.py", "printer", prelude=PRINTS)
    stdout = sys.stdout
    (e,) = load_effect_file(f)
    try:
        inside, release = threading.Event(), threading.Event()
        orig = e.term

        def waiting_term(s, values, mp):   # the user's code, held while the other prints
            inside.set()
            release.wait(10)
            return orig(s, values, mp)
        object.__setattr__(e, "term", waiting_term)
        t = threading.Thread(target=e.evaluate, args=(np.array([1j]), {"k": 1.0}, 0.1))
        t.start()
        assert inside.wait(10)
        print("armfit data")
        release.set()
        t.join(10)
    finally:
        object.__setattr__(e, "term", orig)
        EFFECTS.unregister(["printer"])
    assert sys.stdout is stdout
    captured = capsys.readouterr()
    assert captured.out == "armfit data\n"
    # the loader's checks run the term too: every line after the first is the term's
    lines = captured.err.splitlines()
    assert lines[0] == "printed while loading" and len(lines) > 2
    assert set(lines[1:]) == {"printed by the term"}


@pytest.mark.slow
def test_run_reports_failed_candidates_and_keeps_json_on_stdout(small_study, tmp_path):
    """armfit run -j 2 --json with an effects file whose effects break (NaN, raising) and
    print: the run ends (exit 0), stdout is its JSON document alone, each broken
    candidate is a warning on stderr and a line of report.md, and diagnosis.json lists
    it (before: exit 1 on the raising effect, prints ahead of the JSON)."""
    f = effect_file(tmp_path / "broken.py", "sneaky", "raiser", prelude=PRINTS)
    out = tmp_path / "run"
    code, stdout, err = invoke("run", small_study, "-o", out, "--effects", f, "--no-figures",
                               "-j", "2", "--json")
    assert code == 0, err
    assert json.loads(stdout)["outdir"] == str(out)
    assert "printed while loading" in err
    for name in ("sneaky", "raiser"):
        assert f"warning: diagnose x: candidate {name} left out: {f}: effect '{name}'" in err
        assert f"- `{name}`: {f}: effect '{name}'" in (out / "report.md").read_text()
    failed = json.loads((out / "diagnosis.json").read_text())["axes"]["x"]
    assert [c["effect"] for c in failed["failed_candidates"]] == ["sneaky", "raiser"]
