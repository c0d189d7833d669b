"""How outputs are committed: each output, and all outputs of one command, appear whole or
not at all, also when another run writes the same output, when a folder turns out to be
read-only at the end, when a process is killed in the middle of the commit, and when a
name is over the system's limits.

The expectations come from the contract in docs/cli-conventions.md ("How outputs are
committed") and armfit.errors (exit 73: an output cannot be written); the bytes of a
previous output are read before the fault and compared after it. Faults are made real
where the machine allows it (a read-only tmpfs, a process killed with SIGKILL, two
processes racing, a user without write permission) and injected otherwise.
"""

from __future__ import annotations

import errno
import hashlib
import logging
import os
import re
import shutil
import signal
import subprocess
import sys
import tempfile
import textwrap
import time
from pathlib import Path

import pytest
from click.testing import CliRunner
from conftest import FAULT_SIM as SIM
from faulttools import ARMFIT

from armfit.cli.main import cli
from armfit.errors import EXIT_CANTCREAT, OutputError
from armfit.io import atomic
from armfit.io.atomic import atomic_path, clean_stale, write_text_atomic

#: armfit's temporaries, set-aside copies and journals (docs/cli-conventions.md)
LEFTOVER = re.compile(r"^\..*\.\d+\.[0-9a-f]{8}\.(tmp|old|txn)$")

# a small simulated study: 2 subjects x axes x, z x grips 1, 2 N

APPEARED = "appeared while it was being written (another run?); nothing replaced"


def invoke(*args):
    return CliRunner().invoke(cli, [str(a) for a in args])


def leftovers(*folders: Path) -> list[str]:
    return sorted(p.name for f in folders if Path(f).is_dir() for p in Path(f).iterdir()
                  if LEFTOVER.match(p.name))


def digest(path: Path) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def tree(folder: Path) -> dict[str, str]:
    """{relative path: sha256} of every file under ``folder``."""
    return {str(p.relative_to(folder)): digest(p) for p in sorted(Path(folder).rglob("*"))
            if p.is_file()}


def one_line_error(text: str) -> str:
    lines = [ln for ln in text.splitlines() if ln.strip()]
    assert "Traceback" not in text, text
    assert lines and lines[-1].startswith("armfit: error:"), text
    return lines[-1]


def not_called(*args, **kwargs):
    raise AssertionError("the work started although an output could not be written")


@pytest.fixture
def tmpfs(tmp_path):
    """Mount a small tmpfs (root and a kernel that allows it), else skip the test."""
    mounted = []

    def mount(where: Path, *opts: str) -> Path:
        where.mkdir(parents=True, exist_ok=True)
        r = subprocess.run(["mount", "-t", "tmpfs", "-o", ",".join(("size=256k",) + opts),
                            "tmpfs", str(where)], capture_output=True)
        if r.returncode != 0:
            pytest.skip("cannot mount a tmpfs here")
        mounted.append(where)
        return where
    yield mount
    for where in reversed(mounted):
        subprocess.run(["umount", "-l", str(where)], capture_output=True)


def fail_rename_of(monkeypatch, name: str, err: int = errno.EROFS) -> None:
    """Make the rename of a temporary onto ``name`` fail with ``err``, whichever
    system call renames it."""
    real_replace, real_rename, real_r2 = os.replace, os.rename, atomic._renameat2

    def refuse(b):
        if Path(b).name == name:
            raise OSError(err, os.strerror(err), str(b))

    def replace(a, b, **kw):
        refuse(b)
        return real_replace(a, b, **kw)

    def rename(a, b, **kw):
        if ".tmp" in Path(a).name:
            refuse(b)
        return real_rename(a, b, **kw)

    def renameat2(a, b, flags):
        refuse(b)
        return real_r2(a, b, flags)
    monkeypatch.setattr(os, "replace", replace)
    monkeypatch.setattr(os, "rename", rename)
    monkeypatch.setattr(atomic, "_renameat2", renameat2)


# ---------------------------------------------------------------------------
# 1. Another run writes the same output meanwhile: without --overwrite it is never
#    replaced (exit 73), whichever system call commits
# ---------------------------------------------------------------------------

def _no_renameat2(monkeypatch):
    monkeypatch.setattr(atomic, "_renameat2", lambda a, b, f: False)


