"""One grammar on every command: spellings, bands, -v/-q anywhere, metavars and help
text, output formats by extension, table widths, skipped trials listed, the README tour.

The study these tests read is the session's fault study (tests/conftest.py: 2 subjects,
axes x and z, grips 1 and 2 N, 26 s trials) with its spectra and its nominal and grip fits.
"""

from __future__ import annotations

import json
import re
import shlex
from pathlib import Path

import click
import pyarrow.parquet as pq
import pytest
from click.testing import CliRunner

from armfit.cli.grammar import OutputFile, table_width
from armfit.cli.main import cli
from armfit.cli.options import band_spec, parse_bands
from armfit.errors import EXIT_DATAERR, EXIT_NOINPUT, EXIT_USAGE

ROOT = Path(__file__).resolve().parents[1]
NAME = "sub-01_axis-y_grip-2N"


def invoke(*args, env=None):
    return CliRunner().invoke(cli, [str(a) for a in args], env=env)


def _commands():
    """(name, command) of every subcommand, the plot subcommands included."""
    ctx = click.Context(cli)
    for name in cli.list_commands(ctx):
        cmd = cli.get_command(ctx, name)
        if isinstance(cmd, click.Group):
            yield name, cmd
            for sub in cmd.list_commands(click.Context(cmd)):
                yield f"{name} {sub}", cmd.get_command(click.Context(cmd), sub)
        else:
            yield name, cmd


def _help(name: str, columns: int = 80) -> str:
    res = invoke(*name.split(), "--help", env={"COLUMNS": str(columns)})
    assert res.exit_code == 0, res.output
    return res.output


# ---------------------------------------------------------------------------
# One spelling: --fmin everywhere, the old spellings hidden aliases
# ---------------------------------------------------------------------------

def test_ingest_takes_fmin_and_the_old_f_min_as_a_hidden_alias(tmp_path, write_trial,
                                                               make_columns):
    # a 15 s trial: too short for 0.1 Hz (two periods: 20 s), long enough for 0.2 Hz (10 s)
    path = write_trial(tmp_path / f"{NAME}.csv", make_columns("y", duration_s=15.0))
    res = invoke("ingest", path, "-o", tmp_path / "a.parquet")
    assert res.exit_code == EXIT_DATAERR and "lower --fmin" in res.stderr
    res = invoke("ingest", path, "-o", tmp_path / "b.parquet", "--fmin", "0.2")
    assert res.exit_code == 0, res.output
    assert "warning" not in res.stderr
    res = invoke("ingest", path, "-o", tmp_path / "c.parquet", "--f-min", "0.2")
    assert res.exit_code == 0, res.output
    assert "warning: --f-min is now spelled --fmin" in res.stderr
    # the old spelling is read by the new option's own type: the same refusal
    res = invoke("ingest", path, "-o", tmp_path / "d.parquet", "--f-min", "0")
    assert res.exit_code == EXIT_USAGE and not (tmp_path / "d.parquet").exists()
    res = invoke("ingest", path, "-o", tmp_path / "e.parquet", "--fmin", "0.2", "--f-min",
                 "0.3")
    assert res.exit_code == EXIT_USAGE
    assert res.stderr.strip() == ("armfit: error: --fmin and --f-min are one option "
                                  "(--f-min is its old spelling); give --fmin once")
    text = _help("ingest")
    assert "--fmin HZ" in text and "--f-min" not in text


def test_estimate_min_coherence_and_its_old_spelling_reach_the_estimator(tmp_path, study):
    # the value given is the file's metadata options.coherence_min (docs/formats.md)
    for flag, out in (("--min-coherence", "a.parquet"), ("--coherence-min", "b.parquet")):
        res = invoke("estimate", study, "-o", tmp_path / out, flag, "0.9")
        assert res.exit_code == 0, res.output
        meta = json.loads(pq.read_schema(tmp_path / out).metadata[b"armfit"])
        assert meta["options"]["coherence_min"] == 0.9
    assert (tmp_path / "a.parquet").read_bytes() == (tmp_path / "b.parquet").read_bytes()
    text = _help("estimate")
    assert "--min-coherence F" in text and "--coherence-min" not in text


