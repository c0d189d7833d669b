"""User-defined effects: ``armfit.Effect``/``armfit.Param``, ``--effects FILE``, the
entry-point group ``armfit.effects``, and the checks a bad definition meets.

Expected values: the spring constant comes from the simulator's known truth (150 N/m
given to ``armfit simulate``); the exit codes from armfit.errors (65 bad input, 66 no
input)."""

from __future__ import annotations

import json
import pickle
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

import armfit
from armfit.cli.main import cli
from armfit.errors import EffectDefinitionError
from armfit.models import effects as effects_mod
from armfit.models.arm import BASE_PARAMS, ClosedLoopModel, Param, at_bound
from armfit.models.effects import EFFECTS, Effect, EffectRegistry

ROOT = Path(__file__).resolve().parents[1]
SPRING = ROOT / "examples" / "device_spring.py"

HEADER = "import numpy as np\nfrom armfit import Effect, Param\n\n"


def _effect_src(*, name="my-spring", stage="device", params=None, term="values['k'] + 0.0 * s",
                null="(0.01,)", extra=""):
    params = params or 'Param("k", "N/m", 0.01, 5000.0, 50.0, "spring")'
    return HEADER + textwrap.dedent(f"""\
        def _term(s, values, mp):
            return {term}

        EFFECTS = [Effect(name={name!r}, stage={stage!r}, params=({params},),
                          term=_term, summary="test effect", null={null}{extra})]
        """)


def _run(runner, args):
    result = runner.invoke(cli, args)
    return result.exit_code, result.stdout, result.stderr


def test_public_api_and_example_file_registers_once():
    assert armfit.Effect is Effect and armfit.Param is Param
    (e,) = effects_mod.load_effect_file(SPRING)
    try:
        assert e.name == "device-spring" and EFFECTS["device-spring"] is e
        # loading the same file again is a no-op, not a name clash
        assert effects_mod.load_effect_file(SPRING) == [e]
        # the spring adds k to the device impedance: X/F = 1/(Z_ARM + Mp s² + k)
        m = ClosedLoopModel.for_axis("x", [e])
        theta = {p.name: p.typical for p in BASE_PARAMS} | {"device-spring.k_N_per_m": 150.0}
        f = np.array([0.5, 5.0, 20.0])
        base = ClosedLoopModel.for_axis("x").response(f, theta)
        np.testing.assert_allclose(1 / m.response(f, theta), 1 / base + 150.0, rtol=1e-12)
        # pickled by reference: the same object comes back
        assert pickle.loads(pickle.dumps(e)) is e
    finally:
        EFFECTS.unregister(["device-spring"])
    assert "device-spring" not in EFFECTS


def test_pickled_file_effect_loads_its_file_in_a_fresh_process():
    (e,) = effects_mod.load_effect_file(SPRING)
    try:
        blob = pickle.dumps(e)
    finally:
        EFFECTS.unregister(["device-spring"])
    code = ("import pickle, sys, numpy as np\n"
            "e = pickle.loads(sys.stdin.buffer.read())\n"
            "print(e.name, e.term(np.array([1j]), {'k_N_per_m': 7.0}, 0.09)[0].real)")
    out = subprocess.run([sys.executable, "-c", code], input=blob, capture_output=True,
                         check=True, timeout=60)
    assert out.stdout.decode().split() == ["device-spring", "7.0"]


def test_builtins_follow_the_contract():
    # the library is the first EFFECTS list and passes the same checks as a user's file
    from armfit.models import library
    assert [e.name for e in library.EFFECTS] == list(EFFECTS)[:len(library.EFFECTS)]
    for e in library.EFFECTS:
        effects_mod.check_effect(e)
    # device-mass's null is the device mass itself (None in its definition)
    assert EFFECTS["device-mass"].null_values(0.095) == {"mass_kg": 0.095}