def _no_links(monkeypatch):
    _no_renameat2(monkeypatch)

    def link(*a, **k):
        raise OSError(errno.EPERM, os.strerror(errno.EPERM))
    monkeypatch.setattr(os, "link", link)


FALLBACKS = {"renameat2": lambda mp: None, "hard link": _no_renameat2,
             "neither": _no_links}


def _appear_after_the_check(monkeypatch, make) -> None:
    """Run ``make()`` right after the commit's last check of the destinations, so that
    only the renaming system call itself can refuse to replace it."""
    real = atomic.OutputSet._check_at_commit

    def check(self, e):
        real(self, e)
        make()
    monkeypatch.setattr(atomic.OutputSet, "_check_at_commit", check)


@pytest.mark.parametrize("fallback", FALLBACKS)
def test_a_file_that_appears_before_the_rename_is_not_replaced(fallback, tmp_path,
                                                                monkeypatch):
    dest = tmp_path / "out.csv"
    FALLBACKS[fallback](monkeypatch)
    _appear_after_the_check(monkeypatch, lambda: dest.write_text("theirs"))
    with pytest.raises(OutputError, match=re.escape(APPEARED)):
        with atomic_path(dest) as tmp:
            tmp.write_text("mine")
    assert dest.read_text() == "theirs" and leftovers(tmp_path) == []


@pytest.mark.parametrize("fallback", ["renameat2", "hard link"])
def test_a_folder_that_appears_before_the_rename_is_not_replaced(fallback, tmp_path,
                                                                  monkeypatch):
    dest = tmp_path / "results"
    FALLBACKS[fallback](monkeypatch)

    def theirs():
        dest.mkdir()
        (dest / "report.md").write_text("theirs")
    _appear_after_the_check(monkeypatch, theirs)
    with pytest.raises(OutputError, match=re.escape(APPEARED)):
        with atomic_path(dest, folder=True) as tmp:
            (tmp / "report.md").write_text("mine")
    assert tree(dest) == {"report.md": hashlib.sha256(b"theirs").hexdigest()}
    assert leftovers(tmp_path) == []


def test_an_empty_folder_that_appears_is_not_replaced_either(tmp_path, monkeypatch):
    # rename(2) replaces an empty folder: the fallback claims the name with mkdir first
    dest = tmp_path / "results"
    _no_renameat2(monkeypatch)
    _appear_after_the_check(monkeypatch, dest.mkdir)
    with pytest.raises(OutputError, match=re.escape(APPEARED)):
        with atomic_path(dest, folder=True) as tmp:
            (tmp / "report.md").write_text("mine")
    assert dest.is_dir() and list(dest.iterdir()) == [] and leftovers(tmp_path) == []


def test_estimate_output_written_by_another_run_meanwhile(study, tmp_path, monkeypatch):
    import pyarrow.parquet as pq
    out = tmp_path / "s.parquet"
    real_close = pq.ParquetWriter.close

    def close(self):  # the other run commits while this one writes its temporary
        real_close(self)
        if not out.exists():
            out.write_bytes(b"the other run's spectra")
    monkeypatch.setattr(pq.ParquetWriter, "close", close)
    res = invoke("estimate", study, "-o", out)
    assert res.exit_code == EXIT_CANTCREAT, res.output
    assert one_line_error(res.stderr) == f"armfit: error: {out}: {APPEARED}"
    assert out.read_bytes() == b"the other run's spectra" and leftovers(tmp_path) == []


def test_run_outdir_written_by_another_run_meanwhile(study, tmp_path, monkeypatch):
    from armfit import pipeline
    out = tmp_path / "results"

    def work(inputs, folder, options, **kw):  # the stages, then another run commits
        (folder / "report.md").write_text("mine")
        out.mkdir()
        (out / "report.md").write_text("theirs")
    monkeypatch.setattr(pipeline, "_run_in", work)
    with pytest.raises(OutputError, match=re.escape(APPEARED)):
        pipeline.run_pipeline([study], out)
    assert (out / "report.md").read_text() == "theirs" and leftovers(tmp_path) == []


