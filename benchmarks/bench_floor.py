"""`armfit estimate` and `armfit run` against the floor: what reading the study and one
FFT per signal cost, whole processes, ratios measured in one session.

The floor is a fresh Python process that reads every trial with pyarrow (all columns)
and takes one real FFT of each force and position column, zero-padded to a fast length
(scipy.fft.next_fast_len): the least any estimator of these spectra must do. It is
run alternately with

- `armfit estimate DATA -o OUT --jobs 1` on a canonical dataset (the paper-size study of
  benchmarks/bench_estimate.py: 81 trials, 75-100 s at 1 kHz; `--scale` adds the
  810-trial dataset of its --scale mode). Target: estimate / floor <= 1.3.
- `armfit run STUDY -o OUT --jobs 2 --no-figures` (and, with `--figures`, with the
  figures) on the same study written as raw Parquet trial files by `armfit simulate`,
  against the floor on those files. Target: run / floor <= 3.
- `--jobs 2` against `--jobs 1` for both commands (target: never slower, <= 1.0).

The commands are run in rounds, one of each per round in turn, --repeat rounds. Each
ratio is taken within a round (the two commands saw the same load) and the median of
the rounds' ratios is the figure; the best time of each command is printed beside it.
The load average is printed at the start and the end (a shared machine inflates and
scatters the times: compare the ratios), and so is what two cores give together: one
CPU-bound process (a pure-Python loop) timed alone and two of them started at once, in
rounds, twice the best time alone over the best time of the pair (2.0 where each core is
a core of its own; less where the two share a physical core or a host's other guests take their
turn). `run -j2` runs two workers beside its own process while the floor is one process:
on a machine whose two cores give 1.6 times one core's work, the run's ratio to the floor
is higher than on one whose two give 2.0, with the same code.

    .venv/bin/python benchmarks/bench_floor.py [--repeat 3] [--scale] [--figures]
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import bench_estimate  # noqa: E402  (the datasets, made once and cached)
from _bytecode import start  # noqa: E402

ARMFIT = str(Path(sys.executable).with_name("armfit"))

FLOOR = r"""
import sys
from pathlib import Path
import numpy as np
import pyarrow.parquet as pq
from scipy.fft import next_fast_len, rfft
target = Path(sys.argv[1])
files = sorted(target.glob("*.parquet")) if target.is_dir() else [target]
for path in files:
    pf = pq.ParquetFile(path)
    for g in range(pf.num_row_groups):
        table = pf.read_row_group(g)
        for name in table.column_names:
            if name.startswith(("force_", "pos_")):
                x = table.column(name).to_numpy()
                if np.isfinite(x).all():
                    rfft(x, n=next_fast_len(x.size, real=True))
"""


SPIN = "x = 0\nfor i in range(6_000_000):\n    x += i\n"


def two_core_capacity(rounds: int = 3) -> float:
    """Twice the best wall time of one CPU-bound process alone over the best of two
    started at once (``rounds`` of each, alternated): how many cores' work the machine
    gives two processes, 2.0 where each core is a core of its own."""
    cmd = [sys.executable, "-c", SPIN]
    alone, pair = [], []
    for _ in range(rounds):
        alone.append(wall(cmd))
        t0 = time.perf_counter()
        procs = [subprocess.Popen(cmd) for _ in range(2)]
        for p in procs:
            p.wait()
        pair.append(time.perf_counter() - t0)
    return 2 * min(alone) / min(pair)


def wall(cmd: list[str]) -> float:
    """Seconds from the start of ``cmd`` (a fresh process) to its exit."""
    t0 = time.perf_counter()
    subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL)
    return time.perf_counter() - t0


class Rounds:
    """Wall times of commands run in rounds, one of each per round in turn."""

    def __init__(self, commands: dict[str, list[str]], repeat: int):
        self.times = [{name: wall(cmd) for name, cmd in commands.items()}
                      for _ in range(repeat)]

    def best(self, name: str) -> float:
        """The command's best time (s)."""
        return min(t[name] for t in self.times)

    def ratio(self, a: str, b: str) -> float:
        """The median over the rounds of time(a) / time(b) within each round."""
        return statistics.median(t[a] / t[b] for t in self.times)


def floor_cmd(target: Path) -> list[str]:
    return [sys.executable, "-c", FLOOR, str(target)]


def estimate_rows(data: Path, tmp: Path, repeat: int, label: str) -> None:
    out = tmp / "spectra.parquet"
    est = [ARMFIT, "-q", "estimate", str(data), "-o", str(out), "--overwrite"]
    t = Rounds({"floor": floor_cmd(data), "j1": [*est, "--jobs", "1"],
                "j2": [*est, "--jobs", "2"]}, repeat)
    print(f"{label}: floor {t.best('floor'):6.2f} s | estimate -j1 {t.best('j1'):6.2f} s "
          f"({t.ratio('j1', 'floor'):.2f} x floor; target <= 1.3) | -j2 "
          f"{t.best('j2'):6.2f} s ({t.ratio('j2', 'j1'):.2f} x -j1; target <= 1.0)")


def run_rows(tmp: Path, repeat: int, figures: bool) -> None:
    study = tmp / "study"
    subprocess.run([ARMFIT, "-q", "simulate", "-o", str(study), "--seed", "1",
                    "--format", "parquet"], check=True)
    n = len(list(study.glob("*.parquet")))
    cmds = {"floor": floor_cmd(study)}
    for jobs in (1, 2):
        cmds[f"j{jobs}"] = [ARMFIT, "-q", "run", str(study), "-o", str(tmp / f"out{jobs}"),
                            "--jobs", str(jobs), "--overwrite",
                            *([] if figures else ["--no-figures"])]
    t = Rounds(cmds, repeat)
    what = "run" + ("" if figures else " --no-figures")
    print(f"{what} ({n} raw trials): floor {t.best('floor'):6.2f} s | -j2 "
          f"{t.best('j2'):6.2f} s ({t.ratio('j2', 'floor'):.2f} x floor; target <= 3) | "
          f"-j1 {t.best('j1'):6.2f} s (-j2 / -j1 {t.ratio('j2', 'j1'):.2f}; target <= 1.0)")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--scale", action="store_true", help="also the 810-trial dataset")
    ap.add_argument("--figures", action="store_true", help="time run with its figures")
    ap.add_argument("--data", type=Path, default=Path(tempfile.gettempdir())
                    / "armfit_bench_81x75-100s.parquet")
    args = ap.parse_args()
    start()
    print(f"two cores give {two_core_capacity():.2f} x one core's work (two CPU-bound "
          "processes at once against one, best of 3 each; 2.00 where each core is a core "
          "of its own)")
    bench_estimate.ensure(args.data)
    with tempfile.TemporaryDirectory(prefix="armfit-bench-floor-") as tmp:
        estimate_rows(args.data, Path(tmp), args.repeat, "81 trials")
        if args.scale:
            large = Path(tempfile.gettempdir()) / "armfit_bench_810x75s.parquet"
            bench_estimate.ensure(large, subjects=90, duration_s=(75.0, 75.0))
            estimate_rows(large, Path(tmp), max(1, args.repeat - 1), "810 trials")
        run_rows(Path(tmp), args.repeat, args.figures)
    print(f"load average {os.getloadavg()[0]:.2f} (1 min); two cores give "
          f"{two_core_capacity():.2f} x one core's work")


if __name__ == "__main__":
    main()