def test_cli_happy_path_simulate_fit_and_read_back(runner, tmp_path):
    study, spectra, params = tmp_path / "s", tmp_path / "s.parquet", tmp_path / "p.csv"
    code, out, err = _run(runner, ["effects", "--effects", str(SPRING), "--json"])
    assert code == 0, err
    rows = {r["effect"]: r for r in json.loads(out)["effects"]}
    assert rows["device-spring"]["source"] == str(SPRING)
    assert rows["device-spring"]["acts_on"] == "device"
    assert rows["delay"]["source"] == "the built-in library"
    # without the file the name is unknown (usage error, pointing at --effects)
    code, _, err = _run(runner, ["simulate", "-o", str(study), "--effect", "device-spring=150"])
    assert code == 2 and "--effects FILE" in err
    code, _, err = _run(runner, [
        "simulate", "-o", str(study), "--subjects", "2", "--axes", "x", "--grips", "2",
        "--duration", "40,40", "--variability", "0", "--seed", "5",
        "--effects", str(SPRING), "--effect", "device-spring=150"])
    assert code == 0, err
    truth = json.loads((tmp_path / "s.truth.json").read_text())
    assert truth["options"]["effects_files"] == [str(SPRING)]
    code, _, err = _run(runner, ["estimate", str(study), "-o", str(spectra)])
    assert code == 0, err
    code, _, err = _run(runner, ["fit-nominal", str(spectra), "-o", str(params),
                                 "--effects", str(SPRING), "--effect", "device-spring"])
    assert code == 0, err
    from armfit.models.params import read_params
    with pytest.raises(Exception, match="effect_files FILE"):
        read_params(params)      # the file's effect is gone once the command ended
    effects_mod.load_effect_file(SPRING)
    try:
        df = read_params(params)
    finally:
        EFFECTS.unregister(["device-spring"])
    # simulator's truth: 150 N/m
    assert df["device-spring.k_N_per_m"].iloc[0] == pytest.approx(150.0, rel=0.15)
    code, out, err = _run(runner, ["compare", str(spectra), "--model", str(params),
                                   "--effects", str(SPRING), "--json"])
    assert code == 0, err
    assert json.loads(out)["rows"][0]["model"] == "base+device-spring"
    png = tmp_path / "bode.png"
    code, _, err = _run(runner, ["plot", "bode", str(spectra), "--model", str(params),
                                 "-o", str(png), "--effects", str(SPRING)])
    assert code == 0 and png.stat().st_size > 0, err


def test_diagnose_workers_see_the_file_effects(runner, tmp_path):
    """--jobs 2 runs the candidate fits in fresh worker processes (forkserver), which
    load the effect file themselves."""
    study, spectra, params = tmp_path / "s", tmp_path / "s.parquet", tmp_path / "p.csv"
    for args in (["simulate", "-o", str(study), "--subjects", "2", "--axes", "x",
                  "--grips", "2", "--duration", "30,30", "--variability", "0", "--seed", "2",
                  "--effects", str(SPRING), "--effect", "device-spring=300"],
                 ["estimate", str(study), "-o", str(spectra)],
                 ["fit-nominal", str(spectra), "-o", str(params)]):
        code, _, err = _run(runner, args)
        assert code == 0, err
    code, out, err = _run(runner, ["diagnose", str(spectra), "--model", str(params),
                                   "--effects", str(SPRING), "--effect", "device-spring",
                                   "--jobs", "2", "--json"])
    assert code == 0, err
    (axis,) = json.loads(out)["axes"].values()
    (cand,) = axis["candidates"]
    assert cand["effect"] == "device-spring"
    # the simulator's truth: a 300 N/m spring
    assert cand["params"]["k_N_per_m"] == pytest.approx(300.0, rel=0.15)


