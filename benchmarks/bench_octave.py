"""Speed of `armfit estimate` against GNU Octave doing the same estimation (optional).

Both run as a user runs them, a fresh process each, on the paper-size study of
bench_estimate.py (9 subjects x 3 axes x 3 grips = 81 trials, 75-100 s at 1 kHz, made
once with armfit's simulator and cached at --data; this script imports bench_estimate
for it, so both benchmarks time the same study):

- armfit: ``armfit -q estimate DATA -o OUT --jobs 1 --overwrite``;
- Octave: ``octave-cli --norc --quiet --no-history SCRIPT FOLDER``, SCRIPT a program this
  benchmark writes to a temporary file (MATLAB argument conventions, ``pwelch('R12+')``).
  Per trial it reads the samples (fread), then does what armfit's estimator does
  (armfit.spectra ``estimate_trial``): the H1 of the stimulated force to the three
  positions by Welch, ``tfestimate(F, X, hann(nperseg, 'periodic'), nperseg/2, nperseg,
  fs)`` and ``mscohere`` with the same arguments, nperseg as armfit's
  ``EstimateConfig.h1_nperseg`` chooses it for the trial's length and rate; and the
  derived arm dynamics Fa = F - Mp*x'', xa by ``tfestimate`` and ``mscohere`` with 4
  half-overlapped Hamming segments, ``hamming(L)``, L = floor(2N/5), nfft = max(256,
  2^nextpow2(L)). Each of these calls makes its own Welch pass, as MATLAB code is
  usually written; a second program gets each response's H and coherence from one
  ``pwelch(F, X, ..., 'trans', 'coher')`` (one pass instead of two: the fastest way with
  Octave's signal package). Both programs are timed (``--calls both``, the default), or
  one (``--calls tfestimate`` or ``--calls pwelch``).

Octave cannot read Parquet: the trials are exported once into --octave-dir (one file of
float64 samples per trial, written by numpy ``tofile``: the stimulated force then the
three positions; and a text index of file, fs, n and stimulated axis). That export is
not timed; Octave's reading of those files is. The Octave side leaves out what armfit
also does: validating the samples (time column, finite values, saturation), averaging
the native bins onto the common grid with standard errors, flags (coherence, drift,
saturation), aggregates and writing the spectra file; it reads only the four columns it
needs and keeps its results in memory. In all this the comparison is favourable to
Octave.

Octave's FFTW runs one thread (``fftw('threads', 1)``; --octave-threads to change), as
armfit --jobs 1 computes on one core; each round prints the wall and CPU time and the
peak resident memory of each process.

Before timing, the Octave program's H1 and coherence of trial 0 are checked against
armfit's native-bin ``welch_spectra`` of the same trial (relative difference < 1e-6 at
the bins armfit uses, first_bin and above, where the coherence is > 0.5), so that both
sides compute the same thing; the largest difference is printed. (The derived responses
are not compared here: MATLAB's tfestimate, and so this one, keeps each segment's mean,
armfit removes it; tests/test_bench_octave.py compares them with Octave's per-segment
mean removal, pwelch 'short'.) The commands then run alternately, --repeat rounds; the
script prints each round, the best of each and the ratio armfit / Octave of the best
wall times (target: <= 1.0, armfit at least on par; also of the best CPU times, steadier
on a loaded machine), with the Octave version and the load average at start and end.
Without ``octave-cli`` (or ``octave``) on PATH, or without Octave's signal package, it
says so and exits 0: Octave is optional (Debian: ``apt-get install octave
octave-signal``).

    .venv/bin/python benchmarks/bench_octave.py [--repeat 3] [--calls both|tfestimate|pwelch]
        [--octave-threads 1]
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

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import bench_estimate  # noqa: E402  (the study both benchmarks time, the armfit command)
from _bytecode import compile_armfit  # noqa: E402

#: Relative difference allowed between Octave's and armfit's H1 and coherence.
TOLERANCE = 1e-6

#: The Octave program; {fmin} and {mp} are filled in from armfit's defaults, the spectral
#: calls from :data:`CALLS`, {threads} is the number of FFTW threads. Arguments: FOLDER
#: [CHECKFILE]; with CHECKFILE only trial 0 is estimated and its frequencies, H1 (real,
#: imaginary) and coherence are written there as float64 columns.
OCTAVE_SCRIPT = r"""
1;
pkg load signal
pwelch("R12+");  % MATLAB's arguments: overlap in samples (and no mean removal)
fftw("threads", {threads});
args = argv();
folder = args{{1}};
check = "";
if numel(args) > 1
  check = args{{2}};