def test_no_option_is_spelled_two_ways_across_commands():
    # every visible long option: no two that differ only by where a hyphen falls
    seen: dict[str, set[str]] = {}
    for _, cmd in _commands():
        for p in cmd.params:
            if isinstance(p, click.Option) and not p.hidden:
                for o in p.opts:
                    if o.startswith("--"):
                        seen.setdefault(o.replace("-", ""), set()).add(o)
    assert {k: v for k, v in seen.items() if len(v) > 1} == {}


# ---------------------------------------------------------------------------
# One band grammar: [AXIS=]LO:HI[,...] wherever a band is taken, repeatable
# ---------------------------------------------------------------------------

def test_every_band_option_takes_the_one_grammar():
    for name, cmd in _commands():
        for p in cmd.params:
            if isinstance(p, click.Option) and "--band" in p.opts:
                assert p.metavar == "[AXIS=]LO:HI[,...]" and p.multiple, name


def test_band_spec_of_single_band_commands():
    # no axis: one band for every axis, the last wins; with axes: a mapping in which an
    # item without an axis sets every axis and later items win
    assert band_spec(parse_bands(())) is None
    assert band_spec(parse_bands(["0.1:30", "0.2:20"])) == (0.2, 20.0)
    assert band_spec(parse_bands(["z=0.1:10"])) == {"z": (0.1, 10.0)}
    assert band_spec(parse_bands(["0.5:20,z=0.5:10"])) == {
        "x": (0.5, 20.0), "y": (0.5, 20.0), "z": (0.5, 10.0)}


def test_compare_takes_a_band_per_axis(spectra, nominal):
    res = invoke("compare", spectra, "--model", nominal, "--band", "z=0.1:10", "--json")
    assert res.exit_code == 0, res.output
    rows = {r["axis"]: r for r in json.loads(res.stdout)["rows"]}
    # z: the bands of compare's 0.1-1, 1-3, 3-10, 10-30 Hz inside 0.1-10 Hz; x: the grid
    assert [(b["lo_hz"], b["hi_hz"]) for b in rows["z"]["bands"]] == [
        (0.1, 1.0), (1.0, 3.0), (3.0, 10.0)]
    assert [b["hi_hz"] for b in rows["x"]["bands"]] == [1.0, 3.0, 10.0, 30.0]
    assert rows["z"]["overall"]["hi_hz"] <= 10.0
    # the same as one band for z alone
    res_z = invoke("compare", spectra, "--model", nominal, "--band", "0.1:10", "--json")
    z_alone = {r["axis"]: r for r in json.loads(res_z.stdout)["rows"]}["z"]
    assert rows["z"]["overall"] == z_alone["overall"]


def test_fit_uncertainty_takes_a_band_per_axis(spectra, nominal, tmp_path):
    res = invoke("fit-uncertainty", spectra, "--nominal", nominal, "-o", tmp_path / "wu.csv",
                 "--band", "0.1:30", "--band", "z=0.2:10", "--json")
    assert res.exit_code == 0, res.output
    bands = {a["axis"]: a["band_hz"] for a in json.loads(res.stdout)["axes"]}
    # z within 0.2-10 Hz, x over the grid the spectra hold (0.1-30 Hz); each band is a
    # range of grid points, so it lies inside what was asked
    assert 0.2 <= bands["z"][0] < 0.25 and 9.0 < bands["z"][1] <= 10.0
    assert bands["x"] == pytest.approx([0.1, 30.0])


def test_fit_grip_band_is_repeatable_and_later_items_win(spectra, tmp_path):
    res = invoke("fit-nominal", spectra, "-o", tmp_path / "n.csv", "--band", "0.5:20",
                 "--band", "z=0.5:8", "--json")
    assert res.exit_code == 0, res.output
    fits = {f["axis"]: f for f in json.loads(res.stdout)["fits"]}
    # the fitted bins lie inside each axis's band (grid of 40 points per decade)
    assert 0.5 <= fits["x"]["band_lo_hz"] and fits["x"]["band_hi_hz"] <= 20.0 < \
        fits["x"]["band_hi_hz"] * 10 ** (1 / 40) + 1e-9
    assert fits["z"]["band_hi_hz"] <= 8.0 < fits["z"]["band_hi_hz"] * 10 ** (1 / 40) + 1e-9