BAD_FILES = {
    "syntax": (HEADER + "def broken(:\n", "SyntaxError"),
    "missing-module": ("import no_such_module_for_armfit\n", "ModuleNotFoundError"),
    "raises-on-import": ("raise RuntimeError('boom')\n", "RuntimeError: boom"),
    "no-effects": (HEADER + "x = 1\n", "defines no EFFECTS"),
    "effects-not-list": (HEADER + "EFFECTS = {'a': 1}\n", "must be a list or tuple"),
    "not-an-effect": (HEADER + "EFFECTS = ['delay']\n", "EFFECTS[0] is a str"),
    "empty": (HEADER + "EFFECTS = []\n", "EFFECTS is empty"),
    "builtin-name": (_effect_src(name="delay"), "'delay' is already taken by the built-in"),
    "twice-in-file": (_effect_src() + "EFFECTS = EFFECTS * 2\n", "defined twice"),
    "bounds": (_effect_src(params='Param("k", "N/m", 10.0, 5000.0, 5.0)'),
               "lower < typical < upper"),
    "log-bound": (_effect_src(params='Param("k", "N/m", 0.0, 5000.0, 5.0)'), "lower > 0"),
    "stage": (_effect_src(stage="motor"), "stage must be one of arm, device, output"),
    "bad-name": (_effect_src(name="my spring"), "may not hold ' '"),
    "null-length": (_effect_src(null="(0.01, 0.02)"), "null must give one value per"),
    "null-outside": (_effect_src(null="(1e6,)"), "outside its bounds"),
    "term-raises": (_effect_src(term="1 / 0"),
                    "effect 'my-spring' raised ZeroDivisionError: division by zero (in its term"),
    "wrong-shape": (_effect_src(term="values['k']"), "shape ()"),
    "nan": (_effect_src(term="np.nan + 0.0 * s"), "NaN or infinite"),
    "inf": (_effect_src(term="np.inf * values['k'] + 0.0 * s"), "NaN or infinite"),
    "not-nested": (_effect_src(term="values['k'] + 100.0 + 0.0 * s"),
                   "at its null values"),
    "no-broadcast": (_effect_src(term="float(values['k']) + 0.0 * s"), "does not broadcast"),
    "bad-start": (_effect_src(extra=", starts=((1e9,),)"), "starts[0]"),
}


@pytest.mark.parametrize("case", sorted(BAD_FILES))
def test_bad_effect_file_is_one_line_naming_the_file(runner, tmp_path, case):
    text, fragment = BAD_FILES[case]
    path = tmp_path / f"{case}.py"
    path.write_text(text)
    before = list(EFFECTS)
    code, out, err = _run(runner, ["effects", "--effects", str(path)])
    assert code == 65, err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in err, err
    assert lines[0].startswith(f"armfit: error: {path}: "), lines[0]
    assert fragment in lines[0], lines[0]
    assert out == ""
    assert list(EFFECTS) == before      # nothing half-registered


def test_name_taken_by_another_file_and_missing_file(runner, tmp_path):
    a, b = tmp_path / "a.py", tmp_path / "b.py"
    a.write_text(_effect_src())
    b.write_text(_effect_src())
    code, _, err = _run(runner, ["fit-nominal", "x.parquet", "-o", str(tmp_path / "o.csv"),
                                 "--effects", str(a), "--effects", str(b)])
    assert code == 65 and f"{b}: effect name 'my-spring' is already taken by {a}" in err
    assert "my-spring" not in EFFECTS
    code, _, err = _run(runner, ["effects", "--effects", str(tmp_path / "none.py")])
    assert code == 66 and "no such effects file" in err


def test_param_bounds_error_is_an_armfit_error():
    with pytest.raises(EffectDefinitionError, match="lower < typical < upper"):
        Param("k", "N/m", 1.0, 2.0, 3.0)
    with pytest.raises(ValueError):      # still a ValueError for old callers
        Param("k", "N/m", 1.0, 2.0, 3.0)


def _fresh_registry(monkeypatch):
    reg = EffectRegistry()
    monkeypatch.setattr(effects_mod, "EFFECTS", reg)
    import armfit.cli.diagnose as cli_diag
    monkeypatch.setattr(cli_diag, "EFFECTS", reg)
    return reg


def _dist_info(tmp_path, module_text, value="armfit_demo_effects"):
    (tmp_path / "armfit_demo_effects.py").write_text(module_text)
    info = tmp_path / "armfit_demo-0.1.dist-info"
    info.mkdir()
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: armfit-demo\nVersion: 0.1\n")
    (info / "entry_points.txt").write_text(f"[armfit.effects]\ndemo = {value}\n")