end
fmin = {fmin!r};
mp = [{mp}];
fid = fopen(fullfile(folder, "index.txt"), "r");
idx = textscan(fid, "%s %f %f %f");
fclose(fid);
names = idx{{1}}; fsv = idx{{2}}; nv = idx{{3}}; axv = idx{{4}};
ntr = numel(names);
if !isempty(check)
  ntr = 1;
end
results = cell(ntr, 1);
for t = 1:ntr
  fs = fsv(t); n = nv(t); ax = axv(t);
  fid = fopen(fullfile(folder, names{{t}}), "r");
  d = fread(fid, [n, 4], "double");
  fclose(fid);
  F = d(:, 1); X = d(:, 2:4);
  outs = [ax, setdiff(find(all(isfinite(X), 1)), ax)];
  % H1 segment length: armfit's EstimateConfig.h1_nperseg
  seg = 2 ^ ceil(log2(2 * fs / fmin));
  shortest = 2 ^ ceil(log2(fs / fmin));
  while seg > shortest && floor((n - seg / 2) / (seg / 2)) < 4
    seg = seg / 2;
  end
  win = hann(seg, "periodic");
  H = zeros(seg / 2 + 1, numel(outs)); C = H;
  for k = 1:numel(outs)
{h1_calls}  end
  % derived arm dynamics: Fa = F - Mp x'', xa; 4 half-overlapped Hamming segments
  x = X(:, ax);
  Fa = F(2:end-1) - mp(ax) * (x(3:end) - 2 * x(2:end-1) + x(1:end-2)) * fs ^ 2;
  xa = x(2:end-1);
  L = floor(2 * numel(Fa) / 5);
  nfft = max(256, 2 ^ nextpow2(L));
{derived_calls}  results{{t}} = {{f, H, C, fa, Ha, Ca}};
end
if !isempty(check)
  fid = fopen(check, "w");
  fwrite(fid, [f, real(H), imag(H), C], "double");
  fclose(fid);
end
"""


#: The spectral calls of the Octave program: "tfestimate" (tfestimate and mscohere, each
#: its own Welch pass) or "pwelch" (one pwelch pass giving both).
CALLS = {
    "tfestimate": (
        "    [H(:, k), f] = tfestimate(F, X(:, outs(k)), win, seg / 2, seg, fs);\n"
        "    C(:, k) = mscohere(F, X(:, outs(k)), win, seg / 2, seg, fs);\n",
        "  [Ha, fa] = tfestimate(Fa, xa, hamming(L), floor(L / 2), nfft, fs);\n"
        "  Ca = mscohere(Fa, xa, hamming(L), floor(L / 2), nfft, fs);\n"),
    "pwelch": (
        '    [S, f] = pwelch(F, X(:, outs(k)), win, seg / 2, seg, fs, "trans", "coher");\n'
        "    H(:, k) = S(:, 1); C(:, k) = S(:, 2);\n",
        '  [S, fa] = pwelch(Fa, xa, hamming(L), floor(L / 2), nfft, fs, "trans", "coher");\n'
        "  Ha = S(:, 1); Ca = S(:, 2);\n"),
}


def octave_program() -> str | None:
    """The Octave interpreter to run (``octave-cli``, else ``octave``), or None."""
    return shutil.which("octave-cli") or shutil.which("octave")


def octave_cmd(octave: str, script: Path, *args: Path) -> list[str]:
    # --no-history: Octave 7 otherwise reports "error: ignoring const
    # execution_exception& while preparing to exit" (exit status 0) at every exit
    cmd = [octave, "--norc", "--quiet", "--no-history"]
    if Path(octave).name == "octave":
        cmd.append("--no-gui")
    return [*cmd, str(script), *map(str, args)]


def octave_version(octave: str) -> str:
    """'GNU Octave X, signal Y'; raises CalledProcessError without the signal package."""
    code = ("pkg load signal; s = pkg('list', 'signal'); "
            "printf('GNU Octave %s, signal package %s\\n', version, s{1}.version)")
    out = subprocess.run([octave, "--norc", "--quiet", "--no-history", "--eval", code],
                         check=True, capture_output=True, text=True).stdout
    return out.strip().splitlines()[-1]


def write_script(path: Path, calls: str = "tfestimate", threads: int = 1) -> None:
    """Write the Octave program with armfit's default fmin and device masses."""
    from armfit.constants import AXES
    from armfit.spectra import EstimateConfig
    config = EstimateConfig()
    h1_calls, derived_calls = CALLS[calls]
    path.write_text(OCTAVE_SCRIPT.format(
        fmin=float(config.fmin), mp=" ".join(repr(float(config.mp[a])) for a in AXES),
        h1_calls=h1_calls, derived_calls=derived_calls, threads=int(threads)))


