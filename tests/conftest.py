"""Shared test fixtures: synthetic contract-conforming trial files and a CLI runner.

The suite's recorded values (Octave's printed numbers, the outputs its documentation
shows) were made with numpy's AVX2 loops and OpenBLAS's Haswell kernels. Some fits have
near-equal optima, and which one an optimiser reaches can turn on the last bits of the
arithmetic: with AVX-512 kernels the uncertainty weight of the sample study's Y axis
takes 4 pole-zero pairs instead of 5, and a per-subject reflex gain of the test study
another minimum. So the suite runs with that arithmetic on every x86-64 machine that
has AVX2: the environment below is set before numpy is imported, here and in every
process the suite starts (pytest-xdist's workers, the command lines it runs), unless the
caller set it. It changes no result on a machine without AVX-512.
"""

from __future__ import annotations

import os
import sys

if "numpy" not in sys.modules:
    os.environ.setdefault("NPY_DISABLE_CPU_FEATURES", "X86_V4 AVX512_ICL AVX512_SPR")
    os.environ.setdefault("OPENBLAS_CORETYPE", "Haswell")

import json  # noqa: E402
import re  # noqa: E402
import subprocess  # noqa: E402
from collections.abc import Callable  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
import pytest  # noqa: E402
from click.testing import CliRunner  # noqa: E402

AXES = ("x", "y", "z")


def fresh_json(code: str):
    """The JSON a fresh interpreter running ``code`` prints on the last line of its
    stdout."""
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True)
    return json.loads(res.stdout.strip().splitlines()[-1])


def modules_after(args: list[str]) -> set[str]:
    """The modules a fresh interpreter holds after running ``armfit ARGS`` (which must
    succeed)."""
    return set(fresh_json("import sys, json\nfrom armfit.cli.main import cli\n"
                          f"try:\n    cli({args!r}, prog_name='armfit')\n"
                          "except SystemExit as e:\n    assert not e.code, e.code\n"
                          "print()\nprint(json.dumps(sorted(sys.modules)))"))


def trial_columns(axis: str = "y", *, fs: float = 100.0, duration_s: float = 25.0,
                  seed: int = 0, t0_s: float = 0.0, pos_unit: str = "m",
                  all_axes: bool = True, grip: bool = True,
                  grip_N: float = 2.0) -> dict[str, np.ndarray]:
    """Columns of a synthetic trial that meets the raw-trial contract.

    Gaussian force (N, |F| < 5) on ``axis`` (and small cross-axis forces when
    ``all_axes``), a random-walk position (m, or mm with ``pos_unit="mm"``), uniform time
    ``t0_s + k / fs`` and a grip signal around ``grip_N`` held between 65 Hz sensor
    samples.
    """
    rng = np.random.default_rng(seed)
    n = int(round(duration_s * fs))
    cols: dict[str, np.ndarray] = {"time_s": t0_s + np.arange(n) / fs}
    scale = 1000.0 if pos_unit == "mm" else 1.0
    for a in AXES:
        if a != axis and not all_axes:
            continue
        amp = 1.5 if a == axis else 0.1
        cols[f"force_{a}_N"] = np.clip(amp * rng.standard_normal(n), -4.9, 4.9)
        cols[f"pos_{a}_{pos_unit}"] = scale * 1e-3 * np.cumsum(rng.standard_normal(n))
    if grip:
        held = np.floor(np.arange(n) / fs * 65.0)
        cols["grip_N"] = grip_N + 0.1 * np.sin(held)
    return cols


def write_columns(path: Path, cols: dict[str, object]) -> Path:
    """Write columns to ``path`` as CSV, CSV.gz or Parquet (by the extension).

    Numeric columns keep their exact float64 values (pyarrow writes CSV numbers in
    shortest round-trip form). A column given as a list of strings is written as text,
    to make non-numeric cells.
    """
    import pyarrow as pa
    import pyarrow.csv as pcsv
    import pyarrow.parquet as pq

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    table = pa.table({k: (pa.array(v) if isinstance(v, list) else pa.array(np.asarray(v)))
                      for k, v in cols.items()})
    name = path.name.lower()
    if name.endswith(".parquet"):
        pq.write_table(table, path)
    elif name.endswith(".csv.gz"):
        with pa.CompressedOutputStream(str(path), "gzip") as out:
            pcsv.write_csv(table, out, pcsv.WriteOptions(quoting_style="none"))
    else:
        pcsv.write_csv(table, path, pcsv.WriteOptions(quoting_style="none"))
    return path


@pytest.fixture(scope="session")
def write_trial() -> Callable[..., Path]:
    """``write_trial(path, cols=None, **trial_columns_kwargs)`` writes a trial file.

    With ``cols`` None, the columns come from :func:`trial_columns` (the axis is taken
    from the file name when it has ``axis-<a>``). Returns the path.
    """
    def _write(path, cols: dict | None = None, **kwargs) -> Path:
        path = Path(path)
        if cols is None:
            if "axis" not in kwargs and "_axis-" in path.name:
                kwargs["axis"] = path.name.split("_axis-")[1][0]
            grip = re.search(r"_grip-(\d+(?:\.\d+)?)N", path.name)
            if "grip_N" not in kwargs and grip is not None:
                kwargs["grip_N"] = float(grip.group(1))  # the sensor agrees with the name
            cols = trial_columns(**kwargs)
        return write_columns(path, cols)
    return _write


