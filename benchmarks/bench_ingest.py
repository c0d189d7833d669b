"""Benchmark of `armfit ingest` on a paper-size study (81 trials x 100 s at 1 kHz).

Generates a random but contract-conforming study with numpy in a temporary folder, as
Parquet and as CSV, then prints:
- ingest time from Parquet (target < 3 s on 2 cores);
- ingest time from CSV, and pyarrow.csv.read_csv alone over the same files (target:
  ingest within 2x of the plain reader);
- peak memory (ru_maxrss of a fresh subprocess) ingesting 20 and 81 trials, to show it
  does not grow with the number of trials.

Run: .venv/bin/python benchmarks/bench_ingest.py [--trials 81] [--seconds 100]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.csv as pcsv
import pyarrow.parquet as pq

from armfit.io.trials import ingest

FS = 1000.0


def make_study(folder: Path, n_trials: int, seconds: float, fmt: str, seed: int = 0) -> None:
    """Write n_trials raw trials (9 subjects x 3 axes x 3 grips order) in ``fmt``."""
    rng = np.random.default_rng(seed)
    n = int(seconds * FS)
    t = np.arange(n) / FS
    k = 0
    for subject in range(1, 100):
        for axis in "xyz":
            for grip in (1, 2, 3):
                if k == n_trials:
                    return
                cols = {"time_s": t}
                for a in "xyz":
                    amp = 1.5 if a == axis else 0.1
                    cols[f"force_{a}_N"] = np.clip(amp * rng.standard_normal(n), -5, 5)
                    cols[f"pos_{a}_m"] = 1e-4 * np.cumsum(rng.standard_normal(n))
                cols["grip_N"] = grip + 0.1 * np.sin(np.floor(t * 65.0))
                table = pa.table(cols)
                path = folder / f"sub-{subject:02d}_axis-{axis}_grip-{grip}N.{fmt}"
                if fmt == "parquet":
                    pq.write_table(table, path)
                else:
                    pcsv.write_csv(table, path)
                k += 1


def timed(fn) -> float:
    t0 = time.perf_counter()
    fn()
    return time.perf_counter() - t0


def peak_memory_mb(folder: Path, out: Path) -> tuple[float, float]:
    """Peak memory (MB) of a fresh interpreter that ingests ``folder`` into ``out``.

    Returns (ru_maxrss, VmHWM). Linux carries ru_maxrss over from the parent across
    fork/exec, so it is measured before this process holds much memory; VmHWM (from
    /proc/self/status) belongs to the child's own address space only.
    """
    code = (
        "import re, resource, sys\n"
        "from armfit.io.trials import ingest\n"
        "ingest([sys.argv[1]], sys.argv[2], overwrite=True)\n"
        "hwm = re.search(r'VmHWM:\\s+(\\d+)', open('/proc/self/status').read())\n"
        "print(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,\n"
        "      int(hwm.group(1)) / 1024 if hwm else float('nan'))\n"
    )
    res = subprocess.run([sys.executable, "-c", code, str(folder), str(out)],
                         check=True, capture_output=True, text=True)
    maxrss, hwm = res.stdout.split()
    return float(maxrss), float(hwm)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--trials", type=int, default=81)
    ap.add_argument("--seconds", type=float, default=100.0)
    ap.add_argument("--small", type=int, default=20, help="trial count of the memory baseline")
    args = ap.parse_args()

    with tempfile.TemporaryDirectory(dir=os.environ.get("BENCH_TMP")) as tmp:
        tmp = Path(tmp)
        pq_dir, csv_dir, small_dir = tmp / "parquet", tmp / "csv", tmp / "small"
        for d in (pq_dir, csv_dir, small_dir):
            d.mkdir()
        t_gen = timed(lambda: make_study(pq_dir, args.trials, args.seconds, "parquet"))
        make_study(small_dir, args.small, args.seconds, "parquet")
        out = tmp / "trials.parquet"
        # Memory first, while this process is still small (see peak_memory_mb).
        m_small = peak_memory_mb(small_dir, tmp / "small.parquet")
        m_full = peak_memory_mb(pq_dir, out)
        t_gen += timed(lambda: make_study(csv_dir, args.trials, args.seconds, "csv"))
        print(f"study: {args.trials} trials x {args.seconds:g} s at {FS:g} Hz "
              f"(generated in {t_gen:.1f} s)")

        t_pq = min(timed(lambda: ingest([pq_dir], out, overwrite=True)) for _ in range(2))
        size = out.stat().st_size / 2**20
        print(f"ingest from Parquet: {t_pq:.2f} s (target < 3 s); dataset {size:.0f} MiB")

        csv_files = sorted(csv_dir.glob("*.csv"))
        t_read = min(timed(lambda: [pcsv.read_csv(f) for f in csv_files]) for _ in range(2))
        t_csv = min(timed(lambda: ingest([csv_dir], out, overwrite=True)) for _ in range(2))
        print(f"pyarrow.csv.read_csv alone: {t_read:.2f} s; ingest from CSV: {t_csv:.2f} s "
              f"= {t_csv / t_read:.2f}x (target <= 2x)")

        print(f"peak memory ingesting from Parquet, ru_maxrss / VmHWM: {args.small} trials "
              f"{m_small[0]:.0f} / {m_small[1]:.0f} MB, {args.trials} trials "
              f"{m_full[0]:.0f} / {m_full[1]:.0f} MB")
        print(json.dumps({"ingest_parquet_s": round(t_pq, 3), "read_csv_s": round(t_read, 3),
                          "ingest_csv_s": round(t_csv, 3),
                          f"maxrss_{args.small}_MB": round(m_small[0]),
                          f"maxrss_{args.trials}_MB": round(m_full[0])}))


if __name__ == "__main__":
    main()
