"""Fault injection: every way a lab pipeline or a flaky machine breaks armfit, reproduced.

Each test makes one fault happen for real where the machine allows it (a process killed
with SIGKILL, SIGTERM or SIGINT in the middle of a run; a tmpfs that fills up or is
mounted read-only) and otherwise injects it (an OS call monkeypatched to fail), then
checks how armfit ends: the documented exit code (armfit.errors), one line naming the
path and the reason, no traceback, no temporary left behind, no input touched, and the
previous output intact.

The expected values come from the contract itself (exit codes of armfit.errors, the
bounds of armfit.models.arm.BASE_PARAMS) or from the fault (the row and column where a
bad value was written).
"""

from __future__ import annotations

import errno
import hashlib
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from click.testing import CliRunner
from conftest import FAULT_SIM as SIM
from faulttools import ARMFIT, descendants, needs_proc, running, temps, wait_for

from armfit.cli.main import cli
from armfit.errors import (
    EXIT_CANTCREAT,
    EXIT_DATAERR,
    EXIT_INTERRUPTED,
    EXIT_NOINPUT,
    EXIT_TERMINATED,
    BadInputError,
    cell,
)
from armfit.io import atomic
from armfit.io.atomic import atomic_path, clean_stale, write_text_atomic

# the small simulated study every test shares: 2 subjects x axes x, z x grips 1, 2 N


def invoke(*args) -> object:
    return CliRunner().invoke(cli, [str(a) for a in args])



def digest(path: Path) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def one_line_error(text: str) -> str:
    lines = [ln for ln in text.splitlines() if ln.strip()]
    assert "Traceback" not in text, text
    assert lines and lines[-1].startswith("armfit:"), text
    return lines[-1]


def dead_pid() -> int:
    """The pid of a process that has ended (and been reaped)."""
    p = subprocess.Popen([sys.executable, "-c", "pass"])
    p.wait()
    return p.pid


def copy_study(study: Path, dest: Path) -> Path:
    shutil.copytree(study, dest)
    return dest


# ---------------------------------------------------------------------------
# 1. An input is never an output, even with --overwrite
# ---------------------------------------------------------------------------

@pytest.mark.parametrize("command", ["estimate", "ingest", "run"])
def test_output_that_a_folder_input_picks_up_is_refused(command, study, tmp_path):
    raw = copy_study(study, tmp_path / "raw")
    victim = raw / "sub-01_axis-x_grip-1N.parquet"
    before = digest(victim)
    res = invoke(command, raw, "-o", victim, "--overwrite")
    assert res.exit_code == EXIT_CANTCREAT
    line = one_line_error(res.stderr)
    assert str(victim) in line and ("also an input" in line or "not a folder" in line)
    assert digest(victim) == before and temps(raw) == []


def test_new_output_under_a_trial_name_in_an_input_folder_is_refused(study, tmp_path):
    raw = copy_study(study, tmp_path / "raw")
    res = invoke("estimate", raw, "-o", raw / "sub-09_axis-x_grip-1N.parquet")
    assert res.exit_code == EXIT_CANTCREAT
    assert "reading the folder picks it up" in res.stderr
    assert not (raw / "sub-09_axis-x_grip-1N.parquet").exists()


def test_output_that_is_an_explicit_input_or_a_manifest_entry(study, tmp_path):
    raw = copy_study(study, tmp_path / "raw")
    trial = raw / "sub-01_axis-z_grip-2N.parquet"
    before = digest(trial)
    res = invoke("estimate", trial, "-o", trial, "--overwrite")
    assert res.exit_code == EXIT_CANTCREAT and "also an input" in res.stderr
    # listed in a manifest under another name: still an input
    other = raw / "trialA.parquet"
    shutil.copy(trial, other)
    manifest = tmp_path / "m.csv"
    manifest.write_text("file,subject,axis,grip_N\nraw/trialA.parquet,01,z,2\n")
    res = invoke("estimate", "--manifest", manifest, "-o", other, "--overwrite")
    assert res.exit_code == EXIT_CANTCREAT and "manifest" in res.stderr
    assert digest(trial) == before and digest(other) == before


# ---------------------------------------------------------------------------
# 2. Atomic writes: one exclusive temporary, short names, fsync before rename
# ---------------------------------------------------------------------------

