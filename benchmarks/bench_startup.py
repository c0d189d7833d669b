"""Time the start-up of `armfit --help` against `python -c "import numpy"`, paired run by
run (the ratio of each pair; target <= 2.5), whole processes, with the same interpreter.

    .venv/bin/python benchmarks/bench_startup.py [--runs 15]
"""

from __future__ import annotations

import argparse
import statistics
import subprocess
import sys
import time
from pathlib import Path

from _bytecode import compile_armfit

ARMFIT = str(Path(sys.executable).with_name("armfit"))
COMMANDS = {"armfit --help": [ARMFIT, "--help"],
            "import numpy": [sys.executable, "-c", "import numpy"]}


def wall(cmd: list[str]) -> float:
    """Seconds from the start of ``cmd`` to its exit."""
    t0 = time.perf_counter()
    subprocess.run(cmd, stdout=subprocess.DEVNULL, check=True)
    return time.perf_counter() - t0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=15)
    args = ap.parse_args()
    compile_armfit()    # stale bytecode would be timed too
    for cmd in COMMANDS.values():     # warm the file cache
        wall(cmd)
    times = {name: [] for name in COMMANDS}
    for _ in range(args.runs):
        for name, cmd in COMMANDS.items():
            times[name].append(wall(cmd))
    ratios = [a / b for a, b in zip(*times.values(), strict=True)]
    for name, t in times.items():
        print(f"{name:>15}: median {statistics.median(t):.3f} s "
              f"(min {min(t):.3f}, max {max(t):.3f})")
    print(f"{'ratio':>15}: median {statistics.median(ratios):.2f} "
          f"(min {min(ratios):.2f}, max {max(ratios):.2f}); target <= 2.5")


if __name__ == "__main__":
    main()