def test_simulate_study_written_by_another_run_meanwhile(tmp_path, monkeypatch):
    from armfit import api
    out = tmp_path / "study"
    real_write = api.write_trial

    def write_trial(*a, **k):
        if not out.exists():
            out.mkdir()
            (out / "theirs.txt").write_text("theirs")
        return real_write(*a, **k)
    monkeypatch.setattr(api, "write_trial", write_trial)
    res = invoke("simulate", "-o", out, *SIM)
    assert res.exit_code == EXIT_CANTCREAT, res.output
    assert APPEARED in one_line_error(res.stderr)
    assert sorted(p.name for p in out.iterdir()) == ["theirs.txt"]
    assert not (tmp_path / "study.truth.json").exists()   # neither output of the run
    assert leftovers(tmp_path) == []


_SLOW_WRITER = textwrap.dedent("""
    import sys, time
    import pyarrow.parquet as pq
    close = pq.ParquetWriter.close

    def slow_close(self):  # the spectra file takes a while to write
        close(self)
        time.sleep(1.5)
    pq.ParquetWriter.close = slow_close
    from armfit.cli.entry import main
    sys.argv = ["armfit", *sys.argv[1:]]
    main()
""")


def test_two_concurrent_estimates_one_wins_whole(study, tmp_path):
    # `(armfit estimate A -o s.parquet) & (sleep 0.3; armfit estimate B -o s.parquet)`,
    # two real processes, each writing its temporary for 1.5 s so that both are
    # writing at once: one exits 0, the other 73 at its commit, and the output is
    # exactly the winner's (its bytes when run alone)
    half = tmp_path / "half"
    half.mkdir()
    for p in sorted(study.iterdir())[:4]:
        shutil.copy(p, half)
    refs = {}
    for name, src in (("all", study), ("half", half)):
        refs[name] = tmp_path / f"ref_{name}.parquet"
        assert invoke("estimate", src, "-o", refs[name]).exit_code == 0
    out = tmp_path / "s.parquet"
    procs = {}
    for name, src in (("all", study), ("half", half)):
        procs[name] = subprocess.Popen([sys.executable, "-c", _SLOW_WRITER, "estimate",
                                        str(src), "-o", str(out)],
                                       stderr=subprocess.PIPE, text=True)
        time.sleep(0.3)
    codes = {name: p.wait(120) for name, p in procs.items()}
    errs = {name: p.stderr.read() for name, p in procs.items()}
    assert sorted(codes.values()) == [0, EXIT_CANTCREAT], errs
    winner = next(n for n, c in codes.items() if c == 0)
    loser = next(n for n, c in codes.items() if c != 0)
    assert one_line_error(errs[loser]) == f"armfit: error: {out}: {APPEARED}"
    assert digest(out) == digest(refs[winner])
    assert leftovers(tmp_path) == []


# ---------------------------------------------------------------------------
# 2. Several outputs of one command: all committed, or every one as before
# ---------------------------------------------------------------------------

def test_fit_grip_latex_in_a_read_only_folder_is_refused_before_the_fit(spectra, tmp_path,
                                                                         tmpfs, monkeypatch):
    ro = tmpfs(tmp_path / "ro", "ro")
    grip = tmp_path / "grip.csv"
    grip.write_text("previous grip fits\n")
    monkeypatch.setattr("armfit.cli.fit.api_fit_grip", not_called)
    res = invoke("fit-grip", spectra, "-o", grip, "--latex", ro / "t.tex", "--overwrite")
    assert res.exit_code == EXIT_CANTCREAT, res.output
    line = one_line_error(res.stderr)
    assert str(ro / "t.tex") in line and "Read-only file system" in line
    assert grip.read_text() == "previous grip fits\n" and leftovers(tmp_path) == []


@pytest.mark.parametrize("previous", [True, False], ids=["replacing", "new"])
def test_fit_grip_latex_refused_at_the_commit_keeps_the_csv(previous, spectra, tmp_path,
                                                            monkeypatch):
    # the LaTeX folder turns read-only between the checks and the commit
    out = tmp_path / "new" / "grip.csv"   # its folder is made for it
    tex = tmp_path / "tables" / "t.tex"
    tex.parent.mkdir()
    if previous:
        out.parent.mkdir()
        out.write_text("previous grip fits\n")
        tex.write_text("previous table\n")
    before = tree(tmp_path)
    fail_rename_of(monkeypatch, "t.tex")
    res = invoke("fit-grip", spectra, "-o", out, "--latex", tex, "--overwrite")
    assert res.exit_code == EXIT_CANTCREAT, res.output
    assert one_line_error(res.stderr) == f"armfit: error: {tex}: cannot write: " \
                                         "Read-only file system"
    assert tree(tmp_path) == before                   # nothing replaced, nothing new
    assert out.parent.exists() == previous            # the folder made for it is gone
    assert leftovers(tmp_path, out.parent, tex.parent) == []