def test_temporary_is_created_once_exclusively(tmp_path, monkeypatch):
    dest = tmp_path / "out.csv"
    tokens = iter(["abcd", "abcd", "beef"])
    monkeypatch.setattr(atomic, "_random_hex", lambda n: next(tokens))
    squatter = tmp_path / atomic.temp_name("out.csv")  # the first name is taken
    squatter.write_text("someone else's")
    with atomic_path(dest) as tmp:
        assert tmp.exists() and tmp.name != squatter.name
        assert re.fullmatch(rf"\.out\.csv\.{os.getpid()}\.[0-9a-f]{{4}}beef\.tmp", tmp.name)
        tmp.write_text("mine")
    assert dest.read_text() == "mine" and squatter.read_text() == "someone else's"


def test_temporary_name_is_short_next_to_a_255_byte_name(tmp_path):
    name = "é" * 120 + "x" * 11 + ".csv"  # 255 bytes in UTF-8
    assert len(name.encode()) == 255
    with atomic_path(tmp_path / name) as tmp:
        assert len(tmp.name.encode()) <= 64
        tmp.write_text("ok")
    assert (tmp_path / name).read_text() == "ok"


def test_concurrent_writers_each_land_whole(tmp_path):
    from concurrent.futures import ThreadPoolExecutor
    dest = tmp_path / "out.txt"
    texts = [str(i) * 200_000 for i in range(8)]
    with ThreadPoolExecutor(4) as pool:
        list(pool.map(lambda t: write_text_atomic(dest, t, overwrite=True), texts))
    assert dest.read_text() in texts and temps(tmp_path) == []


def test_file_and_folder_fsynced_before_the_rename(tmp_path, monkeypatch):
    events = []
    real_fsync, real_replace = os.fsync, os.replace
    monkeypatch.setattr(os, "fsync", lambda fd: (events.append("fsync"), real_fsync(fd))[1])
    monkeypatch.setattr(os, "replace", lambda a, b: (events.append("rename"),
                                                      real_replace(a, b))[1])
    real_renameat2 = atomic._renameat2  # a new output is renamed in without replacing
    monkeypatch.setattr(atomic, "_renameat2", lambda a, b, f: (events.append("rename"),
                                                               real_renameat2(a, b, f))[1])
    write_text_atomic(tmp_path / "a.txt", "x")
    assert events == ["fsync", "rename", "fsync"]  # the file, the rename, its folder
    write_text_atomic(tmp_path / "a.txt", "y", overwrite=True)
    assert events[3:] == ["fsync", "rename", "fsync"]  # also when it replaces a file


# ---------------------------------------------------------------------------
# 3. Output folders: exchanged in one step, a crash window that the next run repairs
# ---------------------------------------------------------------------------

def _folder(path: Path, text: str) -> None:
    path.mkdir(parents=True, exist_ok=True)
    (path / "report.md").write_text(text)


def test_folder_exchange_replaces_whole(tmp_path):
    out = tmp_path / "results"
    _folder(out, "old")
    with atomic_path(out, overwrite=True, folder=True) as tmp:
        (tmp / "report.md").write_text("new")
    assert (out / "report.md").read_text() == "new" and temps(tmp_path) == []


def test_folder_swap_fallback_puts_the_old_folder_back_on_failure(tmp_path, monkeypatch):
    out = tmp_path / "results"
    _folder(out, "old")
    monkeypatch.setattr(atomic, "_renameat2", lambda a, b, f: False)  # no RENAME_EXCHANGE
    real_rename = os.rename

    def rename(a, b):
        if str(b) == str(out) and ".tmp" in str(a):
            raise OSError(errno.EIO, "Input/output error")
        return real_rename(a, b)
    monkeypatch.setattr(os, "rename", rename)
    with pytest.raises(OSError):
        with atomic_path(out, overwrite=True, folder=True) as tmp:
            (tmp / "report.md").write_text("new")
    assert (out / "report.md").read_text() == "old" and temps(tmp_path) == []


def test_crash_between_the_two_renames_is_repaired_by_the_next_run(tmp_path):
    out = tmp_path / "results"
    pid = dead_pid()
    tag = atomic._host_tag()
    # the fallback swap died after renaming OUTDIR aside: OUTDIR missing, both copies there
    _folder(tmp_path / f".results.{pid}.{tag}0001.old", "previous")
    _folder(tmp_path / f".results.{pid}.{tag}0002.tmp", "half new")
    done = clean_stale(tmp_path, "results")
    assert len(done) == 2 and (out / "report.md").read_text() == "previous"
    assert temps(tmp_path) == []
    # a live owner's temporary (this process) and another host's are left alone
    mine = tmp_path / atomic.temp_name("results")
    other = tmp_path / f".results.{pid}.{'0000' if tag != '0000' else '0001'}0003.tmp"
    mine.mkdir()
    other.mkdir()
    assert clean_stale(tmp_path, "results") == [] and mine.exists() and other.exists()


