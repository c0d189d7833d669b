"""Shell-script latency: `armfit estimate` of one trial file and `armfit fit-nominal` of
one spectra file, whole processes, paired run by run with `python -c "import numpy"`
(the same interpreter), so that the ratio survives a loaded machine.

Targets: each command <= 0.4 s where `python -c "import numpy"` takes 0.07-0.077 s
(`armfit --help` took 0.77-0.85 s there, 11 x `import numpy`): as a ratio measured in
one run, <= 5.2 x `import numpy` (0.4 / 0.077), which is what the script checks. The
absolute times are printed too; they move with the machine.

Each command is also paired with its libraries' floor: a fresh process that imports
every module outside armfit and the standard library that the command imports (found
by running it once with `python -X importtime`), and nothing else. What the command
takes beyond that floor is armfit's own share: its imports, reading, computing and
writing.

    .venv/bin/python benchmarks/bench_latency.py [--runs 10]
"""

from __future__ import annotations

import argparse
import importlib.util
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _bytecode import start  # noqa: E402
from bench_startup import wall  # noqa: E402  (seconds from a command's start to its exit)

ARMFIT = str(Path(sys.executable).with_name("armfit"))
TRIAL = Path(__file__).resolve().parents[1] / "sample_data/study/sub-01_axis-x_grip-1N.parquet"
ENTRY = "from armfit.cli.entry import main; main()"
#: The target as a ratio to `import numpy` (see the module docstring).
TARGET_RATIO = 0.4 / 0.077
#: The libraries' floor: import the modules named on the command line, in order (an
#: import that fails, as it failed in the command, is passed over).
FLOOR = """
import importlib, sys
for name in sys.argv[1:]:
    try:
        importlib.import_module(name)
    except Exception:
        pass
"""


def library_imports(args: list[str]) -> list[str]:
    """The modules outside armfit and the standard library that ``armfit ARGS`` imports,
    in the order their imports end (``python -X importtime``; a module only looked for,
    such as ``sitecustomize``, is left out; one whose import failed is kept: the floor
    tries it too)."""
    res = subprocess.run([sys.executable, "-X", "importtime", "-c", ENTRY, *args],
                         capture_output=True, text=True, check=True)
    names = []
    for line in res.stderr.splitlines():
        if not line.startswith("import time:") or line.count("|") != 2:
            continue
        name = line.rsplit("|", 1)[1].strip()
        root = name.split(".")[0]
        if (name == "imported package" or root == "armfit" or root.startswith("_")
                or root in sys.stdlib_module_names or name in names):
            continue
        try:
            found = importlib.util.find_spec(name) is not None
        except (ImportError, ValueError):
            found = False
        if found:
            names.append(name)
    return names


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=10)
    args = ap.parse_args()
    start()
    with tempfile.TemporaryDirectory(prefix="armfit-bench-latency-") as tmp:
        spectra = Path(tmp) / "one.parquet"
        runs = {
            "estimate one trial": ["-q", "estimate", str(TRIAL), "-o", str(spectra),
                                   "--overwrite"],
            "fit-nominal one spectra": ["-q", "fit-nominal", str(spectra), "-o",
                                        str(Path(tmp) / "nominal.csv"), "--overwrite"],
        }
        commands = {"import numpy": [sys.executable, "-c", "import numpy"]}
        floors = {}
        for name, cmd in runs.items():
            commands[name] = [ARMFIT, *cmd]
            wall(commands[name])          # warm the file cache (and make the spectra)
            modules = library_imports(cmd)
            floors[name] = sorted({m.split(".")[0] for m in modules})
            commands[f"{name}: floor"] = [sys.executable, "-c", FLOOR, *modules]
        for cmd in commands.values():
            wall(cmd)
        times: dict[str, list[float]] = {name: [] for name in commands}
        for _ in range(args.runs):
            for name, cmd in commands.items():
                times[name].append(wall(cmd))
    base = times.pop("import numpy")
    print(f"{'import numpy':>24}: median {statistics.median(base):.3f} s")
    for name in runs:
        t, floor = times[name], times[f"{name}: floor"]
        ratios = [a / b for a, b in zip(t, base, strict=True)]
        share = [a - b for a, b in zip(t, floor, strict=True)]
        ratio = statistics.median(ratios)
        print(f"{name:>24}: median {statistics.median(t):.3f} s (min {min(t):.3f}), "
              f"{ratio:.2f} x import numpy (median of the pairs; target <= "
              f"{TARGET_RATIO:.1f} x: {'met' if ratio <= TARGET_RATIO else 'not met'})")
        print(f"{'its libraries alone':>24}: median {statistics.median(floor):.3f} s "
              f"(importing {', '.join(floors[name])}); armfit's own share "
              f"{statistics.median(share):.3f} s (median of the pairs)")
    print(f"load average {os.getloadavg()[0]:.2f} (1 min)")


if __name__ == "__main__":
    main()
