"""The command line's outputs on sample_data/study, byte for byte.

The SHA-256 of every file the main commands write on the sample study is compared with
the values recorded below. They were recorded by :func:`produce` with the locked
versions of requirements.lock; a change of these bytes is a change of armfit's results
(numbers, formats or figures) and must be deliberate: re-record with

    .venv/bin/python tests/test_output_hashes.py

and say in the commit which outputs changed and why. Floating-point results differ in
their last bits between library versions, so the test runs only with the locked versions
of the numerical libraries (skipped otherwise).
"""

from __future__ import annotations

import hashlib
import os
import sys
from importlib import metadata
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]

#: Libraries whose versions decide the bytes.
LOCKED = ("numpy", "scipy", "pandas", "pyarrow", "matplotlib")

#: The commands run, in order, from a scratch folder holding ``sample_data`` (a link to
#: the repository's). ``run`` writes every table; the others add their own outputs.
COMMANDS: tuple[tuple[str, ...], ...] = (
    ("run", "sample_data/study", "-o", "run", "--no-figures"),
    ("fit-grip", "run/spectra.parquet", "-o", "grip.csv", "--json"),
    ("fit-nominal", "run/spectra.parquet", "-o", "nominal.csv", "--json"),
    ("fit-uncertainty", "run/spectra.parquet", "--nominal", "run/nominal_params.csv",
     "-o", "wu.csv", "--json"),
    ("compare", "run/spectra.parquet", "--model", "run/nominal_params.csv", "--json"),
    ("diagnose", "run/spectra.parquet", "--model", "run/grip_params.csv", "--json",
     "--effect", "delay", "--effect", "lowpass"),
    ("plot", "bode", "run/spectra.parquet", "--model", "run/grip_params.csv",
     "-o", "bode.png"),
)

#: SHA-256 of each output (``<command>.stdout`` for what a command prints).
EXPECTED: dict[str, str] = {}


def locked_versions(lock: Path = REPO / "requirements.lock") -> dict[str, str]:
    """{name: version} of :data:`LOCKED` in the lock file (names compared lower-case)."""
    out = {}
    for line in lock.read_text(encoding="utf-8").splitlines():
        name, sep, version = line.strip().partition("==")
        if sep and name.lower() in LOCKED:
            out[name.lower()] = version
    return out


def produce(folder: Path) -> dict[str, str]:
    """Run :data:`COMMANDS` in ``folder`` and return {output: SHA-256}."""
    from click.testing import CliRunner

    from armfit.cli.main import cli

    folder.mkdir(parents=True, exist_ok=True)
    link = folder / "sample_data"
    if not link.exists():
        link.symlink_to(REPO / "sample_data", target_is_directory=True)
    here = os.getcwd()
    os.chdir(folder)
    try:
        runner = CliRunner()
        printed = {}
        for args in COMMANDS:
            res = runner.invoke(cli, ["-q", *args], catch_exceptions=False)
            assert res.exit_code == 0, (args, res.output)
            printed[f"{'-'.join(args[:2] if args[0] == 'plot' else args[:1])}.stdout"] = \
                res.stdout.encode()
    finally:
        os.chdir(here)
    sums = {name: hashlib.sha256(data).hexdigest() for name, data in printed.items()}
    for path in sorted(folder.rglob("*")):
        if path.is_file() and "sample_data" not in path.relative_to(folder).parts:
            sums[str(path.relative_to(folder))] = hashlib.sha256(path.read_bytes()).hexdigest()
    return sums


@pytest.fixture(scope="module")
def produced(tmp_path_factory) -> dict[str, str]:
    locked = locked_versions()
    installed = {name: metadata.version(name) for name in LOCKED}
    differ = {n: (installed[n], locked.get(n)) for n in LOCKED if installed[n] != locked.get(n)}
    if differ:
        pytest.skip("output bytes are recorded with the locked versions; installed "
                    + ", ".join(f"{n} {a} (locked {b})" for n, (a, b) in differ.items()))
    return produce(tmp_path_factory.mktemp("hashes"))


def test_outputs_are_the_recorded_bytes(produced):
    assert set(produced) == set(EXPECTED)
    changed = sorted(k for k in EXPECTED if produced[k] != EXPECTED[k])
    assert changed == [], f"outputs changed: {changed}"


if __name__ == "__main__":  # re-record EXPECTED (run from the repository root)
    import tempfile
    with tempfile.TemporaryDirectory() as tmp:
        sums = produce(Path(tmp) / "hashes")
    print("EXPECTED: dict[str, str] = {")
    for name, digest in sums.items():
        print(f'    "{name}":\n        "{digest}",')
    print("}")
    sys.exit(0)