def test_folder_output_replaced_whole_and_no_old_copy_left(tmp_path):
    out = tmp_path / "study"
    _folder(out, "previous")
    res = invoke("simulate", "-o", out, "--subjects", "1", "--axes", "x", "--grips", "1",
                 "--duration", "26,26", "--overwrite")
    assert res.exit_code == 0, res.stderr
    assert sorted(p.name for p in out.iterdir()) == ["sub-01_axis-x_grip-1N.parquet"]
    assert temps(tmp_path) == []


# ---------------------------------------------------------------------------
# 4. Signals: SIGKILL, SIGTERM, SIGINT on the installed command
# ---------------------------------------------------------------------------

@needs_proc
def test_sigkill_mid_write_keeps_the_previous_output_and_next_run_cleans(study, tmp_path):
    out = tmp_path / "trials.parquet"
    assert invoke("ingest", study, "-o", out).exit_code == 0
    before = digest(out)
    proc = subprocess.Popen([ARMFIT, "ingest", str(study), "-o", str(out), "--overwrite"],
                            stderr=subprocess.DEVNULL)
    pattern = re.compile(rf"^\.trials\.parquet\.{proc.pid}\.[0-9a-f]{{8}}\.tmp$")
    seen = wait_for(lambda: any(pattern.match(n) for n in os.listdir(tmp_path)))
    proc.kill()
    proc.wait()
    assert seen, "the temporary never appeared"
    assert digest(out) == before                        # the previous output is intact
    assert len(temps(tmp_path)) == 1                    # the dead process's temporary
    res = subprocess.run([ARMFIT, "ingest", str(study), "-o", str(out), "--overwrite"],
                         capture_output=True, text=True)
    assert res.returncode == 0, res.stderr
    assert "left by a run that stopped" in res.stderr   # it says what it removed
    assert temps(tmp_path) == [] and digest(out) == before  # same inputs, same bytes


def _start_estimate(study: Path, out: Path):
    proc = subprocess.Popen([ARMFIT, "estimate", str(study), "-o", str(out), "--jobs", "2"],
                            stderr=subprocess.PIPE, text=True, start_new_session=True)
    kids: set[int] = set()

    def workers_up() -> bool:
        kids.update(descendants(proc.pid))
        return len(kids) >= 2  # the fork server and the resource tracker, then 2 workers
    assert wait_for(workers_up, step=0.02), "no worker processes appeared"
    # the workers start at once: signal while they work
    time.sleep(0.05)
    kids.update(descendants(proc.pid))
    return proc, kids


@needs_proc
@pytest.mark.parametrize("sig, code, group", [
    (signal.SIGTERM, EXIT_TERMINATED, False),
    (signal.SIGINT, EXIT_INTERRUPTED, True),   # Ctrl-C reaches the whole process group
])
def test_signal_during_parallel_estimate(sig, code, group, study, tmp_path):
    out = tmp_path / "s.parquet"
    proc, kids = _start_estimate(study, out)
    if group:
        os.killpg(proc.pid, sig)
    else:
        proc.send_signal(sig)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == code, err
    assert "Traceback" not in err and len(err.strip().splitlines()) == 1, err
    assert err.startswith("armfit: terminated" if sig == signal.SIGTERM
                          else "armfit: interrupted")
    assert wait_for(lambda: not any(running(k) for k in kids), timeout=10, step=0.05), \
        f"worker processes survive: {[k for k in kids if running(k)]}"
    assert not out.exists() and temps(tmp_path) == []


@needs_proc
def test_sigint_at_start_up_is_one_line(study, tmp_path):
    proc = subprocess.Popen([ARMFIT, "estimate", str(study), "-o", str(tmp_path / "s.parquet")],
                            stderr=subprocess.PIPE, text=True)

    def importing_numpy() -> bool:
        try:
            return "numpy" in Path(f"/proc/{proc.pid}/maps").read_text()
        except OSError:
            return False
    assert wait_for(importing_numpy, timeout=30, step=0.001)
    proc.send_signal(signal.SIGINT)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == EXIT_INTERRUPTED, err
    assert err == "armfit: interrupted\n"