def test_a_bad_band_is_one_line_and_exit_2(spectra, nominal):
    res = invoke("diagnose", spectra, "--model", nominal, "--band", "w=1:2")
    assert res.exit_code == EXIT_USAGE
    assert res.stderr.count("\n") == 1 and "--band 'w=1:2'" in res.stderr


# ---------------------------------------------------------------------------
# -v / -q anywhere, on every command and the plot subcommands
# ---------------------------------------------------------------------------

#: Each command with arguments that fail early on a missing input (exit 66), or an
#: impossible setting (simulate: a grip not in Table I, exit 2).
FAILING = {
    "ingest": (["nope", "-o", "t.parquet"], EXIT_NOINPUT),
    "estimate": (["nope", "-o", "s.parquet"], EXIT_NOINPUT),
    "fit-grip": (["nope.parquet", "-o", "g.csv"], EXIT_NOINPUT),
    "fit-nominal": (["nope.parquet", "-o", "n.csv"], EXIT_NOINPUT),
    "fit-trials": (["nope.parquet", "-o", "t.csv"], EXIT_NOINPUT),
    "fit-uncertainty": (["nope.parquet", "--nominal", "nope.csv", "-o", "wu.csv"],
                        EXIT_NOINPUT),
    "effects": (["--effects", "nope.py"], EXIT_NOINPUT),
    "compare": (["nope.parquet", "--model", "nope.csv"], EXIT_NOINPUT),
    "diagnose": (["nope.parquet", "--model", "nope.csv"], EXIT_NOINPUT),
    "stability": (["nope.csv"], EXIT_NOINPUT),
    "simulate": (["-o", "sim", "--grips", "7"], EXIT_USAGE),
    "run": (["nope", "-o", "out"], EXIT_NOINPUT),
    "plot bode": (["nope.parquet", "-o", "f.png"], EXIT_NOINPUT),
    "plot residual": (["nope.parquet", "--model", "nope.csv", "-o", "f.png"], EXIT_NOINPUT),
    "plot uncertainty": (["nope.parquet", "--nominal", "nope.csv", "-o", "f.png"],
                         EXIT_NOINPUT),
    "plot literature": (["--model", "nope.csv", "-o", "f.png"], EXIT_NOINPUT),
    "plot stability": (["nope.csv", "-o", "f.png"], EXIT_NOINPUT),
    "export": (["nope.csv", "-o", "m.mat"], EXIT_NOINPUT),
}


def test_every_command_is_in_the_verbosity_table():
    assert set(FAILING) == {n for n, c in _commands() if not isinstance(c, click.Group)}