def test_entry_point_effects_are_registered(runner, tmp_path, monkeypatch):
    _dist_info(tmp_path, _effect_src(name="ep-spring"))
    monkeypatch.syspath_prepend(str(tmp_path))
    reg = _fresh_registry(monkeypatch)
    names = list(reg)
    assert names[-1] == "ep-spring" and names[0] == "delay"
    assert "entry point 'demo = armfit_demo_effects' of armfit-demo 0.1" in \
        reg.describe_origin("ep-spring")
    code, out, err = _run(runner, ["effects", "--json"])
    assert code == 0, err
    assert "ep-spring" in [r["effect"] for r in json.loads(out)["effects"]]
    # a file may not reuse a name an installed package took
    f = tmp_path / "clash.py"
    f.write_text(_effect_src(name="ep-spring"))
    code, _, err = _run(runner, ["effects", "--effects", str(f)])
    assert code == 65 and "already taken by entry point 'demo" in err
    sys.modules.pop("armfit_demo_effects", None)


def test_broken_entry_point_names_the_package(runner, tmp_path, monkeypatch):
    _dist_info(tmp_path, _effect_src(name="ep-bad", stage="nowhere"))
    monkeypatch.syspath_prepend(str(tmp_path))
    _fresh_registry(monkeypatch)
    code, _, err = _run(runner, ["effects"])
    assert code == 65 and "Traceback" not in err
    assert "entry point 'demo = armfit_demo_effects' of armfit-demo 0.1: " in err
    assert "stage must be one of" in err
    sys.modules.pop("armfit_demo_effects", None)


def test_a_builtin_is_found_by_name_without_the_installed_packages(tmp_path, monkeypatch):
    # a broken package: listing the effects reports it, finding a built-in by name does
    # not look through the packages (a worker handed a built-in effect saves the scan),
    # and finds the library's own object; a name that is not a built-in does look
    from armfit.models import library
    _dist_info(tmp_path, _effect_src(name="ep-bad", stage="nowhere"))
    monkeypatch.syspath_prepend(str(tmp_path))
    scans = []
    real = effects_mod._entry_points
    monkeypatch.setattr(effects_mod, "_entry_points", lambda: scans.append(1) or real())
    reg = _fresh_registry(monkeypatch)
    assert reg["delay"] is library.EFFECTS[0] and reg["device-mass"].name == "device-mass"
    assert scans == []
    with pytest.raises(EffectDefinitionError, match="stage must be one of"):
        reg["no-such-effect"]
    assert scans == [1]
    sys.modules.pop("armfit_demo_effects", None)


def test_a_pickled_builtin_effect_loads_no_package_metadata_in_a_fresh_process():
    # what a worker process does with a task's effect: the built-in library is enough
    code = ("import pickle, sys; e = pickle.loads(sys.stdin.buffer.read()); "
            "print(e.name, 'importlib.metadata' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], input=pickle.dumps(EFFECTS["lowpass"]),
                         capture_output=True, check=True, timeout=60)
    assert out.stdout.decode().split() == ["lowpass", "False"]


def test_listing_the_library_reads_no_package_metadata_when_no_package_declares_effects():
    # the packages installed with armfit declare no effect: listing the library looks
    # for the group's name in their entry_points.txt and does not import
    # importlib.metadata (about 45 ms); the registry then holds the built-ins only
    code = ("import sys; from armfit.models.effects import EFFECTS; "
            "print(len(list(EFFECTS)), 'importlib.metadata' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, check=True,
                         timeout=60, cwd=Path(__file__).parent)
    from armfit.models import library
    assert out.stdout.decode().split() == [str(len(library.EFFECTS)), "False"]


@pytest.mark.parametrize("layout", ["dist-info", "egg-info", "other-group", "none", "zip",
                                    "egg"])