def test_estimate_csv_on_a_full_disk_keeps_the_parquet(study, tmp_path, monkeypatch):
    out, csv = tmp_path / "s.parquet", tmp_path / "s.csv"
    out.write_bytes(b"previous spectra")
    csv.write_text("previous csv\n")
    before = tree(tmp_path)
    real = atomic._fsync_path

    def fsync(path, directory=False):  # the disk fills up while the CSV is written
        if Path(path).name.startswith(".s.csv."):
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        return real(path, directory)
    monkeypatch.setattr(atomic, "_fsync_path", fsync)
    res = invoke("estimate", study, "-o", out, "--csv", csv, "--overwrite")
    assert res.exit_code == EXIT_CANTCREAT, res.output
    assert one_line_error(res.stderr) == f"armfit: error: {csv}: cannot write: " \
                                         "No space left on device"
    assert tree(tmp_path) == before and leftovers(tmp_path) == []


@pytest.mark.parametrize("failing", ["wu.tex", "wu_wmax.csv"])
def test_fit_uncertainty_keeps_every_output_when_one_fails(failing, spectra, nominal,
                                                           tmp_path, monkeypatch):
    names = ["wu.csv", "wu_summary.csv", "wu_wmax.csv", "wu.tex"]
    for n in names:
        (tmp_path / n).write_text(f"previous {n}\n")
    before = tree(tmp_path)
    fail_rename_of(monkeypatch, failing, errno.EACCES)
    res = invoke("fit-uncertainty", spectra, "--nominal", nominal, "-o", tmp_path / "wu.csv",
                 "--latex", tmp_path / "wu.tex", "--overwrite")
    assert res.exit_code == EXIT_CANTCREAT, res.output
    assert f"{tmp_path / failing}: cannot write: Permission denied" in \
        one_line_error(res.stderr)
    assert tree(tmp_path) == before and leftovers(tmp_path) == []


@pytest.mark.parametrize("failing", ["truth", "study"])
def test_simulate_keeps_the_study_and_its_truth_when_one_fails(failing, tmp_path,
                                                               monkeypatch):
    out, truth = tmp_path / "study", tmp_path / "study.truth.json"
    out.mkdir()
    (out / "sub-01_axis-x_grip-1N.parquet").write_bytes(b"previous trial")
    truth.write_text("previous truth\n")
    before = tree(tmp_path)
    fail_rename_of(monkeypatch, {"truth": truth.name, "study": out.name}[failing])
    res = invoke("simulate", "-o", out, *SIM, "--overwrite")
    assert res.exit_code == EXIT_CANTCREAT, res.output
    assert "Read-only file system" in one_line_error(res.stderr)
    assert tree(tmp_path) == before and leftovers(tmp_path) == []