@pytest.fixture(scope="session")
def make_columns() -> Callable[..., dict[str, np.ndarray]]:
    """The :func:`trial_columns` maker, for tests that alter columns before writing."""
    return trial_columns


@pytest.fixture
def runner() -> CliRunner:
    """A click CliRunner; stderr is kept apart from stdout (``result.stderr``)."""
    return CliRunner()


@pytest.fixture
def solver_stops_at_budget(monkeypatch):
    """Every least-squares solve reports that it ran out of evaluations (status 0), as
    scipy.optimize.least_squares does when max_nfev is reached: an injected solver result,
    so the test does not depend on how many evaluations a scipy release needs. The solver
    patched is :func:`armfit._trf.bounded_least_squares` (scipy's, copied), which every
    fit calls."""
    from armfit import _trf

    def stopping(real):
        def stopped(*args, **kwargs):
            res = real(*args, **kwargs)
            res.status, res.success = 0, False
            res.message = "The maximum number of function evaluations is exceeded."
            return res
        return stopped

    monkeypatch.setattr(_trf, "bounded_least_squares", stopping(_trf.bounded_least_squares))


@pytest.fixture(scope="session")
def sample_runs(tmp_path_factory) -> Callable[[str], Path]:
    """``name -> `` the output folder of ``armfit run sample_data/<name> --jobs 2
    --no-figures``, made once per session (the same bytes as with one job): the tests
    that read the runs of the sample studies share them and must not write into them."""
    from armfit.cli.main import cli
    samples = Path(__file__).resolve().parents[1] / "sample_data"
    made: dict[str, Path] = {}

    def get(name: str) -> Path:
        if name not in made:
            out = tmp_path_factory.mktemp(f"run-{name}") / "out"
            res = CliRunner().invoke(cli, ["-q", "run", str(samples / name), "-o", str(out),
                                           "--jobs", "2", "--no-figures"])
            assert res.exit_code == 0, res.output
            made[name] = out
        return made[name]

    return get


@pytest.fixture(scope="session")
def small_study(tmp_path_factory) -> Path:
    """2 subjects, axis x, grips 1 and 2 N, 26 s trials (armfit.simulate, seed 5): a study
    small enough to run on every executor."""
    import armfit
    root = tmp_path_factory.mktemp("small") / "study"
    armfit.simulate(subjects=2, axes=("x",), grips_N=(1.0, 2.0), duration_s=(26.0, 26.0),
                    seed=5).write(root)
    return root


@pytest.fixture(scope="session")
def serial_spectra(small_study):
    """:func:`small_study` estimated in this process (jobs=1): the reference of the
    executor tests."""
    import armfit
    return armfit.estimate(small_study)


#: The small study the fault tests work on (tests/test_faults*.py): 2 subjects, x and z,
#: grips 1 and 2 N, 26 s trials.
FAULT_SIM = ["--subjects", "2", "--axes", "xz", "--grips", "1,2", "--duration", "26,26",
             "--seed", "11"]


@pytest.fixture(scope="session")
def _fault_files(tmp_path_factory) -> Path:
    """The fault study, its spectra and nominal and grip fits, made once per session by
    the command line."""
    from armfit.cli.main import cli
    root = tmp_path_factory.mktemp("fault_files")
    steps = [["simulate", "-o", root / "study", *FAULT_SIM],
             ["estimate", root / "study", "-o", root / "spectra.parquet"],
             ["fit-nominal", root / "spectra.parquet", "-o", root / "nominal.csv"],
             ["fit-grip", root / "spectra.parquet", "-o", root / "grip.csv"]]
    for args in steps:
        res = CliRunner().invoke(cli, [str(a) for a in args])
        assert res.exit_code == 0, res.output
    return root


@pytest.fixture(scope="module")
def fault_root(_fault_files, tmp_path_factory) -> Path:
    """A fresh copy of the fault files for one test module (which may change them)."""
    import shutil
    root = tmp_path_factory.mktemp("faults") / "files"
    shutil.copytree(_fault_files, root, symlinks=True)
    return root


@pytest.fixture(scope="module")
def study(fault_root) -> Path:
    """The fault study's raw trial folder (a module's own copy)."""
    return fault_root / "study"


@pytest.fixture(scope="module")
def spectra(fault_root) -> Path:
    """The fault study's spectra file (``armfit estimate``)."""
    return fault_root / "spectra.parquet"


@pytest.fixture(scope="module")
def nominal(fault_root) -> Path:
    """The fault study's nominal fit (``armfit fit-nominal``)."""
    return fault_root / "nominal.csv"


@pytest.fixture(scope="module")
def grip(fault_root) -> Path:
    """The fault study's grip fits (``armfit fit-grip``)."""
    return fault_root / "grip.csv"