def export_trials(data: Path, folder: Path) -> None:
    """One float64 file per trial (stimulated force, positions x, y, z) and index.txt.

    Not timed. Kept while the dataset's size and modification time are unchanged.
    """
    stamp = f"{data.stat().st_size} {data.stat().st_mtime_ns}\n"
    index = folder / "index.txt"
    if index.exists() and (folder / "source.txt").read_text() == stamp:
        print(f"Octave's copy of the trials: {folder} (cached)")
        return
    from armfit.io.trials import open_trials
    folder.mkdir(parents=True, exist_ok=True)
    lines = []
    for k, trial in enumerate(open_trials([data])):
        m = trial.meta
        name = f"trial{k:03d}.f64"
        cols = np.vstack([trial.f, trial.pos.T])  # (4, n): each signal contiguous
        np.ascontiguousarray(cols, dtype="<f8").tofile(folder / name)
        lines.append(f"{name} {m.fs!r} {m.n_samples} {m.axis_index + 1}\n")
    (folder / "source.txt").write_text(stamp)
    tmp = folder / "index.txt.tmp"
    tmp.write_text("".join(lines))
    tmp.replace(index)
    print(f"Octave's copy of the trials: wrote {len(lines)} files to {folder}")


def check_same_h1(data: Path, folder: Path, octave: str, script: Path, out: Path, *,
                  label: str = "") -> float:
    """Max relative difference of Octave's and armfit's H1 (and coherence) of trial 0.

    Raises AssertionError above :data:`TOLERANCE`.
    """
    from armfit.io.trials import open_trials
    from armfit.spectra import EstimateConfig, welch_spectra
    subprocess.run(octave_cmd(octave, script, folder, out), check=True)
    trial = next(iter(open_trials([data])))
    m = trial.meta
    outs = [m.axis_index] + [j for j in range(3)
                             if j != m.axis_index and np.all(np.isfinite(trial.pos[:, j]))]
    nper = EstimateConfig().h1_nperseg(m.fs, m.n_samples)
    sp = welch_spectra(trial.f, trial.pos[:, outs], m.fs, nperseg=nper)
    k = len(outs)
    oct_ = np.fromfile(out, dtype="<f8").reshape(1 + 3 * k, -1)
    freq, h = oct_[0], oct_[1:1 + k] + 1j * oct_[1 + k:1 + 2 * k]
    coh = oct_[1 + 2 * k:]
    assert freq.shape == sp.freq_hz.shape and np.allclose(freq, sp.freq_hz, rtol=1e-12)
    # Octave keeps each segment's mean (MATLAB's convention), armfit removes it: with a
    # periodic Hann window and nfft = nperseg that changes only bins below first_bin,
    # which armfit never uses
    use = (sp.coherence > 0.5) & (np.arange(freq.size) >= sp.first_bin)
    rel_h = np.max(np.abs(h - sp.h)[use] / np.abs(sp.h)[use])
    rel_c = np.max(np.abs(coh - sp.coherence)[use] / sp.coherence[use])
    print(f"check {label}, trial 0 ({m.axis}, {m.n_samples} samples, nperseg {nper}): "
          f"{int(use.sum())} bins with coherence > 0.5, max relative difference "
          f"Octave vs armfit: H1 {rel_h:.1e}, coherence {rel_c:.1e} (limit {TOLERANCE:g})")
    assert rel_h < TOLERANCE and rel_c < TOLERANCE, "Octave and armfit compute different H1"
    return max(rel_h, rel_c)


