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
        "516323bd67968046d6f4ad69470323bb92a04760945e528d19ddfe424d677469",
    "diagnose.stdout":
        "979d09e3dc56bd36dd4c541638c914c7580deffa05076d9b8c8514f24a39f26e",
    "plot-bode.stdout":
        "e3b0c44298fc1c149afbf4c8996fb92427ae41e4649b934ca495991b7852b855",
    "bode.png":
        "df075c513fd7911f8c0535505e1cd6a8f6c937eca08e7c8a6164484c4e995463",
    "grip.csv":
        "0deb889a2d14ad30c8e5e6eb89eec8b31a2ab82be4883070caeb2339f5471125",
    "nominal.csv":
        "0053d5e5beda45559d72e0e56545143f4882f41b33beb1ecc59fdf3f831e0d37",
    "run/adoption.csv":
        "b55f0a13253b42c415ea5bfba4589e66c3adf945902cd3606666bc9ca797269c",
    "run/certificate.csv":
        "752f009838dff8d3dadac45bd35ecad87adeb3492c0c6e4f861f498da97fd7c8",
    "run/compare.csv":
        "aa2b8b7b1f3d7f61adffdc5b570b08546bb6186b42752f92bfb4ae09b965e6c2",
    "run/diagnosis.json":
        "979d09e3dc56bd36dd4c541638c914c7580deffa05076d9b8c8514f24a39f26e",
    "run/grip_params.csv":
        "0deb889a2d14ad30c8e5e6eb89eec8b31a2ab82be4883070caeb2339f5471125",
    "run/grip_params.tex":
        "a30e9288acad14b36f41695e560bea5d7201a820e8e1f5151b4040acda5136ca",
    "run/nominal_params.csv":
        "0053d5e5beda45559d72e0e56545143f4882f41b33beb1ecc59fdf3f831e0d37",
    "run/nominal_params.tex":
        "13e3da5b8799deacf95f0f56b253209c06456e428bedb35d019dfda8775e8fea",
    "run/report.md":
        "9265aa424ab94022276f8fde7a0027e9e253a2ebe4f8a5147e7e0a47c31c1c04",
    "run/spectra.parquet":
        "19eb2ccf12f514cf1809667c550e8cfcf2bf0a5f37d6e50441b3abca55f53fee",
    "run/stability.csv":
        "e7aeee8413f3c36b6898f177b293dbbf5a83f29150b95ff440a676bd51575796",
    "run/trial_params.csv":
        "412a232790ac60fe532280f65fe8eb4b4403b0a48789c2ac7c7da9f747d344d4",
    "run/trials.parquet":
        "f11d71fa08bdbf7aaa708763a1b50612aec51f96af640c7cc23806c513ff7855",
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