# ---------------------------------------------------------------------------
# 12. Write failures: disk full, unwritable folder, parent is a file, -o .
# ---------------------------------------------------------------------------

@pytest.fixture
def small_tmpfs(tmp_path):
    """A 256 KiB tmpfs (root and a kernel that allows it), else the test is skipped."""
    mnt = tmp_path / "mnt"
    mnt.mkdir()

    def mount(*opts):
        r = subprocess.run(["mount", "-t", "tmpfs", "-o", ",".join(("size=256k",) + opts),
                            "tmpfs", str(mnt)], capture_output=True)
        if r.returncode != 0:
            pytest.skip("cannot mount a tmpfs here")
        return mnt
    yield mount
    subprocess.run(["umount", str(mnt)], capture_output=True)


def test_disk_full_on_a_small_tmpfs(study, small_tmpfs):
    mnt = small_tmpfs()
    out = mnt / "trials.parquet"
    res = invoke("ingest", study, "-o", out)          # ~13 MB into 256 KiB
    assert res.exit_code == EXIT_CANTCREAT
    line = one_line_error(res.stderr)
    assert str(out) in line and "No space left on device" in line
    assert os.listdir(mnt) == []                       # the temporary is gone


def test_disk_full_injected(study, tmp_path, monkeypatch):
    def full(fd):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
    monkeypatch.setattr(os, "fsync", full)
    out = tmp_path / "spectra.parquet"
    res = invoke("estimate", study, "-o", out)
    assert res.exit_code == EXIT_CANTCREAT
    assert f"{out}: cannot write: No space left on device" in one_line_error(res.stderr)
    assert os.listdir(tmp_path) == []


def test_read_only_folder(study, small_tmpfs):
    mnt = small_tmpfs("ro")
    res = invoke("estimate", study, "-o", mnt / "s.parquet")
    assert res.exit_code == EXIT_CANTCREAT
    assert "Read-only file system" in one_line_error(res.stderr)


def test_unwritable_folder_injected(study, tmp_path, monkeypatch):
    real_open = os.open

    def no_access(path, flags, *a, **k):
        if str(path).startswith(str(tmp_path / "locked")) and flags & os.O_CREAT:
            raise PermissionError(errno.EACCES, os.strerror(errno.EACCES), str(path))
        return real_open(path, flags, *a, **k)
    (tmp_path / "locked").mkdir()
    monkeypatch.setattr(os, "open", no_access)
    out = tmp_path / "locked" / "s.parquet"
    res = invoke("estimate", study, "-o", out)
    assert res.exit_code == EXIT_CANTCREAT
    assert f"{out}: cannot write: Permission denied" in one_line_error(res.stderr)


@pytest.mark.parametrize("command", ["estimate", "ingest", "run", "simulate"])
def test_parent_is_a_regular_file(command, study, tmp_path):
    (tmp_path / "plain.txt").write_text("x")
    out = tmp_path / "plain.txt" / "out.parquet"
    args = [command, "-o", out] + (SIM if command == "simulate" else [study])
    res = invoke(*args)
    assert res.exit_code == EXIT_CANTCREAT, res.stderr
    line = one_line_error(res.stderr)
    assert str(out) in line and ("is a file" in line or "Not a directory" in line)


def test_output_dot(study, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "keep.txt").write_text("mine")
    res = invoke("estimate", study, "-o", ".", "--overwrite")
    assert res.exit_code == EXIT_CANTCREAT
    assert "is a folder" in one_line_error(res.stderr)
    res = invoke("run", study, "-o", ".", "--overwrite")
    assert res.exit_code == EXIT_CANTCREAT
    assert "never replaced" in one_line_error(res.stderr)
    assert (tmp_path / "keep.txt").read_text() == "mine"


# ---------------------------------------------------------------------------
# 5-6. Folders that cannot be read, symlinked folders, manifests with holes
# ---------------------------------------------------------------------------

def test_unreadable_subfolder(study, tmp_path, monkeypatch):
    raw = copy_study(study, tmp_path / "raw")
    sub = raw / "more"
    sub.mkdir()
    shutil.move(raw / "sub-02_axis-z_grip-2N.parquet", sub)
    real_scandir = os.scandir

    def scandir(path="."):
        if Path(path) == sub:
            raise PermissionError(errno.EACCES, os.strerror(errno.EACCES), str(path))
        return real_scandir(path)
    monkeypatch.setattr(os, "scandir", scandir)
    res = invoke("estimate", raw, "-o", tmp_path / "s.parquet")
    assert res.exit_code == EXIT_NOINPUT
    assert f"{sub}: cannot read the folder: Permission denied" in one_line_error(res.stderr)
    res = invoke("estimate", raw, "-o", tmp_path / "s.parquet", "--skip-bad")
    assert res.exit_code == 0 and f"skipped {sub}: cannot read the folder" in res.stderr