def load() -> str:
    return " ".join(f"{x:.2f}" for x in os.getloadavg())


def measured(cmd: list[str]) -> tuple[float, float, float]:
    """Run ``cmd``; its (wall s, CPU s of user and system, peak RSS MB), from os.wait4."""
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd)
    _, status, usage = os.wait4(proc.pid, 0)
    wall = time.perf_counter() - t0
    proc.returncode = os.waitstatus_to_exitcode(status)
    if proc.returncode:
        raise subprocess.CalledProcessError(proc.returncode, cmd)
    return wall, usage.ru_utime + usage.ru_stime, usage.ru_maxrss / 1024.0  # kB on Linux


def timed_rounds(commands: dict[str, list[str]], repeat: int
                 ) -> tuple[dict[str, float], dict[str, float]]:
    """Run the commands alternately, ``repeat`` rounds; print each round. Returns the best
    wall and the best CPU time of each command."""
    wall = dict.fromkeys(commands, float("inf"))
    cpu = dict(wall)
    for r in range(repeat):
        parts = []
        for name, cmd in commands.items():
            t, c, rss = measured(cmd)
            wall[name], cpu[name] = min(wall[name], t), min(cpu[name], c)
            parts.append(f"{name} {t:5.2f} s (CPU {c:5.2f} s, {rss:.0f} MB)")
        print(f"round {r + 1}: " + " | ".join(parts))
    return wall, cpu


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path,
                    default=Path(tempfile.gettempdir()) / "armfit_bench_81x75-100s.parquet")
    ap.add_argument("--octave-dir", type=Path, default=None,
                    help="Octave's copy of the trials (default: next to --data)")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--calls", choices=[*CALLS, "both"], default="both",
                    help="Octave's spectral calls: tfestimate and mscohere, one pwelch(..., "
                         "'trans', 'coher') per response, or both programs (default)")
    ap.add_argument("--octave-threads", type=int, default=1,
                    help="FFTW threads of Octave (default 1, as armfit --jobs 1 computes "
                         "on one core; Octave's own default is one per core)")
    args = ap.parse_args()
    compile_armfit()    # stale bytecode would be timed too
    octave = octave_program()
    if octave is None:
        print("bench_octave: octave not on PATH, skipped (optional; Debian: apt-get install "
              "octave octave-signal)")
        return
    try:
        version = octave_version(octave)
    except subprocess.CalledProcessError:
        print(f"bench_octave: {octave} has no signal package, skipped (Debian: apt-get "
              "install octave-signal)")
        return
    print(f"{version} ({octave}), {args.octave_threads} FFTW thread(s); load average at "
          f"start {load()}")
    bench_estimate.ensure(args.data)
    folder = args.octave_dir or args.data.with_name(args.data.stem + "_octave")
    export_trials(args.data, folder)
    calls = list(CALLS) if args.calls == "both" else [args.calls]
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        commands = {}
        for c in calls:
            script = tmp / f"estimate_{c}.m"
            write_script(script, c, args.octave_threads)
            check_same_h1(args.data, folder, octave, script, tmp / "check.f64", label=c)
            commands[f"Octave {c}"] = octave_cmd(octave, script, folder)
        arm = "armfit estimate --jobs 1"
        commands[arm] = bench_estimate.armfit_cmd(args.data, tmp / "spectra.parquet")
        wall, cpu = timed_rounds(commands, args.repeat)
    print("best: " + ", ".join(f"{name} {wall[name]:.2f} s (CPU {cpu[name]:.2f} s)"
                               for name in commands))
    for name in commands:
        if name != arm:
            print(f"armfit / {name}: {wall[arm] / wall[name]:.2f} (target <= 1.0); "
                  f"CPU time {cpu[arm] / cpu[name]:.2f}")
    print(f"load average at end {load()}")


if __name__ == "__main__":
    main()
