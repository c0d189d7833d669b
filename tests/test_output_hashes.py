"""The command line's outputs on sample_data/study, byte for byte.

The SHA-256 of every file the main commands write on the sample study is compared with
the values recorded below. They were recorded by :func:`produce` with the locked
versions of requirements.lock; a change of these bytes is a change of armfit's results
(numbers, formats or figures) and must be deliberate: re-record with

    .venv/bin/python tests/test_output_hashes.py

and say in the commit which outputs changed and why. Floating-point results differ in
their last bits between library versions, so the test runs only with the locked versions
of the numerical libraries (skipped otherwise). They also differ between processors:
numpy picks its vector loops (AVX2, AVX-512, …) and OpenBLAS its kernels by the CPU it
runs on. The outputs are therefore produced in a child process whose numpy uses only its
x86-64 baseline loops (:data:`PINNED_ENV`: ``NPY_DISABLE_CPU_FEATURES``) and whose
OpenBLAS uses one kernel set (``OPENBLAS_CORETYPE``), the same on any x86-64 machine; on
another architecture the test is skipped.
"""

from __future__ import annotations

import hashlib
import json
import os
import platform
import subprocess
import sys
from pathlib import Path

import pytest
from locked import unlocked

REPO = Path(__file__).resolve().parents[1]

#: The environment of the child process that produces the outputs: numpy's dispatched
#: loops above the x86-64-v2 baseline switched off, OpenBLAS's kernels those of one
#: processor family, so that the bytes do not depend on the machine's vector units.
PINNED_ENV: dict[str, str] = {
    "NPY_DISABLE_CPU_FEATURES": "X86_V3 X86_V4 AVX512_ICL AVX512_SPR",
    "OPENBLAS_CORETYPE": "Nehalem",
}

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
        "7bf5688b17f1438bf4cbaabc6fc48cd305ddf438d063603a78b7b59eb6f6c1e7",
    "fit-nominal.stdout":
        "c6d919b50a286afaaedace1c0832d2a97f66742b1a06559fc7137ce940c868ac",
    "fit-uncertainty.stdout":
        "8f475d7ea5c090bdc7b37b1d8322fbc4b34332aa94c9ad221da7872497bb5422",
    "compare.stdout":
        "9ec295d8ffc8ff63475dc0ce8b4ae3c280a08dd2fd2818a338b84af58aca4193",
    "diagnose.stdout":
        "8480152ea1ea2eb4e8a48527c8a9dbcb436adc16c014a129fe791a48f23422a8",
    "plot-bode.stdout":
        "e3b0c44298fc1c149afbf4c8996fb92427ae41e4649b934ca495991b7852b855",
    "bode.png":
        "dc2740e86ae04d0e296505cb92bca6fd32a8e421bc87a689f88cfd9836382350",
    "grip.csv":
        "e606715dee166b08ea22b22a9e8fcdb5dab3169aaba93469eec68b08f6f6901d",
    "nominal.csv":
        "ce4943d2636582eadb0cbaa6c34618639c17b1cd390c0986ab8db2bc7228364c",
    "run/adoption.csv":
        "a03dd023790b6e27d056b12e9a0658e098fa0e3ddfd4d75e6ee17b5f5ad43866",
    "run/certificate.csv":
        "9c9961a45ea63796526a4492ecb74669bfb2a9dc12ebfb5183ff94172d5bbed6",
    "run/compare.csv":
        "07077598cb14bdf883654c1287ff00aeb0f59ec1873e435de395420e079bf7e5",
    "run/diagnosis.json":
        "8480152ea1ea2eb4e8a48527c8a9dbcb436adc16c014a129fe791a48f23422a8",
    "run/grip_params.csv":
        "e606715dee166b08ea22b22a9e8fcdb5dab3169aaba93469eec68b08f6f6901d",
    "run/grip_params.tex":
        "a30e9288acad14b36f41695e560bea5d7201a820e8e1f5151b4040acda5136ca",
    "run/nominal_params.csv":
        "ce4943d2636582eadb0cbaa6c34618639c17b1cd390c0986ab8db2bc7228364c",
    "run/nominal_params.tex":
        "13e3da5b8799deacf95f0f56b253209c06456e428bedb35d019dfda8775e8fea",
    "run/report.html":
        "363f329d37f61ede9f4ee767add45edd9e790be8e739f5362163d7573cc46895",
    "run/report.md":
        "a102f11d95d46ddf21149b88f6ab49170039a3691c212b2e391327c3de05e409",
    "run/spectra.parquet":
        "ffcc023bbeae47cfe70a5191c972d844bb5a0c3abd0907f6f84c2aa294e8707a",
    "run/stability.csv":
        "2212753ac4ebe213e5c782cbeaf69217018ef1f2a92af072997d3153d73a90f3",
    "run/trial_params.csv":
        "84f536709d0747e263c043c3b0b636daa5cacb528009bad9f78a833ba99b3e24",
    "run/trials.parquet":
        "86eea6cfca8478c12ba69859084db095c2471f59e547fdcc41e8605e0b3bd474",
    "run/wu.csv":
        "bde604c7b102c6e9c3db382a45ffeb81e46666fbfebe9bbdab2bd27c6844ca84",
    "run/wu.tex":
        "901fbf68ac0c0225bb5c2c4117e45ca4d786b80b9a7c4561ce248c20115faad3",
    "run/wu_summary.csv":
        "8c1ced425bb1f6f2bcf036dda1d8ff1977afccf482f605da619290df7d6eda68",
    "run/wu_wmax.csv":
        "aa3b230c4bf6324e322f177d3f179e94beeb7c7793cbace6e88630e9cdac1ace",
    "wu.csv":
        "bde604c7b102c6e9c3db382a45ffeb81e46666fbfebe9bbdab2bd27c6844ca84",
    "wu_summary.csv":
        "8c1ced425bb1f6f2bcf036dda1d8ff1977afccf482f605da619290df7d6eda68",
    "wu_wmax.csv":
        "aa3b230c4bf6324e322f177d3f179e94beeb7c7793cbace6e88630e9cdac1ace",
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


