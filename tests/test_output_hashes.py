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
from pathlib import Path

import pytest
from locked import unlocked

REPO = Path(__file__).resolve().parents[1]

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
EXPECTED: dict[str, str] = {
    "run.stdout":
        "e3b0c44298fc1c149afbf4c8996fb92427ae41e4649b934ca495991b7852b855",
    "fit-grip.stdout":
        "b545b13137856f843cf7452c6e0ebd29146550c0ba012af307982caef8571f4a",
    "fit-nominal.stdout":
        "501203cf10818b2b56d0177cf97f63bb76dea7aef4bd5bb46c3e640831ae5eb0",
    "fit-uncertainty.stdout":
        "3f4c6981d5612cee3f15e6a9193c7fc19b943eb813e6a2c9f6ca5c025d94bdfe",
    "compare.stdout":
        "68d52b6fffe31b4cf76911e3414a14189e3e8f1b59bb37e18b0aff29d838a2f4",
    "diagnose.stdout":
        "f2c72dc526ac113b93caf1c09089bae0b620b625a9951d1d7343369a1e0fa2f4",
    "plot-bode.stdout":
        "e3b0c44298fc1c149afbf4c8996fb92427ae41e4649b934ca495991b7852b855",
    "bode.png":
        "df075c513fd7911f8c0535505e1cd6a8f6c937eca08e7c8a6164484c4e995463",
    "grip.csv":
        "33d633b60b9804160ae14bb95ac54d2d668b2dfe2596d7da946d78566b2b3786",
    "nominal.csv":
        "086929d69cbf9b11936a4a84ff047dbb56d4bcbd835fe01a0f38aa05f8f79da8",
    "run/adoption.csv":
        "b55f0a13253b42c415ea5bfba4589e66c3adf945902cd3606666bc9ca797269c",
    "run/certificate.csv":
        "c355fb376f95d003177c83591d0144f5580276bfb8c185be47c1cf7e7fcdada7",
    "run/compare.csv":
        "a5f960dfafebe811c2e3cf9f1c703eed0b319f606342e280a4ae07107b5df476",
    "run/diagnosis.json":
        "f2c72dc526ac113b93caf1c09089bae0b620b625a9951d1d7343369a1e0fa2f4",
    "run/grip_params.csv":
        "33d633b60b9804160ae14bb95ac54d2d668b2dfe2596d7da946d78566b2b3786",
    "run/grip_params.tex":
        "a30e9288acad14b36f41695e560bea5d7201a820e8e1f5151b4040acda5136ca",
    "run/nominal_params.csv":
        "086929d69cbf9b11936a4a84ff047dbb56d4bcbd835fe01a0f38aa05f8f79da8",
    "run/nominal_params.tex":
        "13e3da5b8799deacf95f0f56b253209c06456e428bedb35d019dfda8775e8fea",
    "run/report.md":
        "abf0294ffc5b20db2513fd502b1da8005eeebe334a83c4d441a8811a42210962",
    "run/spectra.parquet":
        "19eb2ccf12f514cf1809667c550e8cfcf2bf0a5f37d6e50441b3abca55f53fee",
    "run/stability.csv":
        "bbb8c4cc0704eb71b2f4b2d0d28584925059f6a526b393d29c2ef2a8bce5131c",
    "run/trial_params.csv":
        "0b35792769298af40edc39d399f475fee1e3a63436de71a8364896fe248c0667",
    "run/trials.parquet":
        "f11d71fa08bdbf7aaa708763a1b50612aec51f96af640c7cc23806c513ff7855",
    "run/wu.csv":
        "511ab974288fe419bb85c419f9791b8a1f3bbbad60c5d2a9e047215af7dd2b6b",
    "run/wu.tex":
        "f04afb6c5653e883f1fa77c852f1cb4f237fd6cbae7befce94fe5ea77cf0784d",
    "run/wu_summary.csv":
        "f80422978fd05829467189f251e714f5c67a8be79914b3e98c04e8237035156a",
    "run/wu_wmax.csv":
        "817201b0dd94fe77735125ef61d9683112a8a7cd41f428a350d0198147f795a0",
    "wu.csv":
        "511ab974288fe419bb85c419f9791b8a1f3bbbad60c5d2a9e047215af7dd2b6b",
    "wu_summary.csv":
        "f80422978fd05829467189f251e714f5c67a8be79914b3e98c04e8237035156a",
    "wu_wmax.csv":
        "817201b0dd94fe77735125ef61d9683112a8a7cd41f428a350d0198147f795a0",
}


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
    differ = unlocked()
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
