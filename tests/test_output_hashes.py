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
        "1a85f0f517451792cf92760ac2c84c6ae5560d7e7c875d267a5af4917ec87d74",
    "fit-nominal.stdout":
        "f1fc3b0808bd3d1c5e1e9a9936e0869b0b862a3e138d2500cc93833853a3be14",
    "fit-uncertainty.stdout":
        "179c93a6a111dcf81a553f61d6d2248b38f0c0f8cfecf9fec1385719f54a1597",
    "compare.stdout":
        "77fc7927666fa7ab872528c5fd22c688dd3e3fe7b83c7823577a2f1ccb7633ef",
    "diagnose.stdout":
        "16f0158ade6b336dd2f755c24d56687410f854b19f385fbf9dedded2bfce1f9a",
    "plot-bode.stdout":
        "e3b0c44298fc1c149afbf4c8996fb92427ae41e4649b934ca495991b7852b855",
    "bode.png":
        "dc2740e86ae04d0e296505cb92bca6fd32a8e421bc87a689f88cfd9836382350",
    "grip.csv":
        "8fe7b51ecf2f2b77c017d85f9cf80b54ac2ff2d65a4880d37590533f9edf74fe",
    "nominal.csv":
        "9dc56dd6d9d5f8090fa3a12701b1134c9d95116b70df28a8c40a7927391a54fa",
    "run/adoption.csv":
        "a03dd023790b6e27d056b12e9a0658e098fa0e3ddfd4d75e6ee17b5f5ad43866",
    "run/certificate.csv":
        "201327c5c213fe5451985f8d0c1f8618637512074e0500ce3c5325925c029315",
    "run/compare.csv":
        "178b79f03f672b1e15c0a973f2e9fb6d7b4c45f2cb8dc841f6e47c1ff3d8dd66",
    "run/diagnosis.json":
        "16f0158ade6b336dd2f755c24d56687410f854b19f385fbf9dedded2bfce1f9a",
    "run/grip_params.csv":
        "8fe7b51ecf2f2b77c017d85f9cf80b54ac2ff2d65a4880d37590533f9edf74fe",
    "run/grip_params.tex":
        "a30e9288acad14b36f41695e560bea5d7201a820e8e1f5151b4040acda5136ca",
    "run/nominal_params.csv":
        "9dc56dd6d9d5f8090fa3a12701b1134c9d95116b70df28a8c40a7927391a54fa",
    "run/nominal_params.tex":
        "13e3da5b8799deacf95f0f56b253209c06456e428bedb35d019dfda8775e8fea",
    "run/report.html":
        "ce6be3e3cdca2ed676baaafa9da59a2e3e6d4637d61f0979b6057fbd561592d5",
    "run/report.md":
        "ba46f70481cc8c0ac169eee1fd0b4b3e0c9a05f4e53cd869b226c90f3ac855ad",
    "run/spectra.parquet":
        "7f7910c503a4059c4f6ea3bdc8c362fb29624ee31197ec605d4c4b9f3f33f8d9",
    "run/stability.csv":
        "f3df1ad3b5c4dedf2c337f30499d2a7d74144b83f83b053e1258d4b9bd6428dc",
    "run/trial_params.csv":
        "d415cee8608ec56da3f1d7612649367860eee5bb2a6afbe7fc6e6c014fbfc129",
    "run/trials.parquet":
        "34eb582f5fec86f6d7c0d27c62e2eb917c898821d3fbf387c5b22af4ba5c9bea",
    "run/wu.csv":
        "c37cea69e1732f61d2a9d77674c51b087f9cb744c7c6969a11ceec9f6374098e",
    "run/wu.tex":
        "c0da1267f7c7a4af26773acf74f5a2799a2d247b91dfa96b96862689697517f5",
    "run/wu_summary.csv":
        "14bdae00c03cf98cf2401e899fc00b5b5f9f48335197e7c8bd7d081f31c5d15e",
    "run/wu_wmax.csv":
        "3ae2f2e2180a3f3b4b0a3d7308ade707de004cace608eecdd658126ab4b4f78f",
    "wu.csv":
        "c37cea69e1732f61d2a9d77674c51b087f9cb744c7c6969a11ceec9f6374098e",
    "wu_summary.csv":
        "14bdae00c03cf98cf2401e899fc00b5b5f9f48335197e7c8bd7d081f31c5d15e",
    "wu_wmax.csv":
        "3ae2f2e2180a3f3b4b0a3d7308ade707de004cace608eecdd658126ab4b4f78f",
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
