"""How long a program reading `armfit`'s output waits after `armfit` itself has ended.

A shell pipeline (`armfit estimate ... | tee log`) or a program that reads a command's
output to its end (`subprocess.run(..., capture_output=True)`) sees end-of-file only when
every process holding the output has ended: `armfit` and, with `--jobs` > 1, its fork
server and resource tracker, which inherited it. Runs `armfit estimate
sample_data/hidden -o OUT --jobs 2 --overwrite` --runs times as a fresh process, its
output read through pipes; per run, the time from its start to the exit of the `armfit`
process (waited for in a thread) and to end-of-file on both pipes; prints the medians
and the wait between the two (the fork server now ends at once, see
`armfit._server_exit`). The load average is printed before and after.

Run: .venv/bin/python benchmarks/bench_pipe.py [--runs 8]
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

from _bytecode import start

ROOT = Path(__file__).resolve().parents[1]


def one_run(cmd: list[str]) -> tuple[float, float]:
    """(seconds to the process's exit, seconds to end-of-file on its output)."""
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            cwd=tempfile.gettempdir())
    ended: dict[str, float] = {}

    def reap() -> None:
        _, status = os.waitpid(proc.pid, 0)
        ended["t"] = time.perf_counter()
        ended["status"] = status

    waiter = threading.Thread(target=reap)
    waiter.start()
    err = []
    reader = threading.Thread(target=lambda: err.append(proc.stderr.read()))
    reader.start()
    proc.stdout.read()
    reader.join()
    eof = time.perf_counter()
    waiter.join()
    proc.returncode = 0     # reaped above
    if ended["status"]:
        raise SystemExit(f"armfit failed: {err[0].decode(errors='replace')}")
    return ended["t"] - t0, eof - t0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=8)
    args = ap.parse_args()
    start()
    exe = str(Path(sys.executable).with_name("armfit"))
    with tempfile.TemporaryDirectory(prefix="armfit-bench-pipe-") as tmp:
        cmd = [exe, "estimate", str(ROOT / "sample_data" / "hidden"), "-o",
               str(Path(tmp) / "spectra.parquet"), "--jobs", "2", "--overwrite"]
        one_run(cmd)     # warm-up: the file cache
        runs = [one_run(cmd) for _ in range(args.runs)]
    exits = [e for e, _ in runs]
    eofs = [f for _, f in runs]
    waits = sorted(f - e for e, f in runs)
    print(f"armfit estimate sample_data/hidden --jobs 2, {args.runs} runs, output read "
          "through pipes:")
    print(f"  process ended after {statistics.median(exits):.3f} s (median), end-of-file "
          f"after {statistics.median(eofs):.3f} s")
    print(f"  wait after the process ended: median {1000 * statistics.median(waits):.0f} ms "
          f"(min {1000 * waits[0]:.0f}, max {1000 * waits[-1]:.0f})")
    print(f"load average {os.getloadavg()[0]:.2f} (1 min)")


if __name__ == "__main__":
    main()