def produce_pinned(folder: Path) -> dict[str, str]:
    """:func:`produce` in a child process with :data:`PINNED_ENV`."""
    run = subprocess.run([sys.executable, __file__, "--json", str(folder)],
                         env={**os.environ, **PINNED_ENV}, capture_output=True, text=True,
                         timeout=900)
    assert run.returncode == 0, run.stderr
    return json.loads(run.stdout)


@pytest.fixture(scope="module")
def produced(tmp_path_factory) -> dict[str, str]:
    if platform.machine() not in ("x86_64", "AMD64"):
        pytest.skip(f"output bytes are recorded on x86-64 (this is {platform.machine()})")
    differ = unlocked()
    if differ:
        pytest.skip("output bytes are recorded with the locked versions; installed "
                    + ", ".join(f"{n} {a} (locked {b})" for n, (a, b) in differ.items()))
    return produce_pinned(tmp_path_factory.mktemp("hashes"))


def test_outputs_are_the_recorded_bytes(produced):
    assert set(produced) == set(EXPECTED)
    changed = sorted(k for k in EXPECTED if produced[k] != EXPECTED[k])
    assert changed == [], f"outputs changed: {changed}"


if __name__ == "__main__":  # re-record EXPECTED (run from the repository root)
    import tempfile
    if sys.argv[1:2] == ["--json"]:     # the child process of produce_pinned
        print(json.dumps(produce(Path(sys.argv[2]))))
        sys.exit(0)
    with tempfile.TemporaryDirectory() as tmp:
        sums = produce_pinned(Path(tmp) / "hashes")
    print("EXPECTED: dict[str, str] = {")
    for name, digest in sums.items():
        print(f'    "{name}":\n        "{digest}",')
    print("}")
    sys.exit(0)
