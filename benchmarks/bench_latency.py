"""Shell-script latency: `armfit estimate` of one trial file and `armfit fit-nominal` of
one spectra file, whole processes, paired run by run with `python -c "import numpy"`
(the same interpreter), so that the ratio survives a loaded machine.

Targets (on an idle machine): each command <= 0.4 s. The ratio to `import numpy`
(about 0.1 s idle) is printed too: 0.4 s is about 3.5 x that.

    .venv/bin/python benchmarks/bench_latency.py [--runs 10]
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_startup import wall  # noqa: E402  (seconds from a command's start to its exit)

ARMFIT = str(Path(sys.executable).with_name("armfit"))
TRIAL = Path(__file__).resolve().parents[1] / "sample_data/study/sub-01_axis-x_grip-1N.parquet"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=10)
    args = ap.parse_args()
    print(f"load average {os.getloadavg()[0]:.2f} (1 min), {os.cpu_count()} cores")
    with tempfile.TemporaryDirectory(prefix="armfit-bench-latency-") as tmp:
        spectra = Path(tmp) / "one.parquet"
        commands = {
            "import numpy": [sys.executable, "-c", "import numpy"],
            "estimate one trial": [ARMFIT, "-q", "estimate", str(TRIAL), "-o", str(spectra),
                                   "--overwrite"],
            "fit-nominal one spectra": [ARMFIT, "-q", "fit-nominal", str(spectra), "-o",
                                        str(Path(tmp) / "nominal.csv"), "--overwrite"],
        }
        for cmd in commands.values():   # warm the file cache (and make the spectra)
            wall(cmd)
        times: dict[str, list[float]] = {name: [] for name in commands}
        for _ in range(args.runs):
            for name, cmd in commands.items():
                times[name].append(wall(cmd))
    base = times.pop("import numpy")
    print(f"{'import numpy':>24}: median {statistics.median(base):.3f} s")
    for name, t in times.items():
        ratios = [a / b for a, b in zip(t, base, strict=True)]
        print(f"{name:>24}: median {statistics.median(t):.3f} s (min {min(t):.3f}), "
              f"{statistics.median(ratios):.1f} x import numpy; target <= 0.4 s")
    print(f"load average {os.getloadavg()[0]:.2f} (1 min)")


if __name__ == "__main__":
    main()