def test_symlinked_subfolder(study, tmp_path):
    raw = copy_study(study, tmp_path / "raw")
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    shutil.move(raw / "sub-02_axis-z_grip-2N.parquet", elsewhere)
    (raw / "linked").symlink_to(elsewhere, target_is_directory=True)
    res = invoke("ingest", raw, "-o", tmp_path / "t.parquet")
    assert res.exit_code == EXIT_NOINPUT
    assert "symlinked folder, not followed" in one_line_error(res.stderr)
    res = invoke("ingest", raw, "-o", tmp_path / "t.parquet", "--skip-bad", "--json")
    assert res.exit_code == 0
    assert '"reason": "symlinked folder, not followed' in res.stdout


def test_manifest_row_with_a_missing_file_and_paths(study, tmp_path):
    raw = copy_study(study, tmp_path / "raw")
    manifest = tmp_path / "m.csv"
    manifest.write_text("file,subject,axis,grip_N\nraw/sub-01_axis-x_grip-1N.parquet,01,x,1\n"
                        "raw/gone.parquet,03,x,1\n")
    res = invoke("estimate", raw, "--manifest", manifest, "-o", tmp_path / "s.parquet")
    assert res.exit_code == EXIT_NOINPUT
    assert "column 'file', row 2" in res.stderr and "gone.parquet: no such file" in res.stderr


# ---------------------------------------------------------------------------
# 7. Ambiguous data
# ---------------------------------------------------------------------------

def test_duplicate_column_header(tmp_path, make_columns):
    cols = make_columns("x", grip_N=1.0)
    path = tmp_path / "sub-01_axis-x_grip-1N.csv"
    names = list(cols) + ["pos_x_m"]
    lines = [",".join(names)] + [",".join(repr(float(v)) for v in row)
                                 for row in zip(*cols.values(), cols["pos_x_m"], strict=True)]
    path.write_text("\n".join(lines[:200]) + "\n")
    res = invoke("ingest", path, "-o", tmp_path / "t.parquet", "--fmin", "2")
    assert res.exit_code == EXIT_DATAERR
    assert "column 'pos_x_m': duplicate column header" in one_line_error(res.stderr)


def test_non_numeric_grip_in_the_column_file_name_and_manifest(tmp_path, write_trial,
                                                               make_columns):
    cols = make_columns("x", grip_N=1.0)
    grip = [repr(float(v)) for v in cols["grip_N"]]
    grip[6] = "n/a"
    cols["grip_N"] = grip
    path = write_trial(tmp_path / "a" / "sub-01_axis-x_grip-1N.csv", cols)
    res = invoke("ingest", path, "-o", tmp_path / "t.parquet")
    assert res.exit_code == EXIT_DATAERR
    assert "column 'grip_N', row 7: non-numeric value 'n/a'" in res.stderr
    bad_name = write_trial(tmp_path / "b" / "sub-01_axis-x_grip-NaN.csv", axis="x")
    res = invoke("ingest", bad_name, "-o", tmp_path / "t.parquet")
    assert res.exit_code == EXIT_DATAERR and "grip 'NaN' in the file name" in res.stderr
    good = write_trial(tmp_path / "c" / "trial.csv", axis="x")
    manifest = tmp_path / "c" / "m.csv"
    manifest.write_text("file,subject,axis,grip_N\ntrial.csv,01,x,n/a\n")
    res = invoke("ingest", "--manifest", manifest, "-o", tmp_path / "t.parquet")
    assert res.exit_code == EXIT_DATAERR
    assert "column 'grip_N', row 1: grip 'n/a'" in res.stderr and good.exists()


def test_positions_in_millimetres_under_a_metre_column(tmp_path, write_trial, make_columns):
    cols = make_columns("y", grip_N=1.0)
    cols["pos_y_m"] = cols["pos_y_m"] * 1000.0 + 100.0  # mm, 100 mm off the origin
    path = write_trial(tmp_path / "sub-01_axis-y_grip-1N.parquet", cols)
    res = invoke("ingest", path, "-o", tmp_path / "t.parquet")
    assert res.exit_code == EXIT_DATAERR
    line = one_line_error(res.stderr)
    assert "column 'pos_y_m', row 1" in line and "name the column pos_y_mm" in line


