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
        "c6aded63e03b743ab5c44c78195f63372046318878ab5d34b6c6a5938318cef9",
    "fit-nominal.stdout":
        "99b47e6bcc0cb39d81b6483d08bed6846c0fc810ba63cb5e59e15b828834d482",
    "fit-uncertainty.stdout":
        "7acce02812cb51d19039cda6a48c0b11f5ea8d38283c7016a123d6327b88f10e",
    "compare.stdout":
        "b9ea909c0d83d61174e52927e107954e637ecfa9487a8d5f47499e41ec73f809",
    "diagnose.stdout":
        "a9e1d9bf2f2dfc4602ac4e75650dd0cbcf56e71417db5309d1f95a9c1f7d3c1b",
    "plot-bode.stdout":
        "e3b0c44298fc1c149afbf4c8996fb92427ae41e4649b934ca495991b7852b855",
    "bode.png":
        "d7b98c2c5a8fa0effe56c3bd5763592e06d675bbed13b0caa1197b4a7ec8930f",
    "grip.csv":
        "0deb889a2d14ad30c8e5e6eb89eec8b31a2ab82be4883070caeb2339f5471125",
    "nominal.csv":
        "0053d5e5beda45559d72e0e56545143f4882f41b33beb1ecc59fdf3f831e0d37",
    "run/adoption.csv":
        "a03dd023790b6e27d056b12e9a0658e098fa0e3ddfd4d75e6ee17b5f5ad43866",
    "run/certificate.csv":
        "c7de9a4f8bc6659303ebcae12c5a8aa2059fac5fc589cc827bb4c7d5f6cd0990",
    "run/compare.csv":
        "51b8a6179df1704365e6268b0e67b471f7eec0c3013364d104a636d2153bf86d",
    "run/diagnosis.json":
        "a9e1d9bf2f2dfc4602ac4e75650dd0cbcf56e71417db5309d1f95a9c1f7d3c1b",
    "run/grip_params.csv":
        "0deb889a2d14ad30c8e5e6eb89eec8b31a2ab82be4883070caeb2339f5471125",
    "run/grip_params.tex":
        "a30e9288acad14b36f41695e560bea5d7201a820e8e1f5151b4040acda5136ca",
    "run/nominal_params.csv":
        "0053d5e5beda45559d72e0e56545143f4882f41b33beb1ecc59fdf3f831e0d37",
    "run/nominal_params.tex":
        "13e3da5b8799deacf95f0f56b253209c06456e428bedb35d019dfda8775e8fea",
    "run/report.html":
        "826fefb975eba2633694747ec1e98dab33fcf9553c60fcb3feb1ef948c444052",
    "run/report.md":
        "37bb37d1dd5c1c21262ca1531ca63f2fa1534d15ce5bad7e328c7891cb99b65f",
    "run/spectra.parquet":
        "19eb2ccf12f514cf1809667c550e8cfcf2bf0a5f37d6e50441b3abca55f53fee",
    "run/stability.csv":
        "66d8ba0e6d0e027d80bf246397f68a4e736edc64ebf10d6a5230bef283feaa57",
    "run/trial_params.csv":
        "c472ded99324406191766407550b6ab6b9062b22cf4b64c927a07fffd46b6408",
    "run/trials.parquet":
        "34eb582f5fec86f6d7c0d27c62e2eb917c898821d3fbf387c5b22af4ba5c9bea",
    "run/wu.csv":
        "4824f188576131bfb98155414a9dd6c73bf99a5e039738c5f58cf77502c84500",
    "run/wu.tex":
        "18f6592c6705c7f76441595eb5b1c686a32460fec1afc99f3361a49e703c7c99",
    "run/wu_summary.csv":
        "6e204760d044e9ea9442f47c0708e21689a242fd7a435c86356278756bdf2abc",
    "run/wu_wmax.csv":
        "b27c7d622673cf3b81470d7f6d1134362a88990fb8def733286b5beac0425d78",
    "wu.csv":
        "4824f188576131bfb98155414a9dd6c73bf99a5e039738c5f58cf77502c84500",
    "wu_summary.csv":
        "6e204760d044e9ea9442f47c0708e21689a242fd7a435c86356278756bdf2abc",
    "wu_wmax.csv":
        "b27c7d622673cf3b81470d7f6d1134362a88990fb8def733286b5beac0425d78",
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