def test_interrupt_in_the_middle_of_the_commit_rolls_back(tmp_path, monkeypatch):
    # SIGINT/SIGTERM become exceptions; one raised between two renames undoes the first
    (tmp_path / "b.txt").write_text("old b")
    real = atomic._commit_one
    calls = []

    def commit_one(e, *, several):
        calls.append(e.dest.name)
        if len(calls) == 2:
            raise KeyboardInterrupt
        real(e, several=several)
    monkeypatch.setattr(atomic, "_commit_one", commit_one)
    with pytest.raises(KeyboardInterrupt):
        with atomic.atomic_outputs(overwrite=True):
            write_text_atomic(tmp_path / "a.txt", "new a")
            write_text_atomic(tmp_path / "b.txt", "new b", overwrite=True)
    assert calls == ["a.txt", "b.txt"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["b.txt"]
    assert (tmp_path / "b.txt").read_text() == "old b"


@pytest.mark.parametrize("fallback", ["renameat2", "hard link"])
def test_a_replaced_folder_is_put_back_when_a_later_output_fails(fallback, tmp_path,
                                                                  monkeypatch):
    folder, truth = tmp_path / "study", tmp_path / "truth.json"
    folder.mkdir()
    (folder / "old.txt").write_text("old trial")
    truth.write_text("old truth")
    before = tree(tmp_path)
    FALLBACKS[fallback](monkeypatch)
    fail_rename_of(monkeypatch, truth.name, errno.ENOSPC)
    with pytest.raises(OutputError, match=f"{re.escape(str(truth))}: cannot write"):
        with atomic.atomic_outputs(overwrite=True):
            with atomic_path(folder, overwrite=True, folder=True) as tmp:
                (tmp / "new.txt").write_text("new trial")
            write_text_atomic(truth, "new truth", overwrite=True)
    assert tree(tmp_path) == before and leftovers(tmp_path) == []


# ---------------------------------------------------------------------------
# 2b. A process killed (SIGKILL) in the commit: what it leaves, and the repair
# ---------------------------------------------------------------------------

_KILLED_WRITER = textwrap.dedent("""
    import os, signal, sys
    from pathlib import Path
    from armfit.io import atomic
    when, *dests = sys.argv[1:]
    real_commit_one, real_remove = atomic._commit_one, atomic._remove
    done = []

    def commit_one(e, *, several):
        if when == "mid" and len(done) == 2:
            os.kill(os.getpid(), signal.SIGKILL)
        real_commit_one(e, several=several)
        done.append(e.dest)

    def remove(path):
        why = real_remove(path)
        if when == "after-commit-point" and path.name.endswith(".txn"):
            os.kill(os.getpid(), signal.SIGKILL)
        return why

    def write_journals(entries):
        paths = real_write_journals(entries)
        if when == "before-renames":
            os.kill(os.getpid(), signal.SIGKILL)
        return paths
    real_write_journals = atomic._write_journals
    atomic._commit_one, atomic._remove = commit_one, remove
    atomic._write_journals = write_journals
    with atomic.atomic_outputs(overwrite=True):
        for d in dests:
            atomic.write_text_atomic(d, "new " + Path(d).name, overwrite=True)
""")


@pytest.mark.parametrize("when,expected", [
    ("before-renames", "old"), ("mid", "old"), ("after-commit-point", "new")])
def test_sigkill_in_the_commit_is_repaired_by_the_next_write(when, expected, tmp_path):
    one, two = tmp_path / "one", tmp_path / "two"
    one.mkdir()
    two.mkdir()
    a, b, c = one / "a.txt", one / "b.txt", two / "c.txt"   # a is new, b and c replaced
    b.write_text("old b.txt")
    c.write_text("old c.txt")
    proc = subprocess.run([sys.executable, "-c", _KILLED_WRITER, when, a, b, c],
                          capture_output=True, text=True)
    assert proc.returncode == -signal.SIGKILL, proc.stderr
    if when == "mid":  # what the docs say a kill in the commit leaves: a mix + journals
        assert a.read_text() == "new a.txt" and b.read_text() == "new b.txt"
        assert c.read_text() == "old c.txt"
        assert any(n.endswith(".txn") for n in leftovers(one))
        assert any(n.endswith(".txn") for n in leftovers(two))
    # the next write into either folder repairs the whole commit, and the next write
    # of each output removes what is left of it
    done = clean_stale(two, "other.csv")
    assert done, "nothing reported"
    for d, name in ((one, "a.txt"), (one, "b.txt"), (two, "c.txt")):
        clean_stale(d, name)
    if expected == "old":
        assert not a.exists() and b.read_text() == "old b.txt"
        assert c.read_text() == "old c.txt"
    else:
        assert [p.read_text() for p in (a, b, c)] == ["new a.txt", "new b.txt", "new c.txt"]
    assert leftovers(one, two) == []


_KILLED_FOLDER_WRITER = textwrap.dedent("""
    import os, signal, sys
    from pathlib import Path
    from armfit.io import atomic
    folder, truth = map(Path, sys.argv[1:])
    real = atomic._commit_one

    def commit_one(e, *, several):
        if e.dest == truth:
            os.kill(os.getpid(), signal.SIGKILL)
        real(e, several=several)
    atomic._commit_one = commit_one
    with atomic.atomic_outputs(overwrite=True):
        with atomic.atomic_path(folder, overwrite=True, folder=True) as tmp:
            (tmp / "new.txt").write_text("new trial")
        atomic.write_text_atomic(truth, "new truth", overwrite=True)
""")


@pytest.mark.parametrize("fallback", ["renameat2", "rename aside"])
def test_sigkill_after_a_folder_was_replaced_is_rolled_back(fallback, tmp_path):
    folder, truth = tmp_path / "study", tmp_path / "study.truth.json"
    folder.mkdir()
    (folder / "old.txt").write_text("old trial")
    truth.write_text("old truth")
    before = tree(tmp_path)
    script = _KILLED_FOLDER_WRITER
    if fallback == "rename aside":
        script = script.replace("real = atomic._commit_one", "real = atomic._commit_one\n"
                                "atomic._renameat2 = lambda a, b, f: False")
    proc = subprocess.run([sys.executable, "-c", script, folder, truth],
                          capture_output=True, text=True)
    assert proc.returncode == -signal.SIGKILL, proc.stderr
    assert sorted(p.name for p in folder.iterdir()) == ["new.txt"]    # half committed
    done = clean_stale(tmp_path, "study.truth.json")
    assert f"put the previous {folder} back: a run that stopped in the middle of its " \
           "commit is rolled back" in done[0]
    clean_stale(tmp_path, "study")
    assert tree(tmp_path) == before and leftovers(tmp_path) == []


def test_sigkill_mid_commit_is_rolled_back_by_the_next_command(nominal, spectra, tmp_path):
    # fit-grip -o one/grip.csv --latex two/t.tex killed between its two renames; the
    # next armfit command writing into two/ rolls the first rename back and says so
    one, two = tmp_path / "one", tmp_path / "two"
    one.mkdir()
    two.mkdir()
    (one / "grip.csv").write_text("previous grip fits\n")
    (two / "t.tex").write_text("previous table\n")
    before = {**tree(one), **tree(two)}
    script = _KILLED_WRITER.split("with atomic.atomic_outputs")[0] + textwrap.dedent("""
        from armfit.cli.main import cli
        cli.main(["fit-grip", dests[0], "-o", dests[1], "--latex", dests[2],
                  "--overwrite"], standalone_mode=False)
    """)
    proc = subprocess.run([sys.executable, "-c", script.replace("len(done) == 2",
                                                                "len(done) == 1"),
                           "mid", spectra, one / "grip.csv", two / "t.tex"],
                          capture_output=True, text=True)
    assert proc.returncode == -signal.SIGKILL, proc.stderr
    assert (one / "grip.csv").read_text() != "previous grip fits\n"   # half committed
    res = subprocess.run([ARMFIT, "fit-nominal", str(spectra), "-o", str(two / "n.csv")],
                         capture_output=True, text=True)
    assert res.returncode == 0, res.stderr
    assert f"put the previous {one / 'grip.csv'} back: a run that stopped in the middle " \
           "of its commit is rolled back" in res.stderr
    assert "could not" not in res.stderr
    (two / "n.csv").unlink()
    assert {**tree(one), **tree(two)} == before
    clean_stale(one, "grip.csv")
    assert leftovers(one, two) == []


# ---------------------------------------------------------------------------
# 3. Folder outputs that could not be replaced whole, or that are symbolic links
# ---------------------------------------------------------------------------

def test_replacing_a_folder_with_an_unwritable_subfolder_is_refused_up_front(tmp_path,
                                                                           monkeypatch):
    out = tmp_path / "study"
    (out / "sub").mkdir(parents=True)
    (out / "sub" / "keep.txt").write_text("mine")
    before = tree(out)
    real_access = os.access
    monkeypatch.setattr(os, "access", lambda p, m, **k: False if Path(p) == out / "sub"
                        else real_access(p, m, **k))
    monkeypatch.setattr("armfit.cli.simulate.simulate", not_called)
    res = invoke("simulate", "-o", out, *SIM, "--overwrite")
    assert res.exit_code == EXIT_CANTCREAT, res.output
    assert one_line_error(res.stderr) == (
        f"armfit: error: {out}: cannot be replaced: the old folder could not be removed "
        f"({out / 'sub'}: Permission denied); nothing replaced")
    assert tree(out) == before and leftovers(tmp_path) == []


def test_replacing_a_folder_that_holds_a_mount_point_is_refused(study, tmp_path, tmpfs,
                                                                 monkeypatch):
    out = tmp_path / "results"
    (out / "figures").mkdir(parents=True)
    (out / "report.md").write_text("previous report")
    tmpfs(out / "figures", "ro")
    monkeypatch.setattr("armfit.pipeline._run_in", not_called)
    res = invoke("run", study, "-o", out, "--overwrite", "--no-figures")
    assert res.exit_code == EXIT_CANTCREAT, res.output
    assert f"holds the mount point {out / 'figures'}" in one_line_error(res.stderr)
    assert (out / "report.md").read_text() == "previous report"
    assert leftovers(tmp_path) == []


def _as_nobody() -> list[str]:
    if os.geteuid() != 0 or shutil.which("setpriv") is None:
        pytest.skip("needs root and setpriv to run as another user")
    return ["setpriv", "--reuid=65534", "--regid=65534", "--clear-groups"]


def test_run_overwrite_of_a_read_only_outdir_as_a_user(study):
    # a user (not root) without write permission on OUTDIR: refused before any work,
    # the old OUTDIR as it was and no hidden copy of it left beside it
    prefix = _as_nobody()
    root = Path(tempfile.mkdtemp(prefix="armfit-ro-"))
    try:
        root.chmod(0o777)
        shutil.copytree(study, root / "study")
        out = root / "results"
        (out / "figures").mkdir(parents=True)
        (out / "report.md").write_text("previous report")
        for p in (out / "figures", out):
            p.chmod(0o555)
        env = dict(os.environ, MPLCONFIGDIR=str(root), HOME=str(root))
        res = subprocess.run(prefix + [ARMFIT, "run", str(root / "study"), "-o", str(out),
                                       "--overwrite", "--no-figures"],
                             capture_output=True, text=True, env=env, cwd=root)
        assert res.returncode == EXIT_CANTCREAT, res.stderr
        line = one_line_error(res.stderr)
        assert str(out) in line and "Permission denied" in line and "nothing replaced" in line
        assert (out / "report.md").read_text() == "previous report"
        assert leftovers(root) == []
    finally:
        for p in root.rglob("*"):
            if p.is_dir() and not p.is_symlink():
                p.chmod(0o755)
        shutil.rmtree(root)


def test_a_leftover_that_cannot_be_removed_is_reported_as_such(tmp_path, tmpfs, caplog):
    # the old folder a run set aside holds something that cannot be removed: the next
    # run says it could not remove it, instead of saying it removed it
    p = subprocess.Popen([sys.executable, "-c", "pass"])
    p.wait()
    left = tmp_path / f".results.{p.pid}.{atomic._host_tag()}0001.tmp"
    (left / "figures").mkdir(parents=True)
    tmpfs(left / "figures", "ro")
    with caplog.at_level(logging.INFO, logger="armfit"):
        done = clean_stale(tmp_path, "results")
    assert done == [f"could not remove {left}, left by a run that stopped (pid {p.pid}): "
                    f"{left / 'figures'}: {os.strerror(errno.EBUSY)}; remove it by hand"]
    assert left.exists() and done[0] in caplog.text


def test_old_folder_that_cannot_be_removed_after_the_exchange_is_reported(tmp_path, tmpfs,
                                                                          monkeypatch,
                                                                          caplog):
    # the up-front check passed, then the old folder could not be removed: the new
    # folder is in place and a warning names the old one, which is still there
    out = tmp_path / "results"
    (out / "figures").mkdir(parents=True)
    tmpfs(out / "figures", "ro")
    monkeypatch.setattr(atomic, "_check_replaceable", lambda dest: None)
    try:
        with caplog.at_level(logging.INFO, logger="armfit"):
            with atomic_path(out, overwrite=True, folder=True) as tmp:
                (tmp / "report.md").write_text("new")
        assert (out / "report.md").read_text() == "new"
        left = [p for p in tmp_path.iterdir() if LEFTOVER.match(p.name)]
        assert len(left) == 1 and (left[0] / "figures").is_mount()
        assert (f"its previous version, set aside as {left[0]}, could not be removed"
                in caplog.text)
    finally:  # the mount moved with the old folder
        for p in tmp_path.glob(".results.*/figures"):
            subprocess.run(["umount", "-l", str(p)], capture_output=True)


@pytest.mark.parametrize("command", ["run", "simulate"])
@pytest.mark.parametrize("overwrite", [True, False])
def test_symlinked_folder_output_is_refused_before_any_work(command, overwrite, study,
                                                            tmp_path, monkeypatch):
    target = tmp_path / "real"
    target.mkdir()
    (target / "report.md").write_text("previous")
    link = tmp_path / "link"
    link.symlink_to(target)
    monkeypatch.setattr("armfit.pipeline._run_in", not_called)
    monkeypatch.setattr("armfit.cli.simulate.simulate", not_called)
    args = [command, "-o", link] + ([study, "--no-figures"] if command == "run" else SIM)
    res = invoke(*args, *(["--overwrite"] if overwrite else []))
    assert res.exit_code == EXIT_CANTCREAT, res.output
    line = one_line_error(res.stderr)
    assert (f"{link}: is a symbolic link (to {target})" in line if overwrite
            else f"{link}: exists; pass --overwrite" in line)
    assert link.is_symlink() and tree(target) == {"report.md": digest(target / "report.md")}
    assert (target / "report.md").read_text() == "previous" and leftovers(tmp_path) == []


# ---------------------------------------------------------------------------
# 4. Names and paths over the system's limits: exit 73 naming the path, up front
# ---------------------------------------------------------------------------

def test_file_name_over_255_bytes(study, tmp_path, monkeypatch):
    out = tmp_path / ("n" * 300 + ".parquet")
    monkeypatch.setattr("armfit.cli.estimate.estimate_study_result", not_called)
    res = invoke("estimate", study, "-o", out)
    assert res.exit_code == EXIT_CANTCREAT, res.output
    assert one_line_error(res.stderr) == (
        f"armfit: error: {out}: cannot write: the name {'n' * 24}… is 308 bytes, over the "
        f"file system's limit of 255 bytes ({os.strerror(errno.ENAMETOOLONG)})")
    assert list(tmp_path.iterdir()) == []


def test_latex_name_over_255_bytes_is_refused_before_the_fit(spectra, tmp_path,
                                                              monkeypatch):
    tex = tmp_path / ("t" * 252 + ".tex")   # 256 bytes
    monkeypatch.setattr("armfit.cli.fit.api_fit_grip", not_called)
    res = invoke("fit-grip", spectra, "-o", tmp_path / "grip.csv", "--latex", tex)
    assert res.exit_code == EXIT_CANTCREAT, res.output
    assert "is 256 bytes, over the file system's limit of 255 bytes" in \
        one_line_error(res.stderr)
    assert list(tmp_path.iterdir()) == []


def test_api_write_of_a_name_over_255_bytes(tmp_path):
    with pytest.raises(OutputError, match="over the file system's limit of 255 bytes"):
        write_text_atomic(tmp_path / ("x" * 256), "text")


def test_path_over_path_max(study, tmp_path):
    deep = tmp_path.joinpath(*["d" * 200] * 22) / "results"   # over 4096 bytes
    res = invoke("run", study, "-o", deep)
    assert res.exit_code == EXIT_CANTCREAT, res.output
    line = one_line_error(res.stderr)
    assert str(deep) in line and "over the system's limit of 4096 bytes" in line
    assert list(tmp_path.iterdir()) == []


def test_path_that_fits_but_not_with_its_temporary_names(study, tmp_path):
    # the output's own path is under PATH_MAX, its temporary's would not be
    base = tmp_path.joinpath(*["d" * 200] * 19)
    room = 4096 - len(os.fsencode(str(base))) - 2 - 20
    out = base / ("e" * min(room, 200)) / "s.parquet"
    assert len(os.fsencode(str(out))) < 4096 <= len(os.fsencode(str(out.parent))) + 64
    res = invoke("estimate", study, "-o", out)
    assert res.exit_code == EXIT_CANTCREAT, res.output
    line = one_line_error(res.stderr)
    assert str(out) in line and "with the temporary names armfit writes beside it" in line
    assert list(tmp_path.iterdir()) == []


def test_run_stops_when_its_spectra_file_cannot_be_written(study, tmp_path, monkeypatch):
    # spectra.parquet is written in a thread of its own while the grip fits run: the
    # disk filling up there stops the run with the file's one-line error, and OUTDIR is
    # never made
    from armfit import spectra as S

    def full(*args, **kwargs):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(S, "_arrow_table", full)     # only the spectra file's writer
    out = tmp_path / "results"
    res = invoke("run", study, "-o", out, "--no-figures", "--jobs", "2")
    assert res.exit_code == EXIT_CANTCREAT, res.output
    line = one_line_error(res.stderr)
    assert "spectra.parquet" in line and "No space left on device" in line, line
    assert not out.exists() and leftovers(tmp_path) == []