def test_manifest_row_with_an_unknown_axis(tmp_path, write_trial):
    write_trial(tmp_path / "t.csv", axis="x")
    manifest = tmp_path / "m.csv"
    manifest.write_text("file,subject,axis,grip_N\nt.csv,01,w,1\n")
    res = invoke("ingest", "--manifest", manifest, "-o", tmp_path / "t.parquet")
    assert res.exit_code == EXIT_DATAERR
    assert "column 'axis', row 1: axis 'w' is not x, y or z" in res.stderr


def test_spectra_or_params_rows_of_an_unknown_axis(spectra, nominal, tmp_path):
    df = pd.read_parquet(spectra)
    df.loc[df.index[5], "axis"] = "w"
    bad = tmp_path / "s.parquet"
    df.to_parquet(bad)
    res = invoke("fit-nominal", bad, "-o", tmp_path / "n.csv")
    assert res.exit_code == EXIT_DATAERR
    assert f"{bad}, column 'axis', row 6: axis 'w' is not x, y or z" in res.stderr
    p = pd.read_csv(nominal)
    p.loc[1, "axis"] = "q"
    badp = tmp_path / "p.csv"
    p.to_csv(badp, index=False)
    res = invoke("fit-uncertainty", spectra, "--nominal", badp, "-o", tmp_path / "wu.csv")
    assert res.exit_code == EXIT_DATAERR
    assert f"{badp}, column 'axis', row 2: axis 'q' is not x, y or z" in res.stderr


def test_grip_in_the_name_differs_from_the_grip_column(tmp_path, write_trial):
    path = write_trial(tmp_path / "sub-01_axis-x_grip-1N.csv", grip_N=3.0)  # sensor: 3 N
    res = invoke("ingest", path, "-o", tmp_path / "t.parquet")
    assert res.exit_code == 0
    assert (f"warning: {path}, column 'grip_N': the measured grip (3 N, median) differs "
            "from the 1 N") in res.stderr


def test_params_file_with_unknown_effect_columns(nominal, tmp_path):
    df = pd.read_csv(nominal)
    for col, expect in (("gravity.g", "unknown effect 'gravity'"),
                        ("delay.delay_s", "parameter of the effect 'delay', which no row "
                                         "lists in the column 'effects'")):
        bad = tmp_path / "p.csv"
        df.assign(**{col: 0.01}).to_csv(bad, index=False)
        res = invoke("fit-uncertainty", nominal.parent / "spectra.parquet", "--nominal", bad,
                     "-o", tmp_path / "wu.csv")
        assert res.exit_code == EXIT_DATAERR
        assert f"{bad}, column '{col}': {expect}" in one_line_error(res.stderr)


# ---------------------------------------------------------------------------
# 8-10. Values outside physics
# ---------------------------------------------------------------------------

@pytest.mark.parametrize("command", ["estimate", "run", "ingest"])
def test_force_of_1e308(command, tmp_path, write_trial, make_columns):
    cols = make_columns("x", grip_N=1.0)
    cols["force_x_N"][99] = 1e308
    write_trial(tmp_path / "raw" / "sub-01_axis-x_grip-1N.csv", cols)
    out = tmp_path / ("out" if command == "run" else "out.parquet")
    res = invoke(command, tmp_path / "raw", "-o", out)
    assert res.exit_code == EXIT_DATAERR, res.stderr
    line = one_line_error(res.stderr)
    assert "sub-01_axis-x_grip-1N.csv, column 'force_x_N', row 100: value 1e+308" in line
    assert not out.exists()


def test_parameter_outside_its_bounds(nominal, tmp_path):
    bad = tmp_path / "p.csv"
    df = pd.read_csv(nominal)
    df.loc[1, "Ma"] = 1e308
    df.to_csv(bad, index=False)
    res = invoke("fit-uncertainty", nominal.parent / "spectra.parquet", "--nominal", bad,
                 "-o", tmp_path / "wu.csv")
    assert res.exit_code == EXIT_DATAERR
    # armfit.models.arm.BASE_PARAMS: Ma in [0.01, 30] kg
    assert (f"{bad}, column 'Ma', row 2: Ma = 1e+308 kg is outside its physical range "
            "[0.01, 30] kg") in one_line_error(res.stderr)


