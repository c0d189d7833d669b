"""Memory of `armfit run` against the number of trials, and the size of its trials.parquet.

Studies of 81, 810 and (with --big) 4,050 trials are simulated once (`armfit simulate -o
DIR --subjects 9 / 90 / 450 --duration D,D`, Parquet trial files as the simulator writes
them by default; --duration, default 60 s, is shorter than the paper's 50-100 s so that
the large study fits on disk and in time) into --dir (cached). Then
`armfit run STUDY -o OUT --jobs 2 --no-figures` runs on each, in turn, --repeat rounds,
and its peak memory is measured as the largest sum of the resident memory (VmRSS of
/proc/PID/status) over the whole process tree: the main process, the fork server and
every worker of every pool (and the resource tracker), sampled every 10 ms by walking
/proc for the descendants of the main process (about 1 ms a walk). Pages shared between
processes (the fork server's imports in its workers) are counted once per process, as a
system monitor adds them up. Sampling can only miss a peak (a stage's read of trial
rows may last a few tens of milliseconds on 81 trials), so the highest peak of the
rounds is kept per study. Printed: the peak per study with the peak of the main process
and of the largest other process, the ratios 810/81 (target <= 1.15) and 4,050/81
(target: flat, <= 1.15), and the size of trials.parquet against the input (target <=
1.0): the Parquet study as simulated, and the 81-trial study also written as CSV
(`--format csv`) with trials.parquet of `armfit ingest` on it. The load average is
printed before and after.

    .venv/bin/python benchmarks/bench_memory.py [--big] [--repeat 2] [--dir /tmp/...]
    .venv/bin/python benchmarks/bench_memory.py --trace STUDY   # one run, RSS over time
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from _bytecode import start

#: Subjects per study (9 axes x grips each): 81, 810 and 4,050 trials.
SUBJECTS = {"81": 9, "810": 90, "4050": 450}
#: Sampling interval of the memory poll, s.
POLL_S = 0.01


def _armfit() -> str:
    return str(Path(sys.executable).with_name("armfit"))


def _children() -> dict[int, list[int]]:
    """{ppid: [pid, ...]} of every process visible in /proc."""
    out: dict[int, list[int]] = {}
    for name in os.listdir("/proc"):
        if not name.isdigit():
            continue
        try:
            with open(f"/proc/{name}/stat", "rb") as fh:
                stat = fh.read()
        except OSError:
            continue
        # the command name may hold blanks and parentheses: the fields follow the last ')'
        ppid = int(stat[stat.rindex(b")") + 2:].split()[1])
        out.setdefault(ppid, []).append(int(name))
    return out


def _tree(root: int) -> list[int]:
    kids = _children()
    found, todo = [], [root]
    while todo:
        pid = todo.pop()
        found.append(pid)
        todo += kids.get(pid, [])
    return found


def _rss_kb(pid: int) -> int:
    try:
        with open(f"/proc/{pid}/status") as fh:
            for line in fh:
                if line.startswith("VmRSS:"):
                    return int(line.split()[1])
    except OSError:
        pass
    return 0


def measure(cmd: list[str], *, trace: bool = False) -> dict:
    """Run ``cmd`` and poll its process tree: peak of the summed VmRSS (MB), peak of the
    main process and of the largest other process (MB), wall time (s)."""
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                            text=True)
    peak = main = other = 0
    last = -1.0
    while proc.poll() is None:
        pids = _tree(proc.pid)
        sizes = {p: _rss_kb(p) for p in pids}
        total = sum(sizes.values())
        peak = max(peak, total)
        main = max(main, sizes.get(proc.pid, 0))
        other = max([other, *(v for p, v in sizes.items() if p != proc.pid)])
        now = time.perf_counter() - t0
        if trace and now - last >= 0.5:
            last = now
            print(f"  {now:7.1f} s  total {total / 1024:7.0f} MB  main "
                  f"{sizes.get(proc.pid, 0) / 1024:6.0f} MB  others "
                  + " ".join(f"{v / 1024:.0f}" for p, v in sorted(sizes.items())
                             if p != proc.pid), flush=True)
        time.sleep(POLL_S)
    err = proc.stderr.read()
    if proc.returncode:
        raise SystemExit(f"{' '.join(cmd)} failed ({proc.returncode}):\n{err}")
    if trace:
        print(err)
    return {"peak_mb": peak / 1024, "main_mb": main / 1024, "other_mb": other / 1024,
            "wall_s": time.perf_counter() - t0}


def simulate(folder: Path, subjects: int, duration: float, fmt: str = "parquet") -> None:
    if folder.exists():
        print(f"study: {folder} (cached)")
        return
    t0 = time.perf_counter()
    subprocess.run([_armfit(), "-q", "simulate", "-o", str(folder), "--subjects",
                    str(subjects), "--duration", f"{duration:g},{duration:g}", "--format", fmt,
                    "--truth", str(folder.with_name(folder.name + ".truth.json"))],
                   check=True)
    print(f"study: simulated {folder} in {time.perf_counter() - t0:.0f} s "
          f"({size(folder) / 1e6:.0f} MB)")


def size(path: Path) -> int:
    if path.is_file():
        return path.stat().st_size
    return sum(p.stat().st_size for p in path.rglob("*") if p.is_file())


def run_cmd(study: Path, out: Path, jobs: int) -> list[str]:
    return [_armfit(), "-q", "run", str(study), "-o", str(out), "--jobs", str(jobs),
            "--no-figures", "--overwrite"]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--big", action="store_true", help="also the 4,050-trial study")
    ap.add_argument("--repeat", type=int, default=2)
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--duration", type=float, default=60.0, help="trial length, s")
    ap.add_argument("--dir", type=Path,
                    default=Path(tempfile.gettempdir()) / "armfit-bench-memory")
    ap.add_argument("--trace", type=Path, default=None, metavar="STUDY",
                    help="one run on STUDY, printing the memory every 0.5 s")
    args = ap.parse_args()
    start()
    if args.trace is not None:
        with tempfile.TemporaryDirectory() as tmp:
            r = measure(run_cmd(args.trace, Path(tmp) / "out", args.jobs), trace=True)
        print(f"peak {r['peak_mb']:.0f} MB (main {r['main_mb']:.0f} MB), "
              f"{r['wall_s']:.0f} s; load average {os.getloadavg()[0]:.2f}")
        return
    args.dir.mkdir(parents=True, exist_ok=True)
    names = ["81", "810", *(["4050"] if args.big else [])]
    studies = {n: args.dir / f"study-{n}-{args.duration:g}s" for n in names}
    for n, folder in studies.items():
        simulate(folder, SUBJECTS[n], args.duration)
    best: dict[str, dict] = {}
    disk: dict[str, float] = {}
    with tempfile.TemporaryDirectory(dir=args.dir) as tmp:
        out = Path(tmp) / "out"
        for r in range(args.repeat):
            for n, folder in studies.items():
                res = measure(run_cmd(folder, out, args.jobs))
                disk[n] = size(out / "trials.parquet") / size(folder)
                print(f"round {r + 1}: {n:>4s} trials: peak {res['peak_mb']:6.0f} MB summed "
                      f"(main {res['main_mb']:5.0f} MB, largest other {res['other_mb']:4.0f} "
                      f"MB), {res['wall_s']:5.0f} s; load {os.getloadavg()[0]:.2f}",
                      flush=True)
                if n not in best or res["peak_mb"] > best[n]["peak_mb"]:
                    best[n] = res
                shutil.rmtree(out)
        # the raw input as CSV: the 81-trial study written as CSV, ingested
        csv = args.dir / f"study-81-{args.duration:g}s-csv"
        simulate(csv, SUBJECTS["81"], args.duration, fmt="csv")
        subprocess.run([_armfit(), "-q", "ingest", str(csv), "-o", str(Path(tmp) / "t.parquet")],
                       check=True)
        csv_ratio = size(Path(tmp) / "t.parquet") / size(csv)
    base = best["81"]["peak_mb"]
    print(f"armfit run STUDY -o OUT --jobs {args.jobs} --no-figures, {args.duration:g} s trials:")
    for n in names:
        print(f"  {n:>4s} trials: peak {best[n]['peak_mb']:6.0f} MB summed over the processes,"
              f" {best[n]['peak_mb'] / base:.2f} x the 81-trial run")
    print(f"  810 / 81 trials: {best['810']['peak_mb'] / base:.2f} x (target <= 1.15)")
    if args.big:
        print(f"  4050 / 81 trials: {best['4050']['peak_mb'] / base:.2f} x (target: flat, "
              "<= 1.15)")
    for n in names:
        print(f"  trials.parquet / Parquet input, {n} trials: {disk[n]:.2f} (target <= 1.0)")
    print(f"  trials.parquet / CSV input, 81 trials: {csv_ratio:.2f} (target <= 1.0)")
    print(f"load average {os.getloadavg()[0]:.2f} (1 min)")


if __name__ == "__main__":
    main()
