"""Speed of `armfit estimate` on a paper-size study (81 trials x 100 s at 1 kHz).

Makes the canonical dataset once (simulator + write_dataset; cached at --data), then times
`armfit estimate DATA -o OUT --jobs 1` and `--jobs 2` as a user runs them (a fresh
process each, best of --repeat), and a plain hand-written scipy script doing the same
reads and Welch estimates in one process (H1 of the stimulated force to the three
positions, and the 4-segment Hamming tfestimate of the derived arm dynamics).
Run: .venv/bin/python benchmarks/bench_estimate.py
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np


def make_dataset(path: Path) -> None:
    from armfit.io.trials import write_dataset
    from armfit.simulate import StudyConfig, simulate_study
    config = StudyConfig(duration_s=(100.0, 100.0), seed=0)
    write_dataset((trial for _, trial in simulate_study(config)), path)


def plain_scipy(path: Path) -> float:
    """Hand-written reference: read each row group, scipy.signal.csd/welch. Seconds."""
    import pyarrow.parquet as pq
    from scipy import signal
    t0 = time.perf_counter()
    pf = pq.ParquetFile(path)
    names = ["force_x_N", "force_y_N", "force_z_N", "pos_x_m", "pos_y_m", "pos_z_m"]
    mp = {0: 0.09, 1: 0.095, 2: 0.091}
    for g in range(pf.num_row_groups):
        t = pf.read_row_group(g, columns=names)
        cols = np.column_stack([t.column(c).to_numpy() for c in names])
        i = int(np.argmax(np.abs(cols[:, :3]).std(axis=0)))  # stimulated axis
        f, pos = cols[:, i], cols[:, 3:].T
        nper = 32768
        _, pff = signal.welch(f, 1000.0, nperseg=nper)
        _, pfx = signal.csd(f, pos, 1000.0, nperseg=nper)
        _, pxx = signal.welch(pos, 1000.0, nperseg=nper)
        _ = pfx / pff, np.abs(pfx) ** 2 / (pff * pxx)
        x = cols[:, 3 + i]
        fa = f[1:-1] - mp[i] * (x[2:] - 2 * x[1:-1] + x[:-2]) * 1e6
        n = fa.size
        L = 2 * n // 5
        nfft = max(256, 1 << int(np.ceil(np.log2(L))))
        win = signal.get_window("hamming", L, fftbins=False)
        _, paa = signal.welch(fa, 1000.0, window=win, noverlap=L // 2, nfft=nfft)
        _, pax = signal.csd(fa, x[1:-1], 1000.0, window=win, noverlap=L // 2, nfft=nfft)
        _ = pax / paa
    return time.perf_counter() - t0


def armfit_cli(data: Path, jobs: int) -> float:
    armfit = Path(sys.executable).with_name("armfit")
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "spectra.parquet"
        t0 = time.perf_counter()
        subprocess.run([str(armfit), "-q", "estimate", str(data), "-o", str(out),
                        "--jobs", str(jobs)], check=True)
        return time.perf_counter() - t0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path,
                    default=Path(tempfile.gettempdir()) / "armfit_bench_81x100s.parquet")
    ap.add_argument("--repeat", type=int, default=2)
    args = ap.parse_args()
    if not args.data.exists():
        t0 = time.perf_counter()
        make_dataset(args.data)
        print(f"dataset: made {args.data} in {time.perf_counter() - t0:.1f} s")
    else:
        print(f"dataset: {args.data} (cached)")
    ref = min(plain_scipy(args.data) for _ in range(args.repeat))
    print(f"plain scipy script (1 process):     {ref:6.2f} s")
    for jobs in (1, 2):
        t = min(armfit_cli(args.data, jobs) for _ in range(args.repeat))
        print(f"armfit estimate --jobs {jobs} (CLI):   {t:6.2f} s  ({t / ref:.2f} x scipy)")


if __name__ == "__main__":
    main()