def test_the_quick_look_for_declared_effects_never_misses_what_importlib_finds(
        tmp_path, monkeypatch, layout):
    # the independent reference: importlib.metadata's own entry_points on the same path
    from importlib.metadata import entry_points
    group = effects_mod.ENTRY_POINT_GROUP
    if layout in ("dist-info", "egg-info", "other-group"):
        info = tmp_path / f"armfit_demo-0.1.{layout if layout != 'other-group' else 'dist-info'}"
        info.mkdir()
        (info / "METADATA").write_text("Metadata-Version: 2.1\nName: armfit-demo\n"
                                       "Version: 0.1\n")
        (info / "PKG-INFO").write_text("Metadata-Version: 2.1\nName: armfit-demo\n"
                                       "Version: 0.1\n")
        section = "console_scripts" if layout == "other-group" else group
        (info / "entry_points.txt").write_text(f"[{section}]\ndemo = armfit_demo_x\n")
        entry = tmp_path
    elif layout == "zip":         # a zip archive on the path: looked at by importlib only
        import zipfile
        entry = tmp_path / "pkgs.zip"
        with zipfile.ZipFile(entry, "w") as z:
            z.writestr("armfit_demo-0.1.dist-info/METADATA",
                       "Metadata-Version: 2.1\nName: armfit-demo\nVersion: 0.1\n")
            z.writestr("armfit_demo-0.1.dist-info/entry_points.txt",
                       f"[{group}]\ndemo = armfit_demo_x\n")
    elif layout == "egg":
        entry = tmp_path / "armfit_demo-0.1-py3.11.egg"
        (entry / "EGG-INFO").mkdir(parents=True)
        (entry / "EGG-INFO" / "PKG-INFO").write_text("Metadata-Version: 2.1\n"
                                                     "Name: armfit-demo\nVersion: 0.1\n")
        (entry / "EGG-INFO" / "entry_points.txt").write_text(f"[{group}]\ndemo = x\n")
    else:
        entry = tmp_path
    # another distribution finder in this process (importlib_metadata's, once dask is
    # imported) makes the look give way to importlib.metadata: compare with the answer
    # before the folder is added
    before = effects_mod._may_declare_group(group)
    monkeypatch.syspath_prepend(str(entry))
    found = [ep.name for ep in entry_points(group=group)]
    assert found == (["demo"] if layout in ("dist-info", "egg-info", "zip", "egg") else [])
    quick = effects_mod._may_declare_group(group)
    assert quick or not found          # never False where importlib finds one
    # a folder that declares nothing changes nothing; any other answers True
    assert quick == (before if layout in ("other-group", "none") else True)
    assert [ep.name for ep in effects_mod._entry_points()] == found


def test_another_distribution_finder_makes_the_quick_look_give_way(monkeypatch):
    # a finder that finds distributions where the look does not go (importlib.metadata
    # asks every finder on sys.meta_path): the look cannot rule the group out
    class Finder:
        @staticmethod
        def find_spec(*args):
            return None

        @staticmethod
        def find_distributions(*args, **kwargs):
            return iter(())

    import importlib.machinery
    monkeypatch.setattr(sys, "meta_path", [m for m in sys.meta_path
                                           if not hasattr(m, "find_distributions")
                                           or m is importlib.machinery.PathFinder])
    monkeypatch.setattr(sys, "path", [p for p in sys.path if "site-packages" in p])
    assert effects_mod._may_declare_group(effects_mod.ENTRY_POINT_GROUP) is False
    monkeypatch.setattr(sys, "meta_path", [*sys.meta_path, Finder()])
    assert effects_mod._may_declare_group(effects_mod.ENTRY_POINT_GROUP) is True


def test_at_bound_rule():
    # 1 % of the range in the search coordinate: log for b1 (0.05 … 1000 N·s/m)
    b1 = next(p for p in BASE_PARAMS if p.name == "b1")
    edge = 0.05 * (1000 / 0.05) ** 0.01          # = 0.0552 N·s/m
    assert b1.near_bound(0.05) == "lower"
    assert b1.near_bound(edge * 0.999) == "lower" and b1.near_bound(edge * 1.001) is None
    assert b1.near_bound(1000.0 / 1.05) == "upper"
    # linear for delay_s (0 … 0.1 s): within 1 ms of 0
    delay = EFFECTS["delay"].params[0]
    assert delay.near_bound(0.0009) == "lower" and delay.near_bound(0.0011) is None
    assert at_bound(BASE_PARAMS, {"Ma": 0.3, "b1": 0.05, "b2": 999.0}) == ["b1", "b2"]