@pytest.mark.parametrize("row, what", [("x,pole,1,5,0", "unstable"),
                                       ("x,zero,1,0.5,2", "not minimum phase")])
def test_unstable_or_non_minimum_phase_wu(row, what, nominal, tmp_path):
    wu = tmp_path / "wu_bad.csv"
    wu.write_text(f"axis,kind,index,real,imag\nx,gain,0,2,0\nx,zero,1,-3,1\n{row}\n"
                  "z,gain,0,1,0\n")
    res = invoke("fit-uncertainty", nominal.parent / "spectra.parquet", "--nominal", nominal,
                 "-o", tmp_path / "wu.csv", "--check-weights", wu)
    assert res.exit_code == EXIT_DATAERR
    line = one_line_error(res.stderr)
    # the offending row is the file's third data row
    assert f"{wu}, column 'real', row 3: Wu of axis x is {what}" in line
    assert not (tmp_path / "wu.csv").exists()


# ---------------------------------------------------------------------------
# 11. Real recordings: unstimulated axes recorded as zeros
# ---------------------------------------------------------------------------

def test_zero_unstimulated_axes_give_flagged_nan_not_inf(tmp_path, write_trial, make_columns):
    for s in (1, 2):
        cols = make_columns("x", seed=s, grip_N=1.0, duration_s=30.0)
        for a in "yz":
            cols[f"force_{a}_N"] = np.zeros_like(cols["time_s"])
            cols[f"pos_{a}_m"] = np.zeros_like(cols["time_s"])
        write_trial(tmp_path / "raw" / f"sub-0{s}_axis-x_grip-1N.csv", cols)
    out = tmp_path / "s.parquet"
    res = invoke("estimate", tmp_path / "raw", "-o", out)  # RuntimeWarning = test error
    assert res.exit_code == 0, res.stderr
    df = pd.read_parquet(out)
    assert not np.isinf(df.select_dtypes("number").to_numpy(float, na_value=np.nan)).any()
    cross = df[df["kind"] == "cross"]
    assert cross["mag_db"].isna().all() and cross["flags"].str.contains("no_signal").all()
    # per trial 2 cross responses x 100 grid points; mean and median one each per axis
    assert len(cross) == 2 * 2 * 100 + 2 * 100 + 2 * 100
    measured = df[df["kind"] != "cross"]
    assert np.isfinite(measured["mag_db"]).all()
    assert not measured["flags"].str.contains("no_signal").any()
    assert res.stderr.count("all frequencies carry no signal (position y is constant") == 2
    assert "left out of the mean and median" in res.stderr


# ---------------------------------------------------------------------------
# 13. Messages and exit codes
# ---------------------------------------------------------------------------

def test_a_huge_cell_is_cut(tmp_path, write_trial, make_columns):
    cols = make_columns("x", grip_N=1.0)
    force = [repr(float(v)) for v in cols["force_x_N"]]
    force[3] = "z" * 1_000_000
    cols["force_x_N"] = force
    path = write_trial(tmp_path / "sub-01_axis-x_grip-1N.csv", cols)
    res = invoke("ingest", path, "-o", tmp_path / "t.parquet")
    assert res.exit_code == EXIT_DATAERR
    line = one_line_error(res.stderr)
    assert len(line) < 400 and "(1000000 characters)" in line and "row 4" in line


def test_numbers_print_as_numbers(tmp_path, write_trial, make_columns):
    cols = make_columns("x", grip_N=1.0)
    cols["time_s"][5] = cols["time_s"][4]
    path = write_trial(tmp_path / "sub-01_axis-x_grip-1N.parquet", cols)
    res = invoke("ingest", path, "-o", tmp_path / "t.parquet")
    assert res.exit_code == EXIT_DATAERR
    assert "non-monotonic time: 0.04 s follows 0.04 s" in res.stderr
    assert "np.float64" not in res.stderr
    assert cell(np.float64(0.25)) == "0.25" and cell(np.int64(3)) == "3"


def test_exit_code_table_is_documented():
    import armfit.errors as errors
    text = invoke("--help").output
    for code, word in ((65, "bad input"), (66, "not found"), (73, "cannot be written"),
                       (130, "SIGINT"), (143, "SIGTERM")):
        assert f"{code} " in text and word in text
        assert re.search(rf"^{code}\s", errors.__doc__, re.M)