@pytest.mark.parametrize("name", sorted(FAILING))
def test_v_works_before_and_after_the_command(name, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    args, code = FAILING[name]
    words = name.split()
    plain = invoke(*words, *args)
    assert plain.exit_code == code and "Traceback" not in plain.stderr, plain.output
    # -v: the traceback as well, wherever it is written
    places = [["-v", *words, *args], [*words, *args, "-v"], [*words, "-v", *args]]
    if len(words) == 2:
        places.append([words[0], "-v", words[1], *args])   # armfit plot -v bode ...
    for argv in places:
        res = invoke(*argv)
        assert res.exit_code == code, (argv, res.output)
        assert "Traceback" in res.stderr, argv
        assert res.stderr.strip().splitlines()[-1] == plain.stderr.strip(), argv


def test_q_after_the_command_silences_the_messages(study, tmp_path):
    before = invoke("-q", "ingest", study, "-o", tmp_path / "a.parquet")
    after = invoke("ingest", study, "-o", tmp_path / "b.parquet", "-q")
    plain = invoke("ingest", study, "-o", tmp_path / "c.parquet")
    assert before.exit_code == after.exit_code == plain.exit_code == 0
    assert "ingested 8 trial(s)" in plain.stderr        # 2 subjects x 2 axes x 2 grips
    assert before.stderr == after.stderr == ""
    # -q wins over -v, as before the command
    both = invoke("-v", "ingest", study, "-o", tmp_path / "d.parquet", "-q")
    assert both.exit_code == 0 and both.stderr == ""


def test_v_after_the_command_lists_ignored_files(study, tmp_path):
    # ingest lists files that are not trials only with -v
    (study / "notes.txt").write_text("not a trial", encoding="utf-8")
    try:
        plain = invoke("ingest", study, "-o", tmp_path / "a.parquet")
        after = invoke("ingest", study, "-o", tmp_path / "b.parquet", "-v")
    finally:
        (study / "notes.txt").unlink()
    assert "ignored (not a trial name)" not in plain.stderr
    assert "ignored (not a trial name):" in after.stderr and "notes.txt" in after.stderr


# ---------------------------------------------------------------------------
# Metavars say what is parsed; --help reads well in 80 columns
# ---------------------------------------------------------------------------

def test_simulate_effect_says_name_equals_values(tmp_path):
    text = _help("simulate")
    assert "--effect NAME=VALUES" in text and "NAME=V1[,V2..]" in text
    res = invoke("simulate", "-o", tmp_path / "s", "--effect", "delay")
    assert res.exit_code == EXIT_USAGE and "give values as delay=delay_s" in res.stderr


#: click's placeholders when no metavar is given: they name a type, not what is parsed.
TYPE_NAMES = {"INTEGER", "FLOAT", "TEXT", "PATH", "DIRECTORY", "BOOLEAN"}


def test_every_metavar_names_what_is_parsed():
    bad = []
    for name, cmd in _commands():
        ctx = click.Context(cmd)
        for p in cmd.params:
            if isinstance(p, click.Option) and not p.is_flag and not p.count \
                    and not p.hidden and not isinstance(p.type, click.Choice):
                metavar = p.make_metavar(ctx)
                if metavar in TYPE_NAMES:
                    bad.append(f"{name} {p.opts[-1]}: {metavar}")
                if isinstance(p.type, OutputFile) and not all(
                        e in metavar or e in (p.help or "") for e in p.type.formats):
                    bad.append(f"{name} {p.opts[-1]}: extensions not named")
    assert bad == []


@pytest.mark.parametrize("name", ["(group)", *sorted(n for n, _ in _commands())])
def test_help_reads_well_in_80_columns(name):
    text = _help("" if name == "(group)" else name)
    long = [ln for ln in text.splitlines() if len(ln) > 80]
    assert long == []
    # no unbounded range shown as x<=None, no help running into the next option's
    assert "None]" not in text and "x<=None" not in text
    options = text.split("Options:")[1]
    assert not re.search(r"\.\.\.\s*(\[|$)", options, flags=re.M)
    assert not re.search(r"^\s+\.\.\. ", options, flags=re.M)
    # the plot group's subcommands are listed with whole summaries
    if name == "plot":
        listed = text.split("Commands:")[1]
        assert "..." not in listed


def test_the_effect_floors_each_say_their_unit():
    text = " ".join(_help("diagnose").split())
    assert "--min-effect-db DB Practical floor in magnitude, dB:" in text
    assert "--min-effect-deg DEG Practical floor in phase, deg:" in text
    assert "[default: 0.5; x>=0]" in text and "[default: 3.0; x>=0]" in text


def test_a_default_that_matters_is_shown():
    # an option with a value default shows it, or says it in its help
    bad = []
    for name, cmd in _commands():
        for p in cmd.params:
            if not isinstance(p, click.Option) or p.hidden or p.is_flag or p.count:
                continue
            default = p.default
            if default is None or default == () or callable(default) \
                    or type(default).__name__ == "Sentinel":
                continue
            if not p.show_default and "default" not in (p.help or ""):
                bad.append(f"{name} {p.opts[-1]}")
    assert bad == []


# ---------------------------------------------------------------------------
# Output formats follow the extension; any other extension is refused
# ---------------------------------------------------------------------------

#: (command and arguments before the output, option, refused name, what is accepted)
REFUSED = [
    (["ingest", "{study}"], "-o", "t.csv", "ingest writes .parquet; not .csv"),
    (["estimate", "{study}"], "-o", "s.txt", "estimate writes .parquet or .csv; not .txt"),
    (["estimate", "{study}", "-o", "s.parquet"], "--csv", "s.tsv",
     "estimate writes .csv; not .tsv"),
    (["fit-nominal", "{spectra}"], "-o", "nom.parquet", "fit-nominal writes .csv; not .parquet"),
    (["fit-grip", "{spectra}"], "-o", "grip", "fit-grip writes .csv; the name has no extension"),
    (["fit-grip", "{spectra}", "-o", "g.csv"], "--latex", "t.txt",
     "fit-grip writes .tex; not .txt"),
    (["fit-trials", "{spectra}"], "-o", "t.parquet", "fit-trials writes .csv; not .parquet"),
    (["fit-uncertainty", "{spectra}", "--nominal", "{nominal}"], "-o", "wu.json",
     "fit-uncertainty writes .csv; not .json"),
    (["diagnose", "{spectra}", "--model", "{grip}"], "-o", "d.csv",
     "diagnose writes .json; not .csv"),
    (["stability", "{nominal}"], "-o", "k.json", "stability writes .csv; not .json"),
    (["simulate", "-o", "sim"], "--truth", "t.csv", "simulate writes .json; not .csv"),
    (["plot", "bode", "{spectra}"], "-o", "f.jpg", "plot bode writes .png, .svg or .pdf; not .jpg"),
]


@pytest.mark.parametrize("before, option, name, said", REFUSED,
                         ids=[f"{r[0][0]} {r[1]}" for r in REFUSED])
def test_an_extension_not_written_is_refused(before, option, name, said, tmp_path, study,
                                             spectra, nominal, grip):
    paths = {"study": study, "spectra": spectra, "nominal": nominal, "grip": grip}
    args = [a.format(**paths) if a.startswith("{") else
            (str(tmp_path / a) if a.endswith((".parquet", ".csv")) or a == "sim" else a)
            for a in before]
    target = tmp_path / name
    res = invoke(*args, option, target)
    assert res.exit_code == EXIT_USAGE, res.output
    flag = "--output" if option == "-o" else option
    assert res.stderr == f"armfit: error: {flag} {target}: {said}\n"
    assert not target.exists() and not any(tmp_path.iterdir())


def test_estimate_writes_csv_for_a_csv_name(study, tmp_path):
    # -o NAME.csv writes the table --csv writes: the same bytes; -o NAME.parquet Parquet
    res = invoke("estimate", study, "-o", tmp_path / "s.parquet", "--csv", tmp_path / "t.csv")
    assert res.exit_code == 0, res.output
    res = invoke("estimate", study, "-o", tmp_path / "S.CSV")
    assert res.exit_code == 0, res.output
    assert (tmp_path / "S.CSV").read_bytes() == (tmp_path / "t.csv").read_bytes()
    assert (tmp_path / "t.csv").read_text(encoding="utf-8").startswith("level,")
    assert (tmp_path / "s.parquet").read_bytes()[:4] == b"PAR1"


def test_an_existing_folder_is_still_an_output_error(spectra, tmp_path):
    # a file output never replaces a folder: exit 73, as before extensions were checked
    res = invoke("fit-nominal", spectra, "-o", tmp_path)
    assert res.exit_code == 73, res.output


# ---------------------------------------------------------------------------
# Tables follow the terminal's width
# ---------------------------------------------------------------------------

def _lines(text: str) -> list[str]:
    return text.splitlines()


@pytest.mark.parametrize("columns", [80, 200])
def test_tables_fit_the_width(columns, spectra, grip):
    env = {"COLUMNS": str(columns)}
    wide = {"COLUMNS": "2000"}
    for args in (["compare", spectra, "--model", grip], ["effects"]):
        res = invoke(*args, env=env)
        assert res.exit_code == 0, res.output
        widths = [len(ln) for ln in _lines(res.stdout)]
        assert max(widths) <= columns, (args, max(widths))
        natural = invoke(*args, env=wide).stdout
        natural_width = max(len(ln) for ln in _lines(natural))
        if natural_width <= columns:
            # it fits: drawn as on an unlimited terminal, nothing wrapped
            assert res.stdout == natural, args
        else:
            # it does not: the table takes the whole width, wrapping only what must
            assert max(widths) == columns, args
    # the effect library's rows are wider than 200 columns (its texts on one line each)
    assert max(len(ln) for ln in _lines(invoke("effects", env=wide).stdout)) > 200


def test_compare_at_80_columns_keeps_every_number(spectra, grip):
    # every cell's three numbers are printed, whole (wrapped after a "/"), never cut
    wide = invoke("compare", spectra, "--model", grip, "--json").stdout
    rows = json.loads(wide)["rows"]
    text = invoke("compare", spectra, "--model", grip, env={"COLUMNS": "80"}).stdout
    assert "…" not in text
    numbers = re.findall(r"\d+\.\d+", text)
    for r in rows:
        for b in [r["overall"], *r["bands"]]:
            assert f"{b['rms_db']:.2f}" in numbers and f"{b['rms_norm']:.2f}" in numbers


def test_piped_tables_have_a_fixed_width(monkeypatch, spectra, grip):
    # not a terminal and no COLUMNS: 120 columns (CliRunner's stdout is not a terminal)
    monkeypatch.delenv("COLUMNS", raising=False)
    assert table_width() == 120
    fixed = invoke("compare", spectra, "--model", grip).stdout
    assert fixed == invoke("compare", spectra, "--model", grip, env={"COLUMNS": "120"}).stdout
    monkeypatch.setenv("COLUMNS", "97")
    assert table_width() == 97
    monkeypatch.setenv("COLUMNS", "wide")
    assert table_width() == 120


# ---------------------------------------------------------------------------
# --skip-bad with every trial bad: each one listed with its reason
# ---------------------------------------------------------------------------

@pytest.fixture
def all_bad(tmp_path, write_trial, make_columns) -> Path:
    """Three trials of 5 s: too short for 0.1 Hz (20 s) on every command."""
    folder = tmp_path / "raw"
    for sub in ("01", "02", "03"):
        write_trial(folder / f"sub-{sub}_axis-y_grip-2N.csv", make_columns("y", duration_s=5.0))
    return folder


@pytest.mark.parametrize("command, output, code, error", [
    ("ingest", "t.parquet", EXIT_DATAERR, "every trial was bad (3 skipped"),
    ("estimate", "s.parquet", EXIT_NOINPUT, "no trial could be estimated (3 skipped)"),
    ("run", "out", EXIT_DATAERR, "every trial was bad (3 skipped"),
])
def test_skip_bad_lists_every_skipped_trial_when_none_is_left(command, output, code, error,
                                                             all_bad, tmp_path):
    res = invoke(command, all_bad, "-o", tmp_path / output, "--skip-bad")
    assert res.exit_code == code, res.output
    lines = res.stderr.strip().splitlines()
    skipped = [ln for ln in lines if ln.startswith("skipped ")]
    assert len(skipped) == 3
    for sub in ("01", "02", "03"):
        assert any(f"sub-{sub}_axis-y_grip-2N.csv: " in ln and "too short: 5 s" in ln
                   for ln in skipped), sub
    assert lines[-1].startswith("armfit: error: ") and error in lines[-1]
    assert lines.index(skipped[-1]) < len(lines) - 1       # before the error line
    quiet = invoke(command, all_bad, "-o", tmp_path / output, "--skip-bad", "-q")
    assert quiet.exit_code == code and quiet.stderr.strip().splitlines() == [lines[-1]]


# ---------------------------------------------------------------------------
# The README tour writes under out/ (ignored by git) and uses what it writes
# ---------------------------------------------------------------------------

def _tour_commands() -> list[list[str]]:
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    commands = []
    for block in re.findall(r"```console[^\n]*\n(.*?)```", text, flags=re.S):
        joined = re.sub(r"\\\n\s*", " ", block)
        commands += [shlex.split(ln[1:].strip(), comments=True)
                     for ln in joined.splitlines() if ln.startswith("$ armfit")]
    return commands


def test_readme_tour_writes_under_out_and_reads_what_it_writes():
    commands = _tour_commands()
    assert len(commands) >= 8
    written = [(argv[i + 1], k) for k, argv in enumerate(commands)
               for i, a in enumerate(argv[:-1]) if a in ("-o", "--output")]
    assert written and all(path.startswith("out/") for path, _ in written)
    for path, k in written:
        later = [a for argv in commands[k + 1:] for a in argv]
        assert path in later, f"{path} is written and never used"
    ignored = (ROOT / ".gitignore").read_text(encoding="utf-8").split()
    assert "out/" in ignored