@pytest.mark.parametrize("args", [
    ["ingest", "{missing}", "-o", "{out}.parquet"],
    ["estimate", "{missing}", "-o", "{out}.parquet"],
    ["run", "{missing}", "-o", "{out}"],
    ["fit-grip", "{missing}", "-o", "{out}.csv"],
    ["fit-nominal", "{missing}", "-o", "{out}.csv"],
    ["fit-uncertainty", "{missing}", "--nominal", "{missing}", "-o", "{out}.csv"],
    ["diagnose", "{missing}", "--model", "{missing}"],
    ["compare", "{missing}", "--model", "{missing}"],
    ["plot", "bode", "{missing}", "-o", "{out}.png"],
    ["estimate", "--manifest", "{missing}", "-o", "{out}.parquet"],
])
def test_missing_input_is_66_on_every_command(args, tmp_path):
    filled = [a.format(missing=tmp_path / "nope", out=tmp_path / "out") for a in args]
    res = invoke(*filled)
    assert res.exit_code == EXIT_NOINPUT, (res.exit_code, res.output)
    assert str(tmp_path / "nope") in one_line_error(res.stderr)


@pytest.mark.parametrize("command", ["ingest", "estimate", "fit-grip", "fit-nominal",
                                     "plot", "run", "simulate", "fit-uncertainty"])
def test_existing_output_is_73_on_every_command(command, study, spectra, nominal, tmp_path):
    out = tmp_path / {"run": "out", "simulate": "out", "ingest": "out.parquet"}.get(
        command, "out.csv")
    if command in ("run", "simulate"):
        out.mkdir()
    else:
        out.write_text("keep")
    args = {"ingest": [study], "estimate": [study], "fit-grip": [spectra],
            "fit-nominal": [spectra], "plot": ["bode", spectra],
            "run": [study], "simulate": SIM,
            "fit-uncertainty": [spectra, "--nominal", nominal]}[command]
    if command == "plot":
        out = out.with_suffix(".png")
        out.write_text("keep")
    res = invoke(*(([command] if command != "plot" else ["plot"]) + args + ["-o", out]))
    assert res.exit_code == EXIT_CANTCREAT, res.output
    assert "exists; pass --overwrite" in one_line_error(res.stderr)


def test_bad_input_error_names_file_column_row():
    e = BadInputError("bad", file="f.csv", column="force_x_N", row=3)
    assert str(e) == "f.csv, column 'force_x_N', row 3: bad"


def _interrupted_while_a_class_is_created(*args, **kwargs):
    """What a SIGINT raises when it lands while Python creates a class during a lazy import:
    Python (3.11) wraps the KeyboardInterrupt of ``__set_name__`` in a RuntimeError."""
    class Field:
        def __set_name__(self, owner, name):
            raise KeyboardInterrupt

    class Stream:  # noqa: F841 - creating it is the point
        skipped = Field()


@pytest.mark.parametrize("command", ["estimate", "fit-nominal"])
def test_a_signal_that_python_wrapped_is_a_stop_not_a_bug(command, study, tmp_path,
                                                           monkeypatch):
    """A stop is a stop (code 130, one line) even when Python wrapped its KeyboardInterrupt
    in another exception, as it does in ``__set_name__`` while a module is imported."""
    monkeypatch.setattr("armfit.cli.estimate.estimate_study_result",
                        _interrupted_while_a_class_is_created)
    monkeypatch.setattr("armfit.cli.fit.api_fit_nominal", _interrupted_while_a_class_is_created)
    spectra = tmp_path / "s.parquet"
    if command == "fit-nominal":
        monkeypatch.undo()
        assert CliRunner().invoke(cli, ["estimate", str(study), "-o", str(spectra)]).exit_code == 0
        monkeypatch.setattr("armfit.cli.fit.api_fit_nominal",
                            _interrupted_while_a_class_is_created)
    args = ([command, str(study), "-o", str(tmp_path / "s2.parquet")] if command == "estimate"
            else [command, str(spectra), "-o", str(tmp_path / "nom.csv")])
    result = CliRunner().invoke(cli, args)
    assert result.exit_code == EXIT_INTERRUPTED, result.output
    assert "internal error" not in result.output
    with pytest.raises(RuntimeError) as caught:
        _interrupted_while_a_class_is_created()
    from armfit.cli.entry import wrapped_stop
    assert isinstance(wrapped_stop(caught.value), KeyboardInterrupt)
    assert wrapped_stop(RuntimeError("a bug")) is None
