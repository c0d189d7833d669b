"""Atomic output: every file or folder a command writes appears whole, or not at all, and
the outputs of one command are committed together.

**Temporaries.** A writer never writes the destination itself: it gets a temporary in
the destination's own folder, created once, exclusively (``O_CREAT | O_EXCL``, or
``mkdir`` for a folder), under a short name that identifies its owner:
``.<first 40 bytes of the name>.<pid>.<host tag><random>.tmp`` (at most 63 bytes, so a
destination name near the 255-byte limit still has a valid temporary name). When the
writer is done, the file (every file of a folder) is fsync'ed. On any exception, also on
SIGINT and SIGTERM (which the command line turns into exceptions), the temporary is
removed and the destination is untouched.

**Commit of one destination.** Under an advisory lock of the destination's folder
(``flock``; commits of armfit processes into one folder take turns), the destination
is checked again, then:

- a new destination is claimed without replacing anything: ``renameat2(RENAME_NOREPLACE)``;
  where the system or the file system lacks it, for a file a hard link
  ``link(tmp, dest)`` (which fails if ``dest`` exists) and the temporary unlinked, for a
  folder ``mkdir(dest)`` (which fails if it exists) and the temporary renamed onto that
  empty folder; on a file system with neither (no hard links), a check and then
  ``rename(2)``, which only a writer outside armfit can race;
- an existing destination is replaced only with ``overwrite``, else the commit fails
  with OutputError (exit 73), nothing replaced, the temporary removed: another run wrote
  it after this one started. A file is replaced by ``rename(2)`` (its previous version is
  kept as a hard link ``.<name>.<pid>.<tag>.old`` until the commit is done); a folder is
  exchanged with the new one in a single ``renameat2(RENAME_EXCHANGE)`` where the system
  has it (Linux), so it always exists, old or new; elsewhere the old folder is renamed
  aside to a ``.old`` name first. The old folder is then removed. A folder is replaced
  only if it can be removed whole (every subfolder writable, no mount point inside),
  and never through a symbolic link: both are refused before any work.

The destination's folder is fsync'ed after the rename.

**Several destinations** (:class:`OutputSet`, :func:`atomic_outputs`): the temporaries of
every output of one command are written first; then all destinations are checked, a
journal ``.armfit.<pid>.<tag>.txn`` listing them is written (fsync'ed) into every
destination folder, every replaced destination is set aside (a hard link, or the old
folder), and the temporaries are renamed in one after the other. If any step fails
(also on SIGINT/SIGTERM), the destinations already committed are rolled back: each
previous version is put back and each new output removed; the temporaries, set-aside
copies, journals and the parent folders created for the outputs are removed. Either
every output is the new one or every output is as before.

**A process killed outright** (SIGKILL, power loss) cannot be atomic across several
renames. What it can leave: its temporaries (``.tmp``); with the folder fallback, the old
folder set aside (``.old``) while the destination is missing; killed in the commit of
several outputs, some outputs new and others old, with the set-aside previous versions
and the journals; killed after its commit, set-aside previous versions. Removing the
first journal is the commit point: a journal whose first copy is gone belongs to a
commit that was complete. The next write into one of those folders repairs it
(:func:`clean_stale`): a journal of a dead process (its pid, on this host) whose commit
was not complete is rolled back whole (each output whose content is the new one,
recognised by its inode, gets its previous version back, or is removed if it had none);
the temporaries and set-aside copies of dead processes are removed; a set-aside folder
is put back if the destination is missing. Each action is reported, and a leftover that
cannot be removed is reported as such, never as removed.

Every OS refusal of a write (no space, read-only or unwritable folder, a parent that is a
file, a name over the file system's limit ...) becomes an
:class:`~armfit.errors.OutputError` (exit 73) naming the path and the OS reason;
:func:`check_output` finds the ones it can before any work.
"""

from __future__ import annotations

import contextlib
import contextvars
import ctypes
import errno
import json
import logging
import os
import re
import shutil
import socket
import sys
import zlib
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

from armfit.errors import OutputError

_log = logging.getLogger("armfit")

#: Bytes of the destination name kept in a temporary name.
SHORT_BYTES = 40

#: The longest temporary or set-aside name (bytes).
TEMP_NAME_BYTES = 63

#: Room (bytes) kept below the path limit for what a folder output holds: a subfolder
#: (``figures/``) and a temporary name in it.
FOLDER_ROOM_BYTES = 8 + 1 + TEMP_NAME_BYTES

#: Temporary, set-aside and journal names: .<short>.<pid>.<host tag 4 hex><random 4 hex>.<kind>
_TEMP = re.compile(r"^\.(?P<short>.*)\.(?P<pid>\d+)\.(?P<host>[0-9a-f]{4})[0-9a-f]{4}"
                   r"\.(?P<kind>tmp|old|txn)$", re.DOTALL)

#: The short name of a journal.
_JOURNAL = "armfit"

#: errno values that mean "this output cannot be written", whatever wrote it.
_WRITE_ERRNOS = {errno.ENOSPC, errno.EDQUOT, errno.EFBIG, errno.EROFS, errno.EACCES,
                 errno.EPERM, errno.ENOTDIR, errno.EISDIR, errno.ENAMETOOLONG, errno.EEXIST,
                 errno.ENOTEMPTY, errno.EXDEV, errno.EBUSY, errno.EMLINK}

#: errno values of a file system that has no hard links.
_NO_LINKS = {errno.EPERM, errno.ENOTSUP, errno.EOPNOTSUPP, errno.ENOSYS, errno.EMLINK}


def _host_tag() -> str:
    return f"{zlib.crc32(socket.gethostname().encode()) & 0xFFFF:04x}"


def _short(name: str) -> str:
    """The first SHORT_BYTES bytes of ``name`` (UTF-8, never cutting a character)."""
    return name.encode("utf-8", "surrogateescape")[:SHORT_BYTES].decode("utf-8", "ignore")


def temp_name(dest_name: str, kind: str = "tmp") -> str:
    """A fresh temporary name for ``dest_name``.

    Parameters
    ----------
    dest_name : str
        The destination's file name.
    kind : {"tmp", "old", "txn"}
        A temporary, a set-aside previous version, or a journal.

    Returns
    -------
    str
        ``.<short>.<pid>.<host tag><random>.<kind>``, at most :data:`TEMP_NAME_BYTES`.
    """
    return f".{_short(dest_name)}.{os.getpid()}.{_host_tag()}{_random_hex(2)}.{kind}"


def _random_hex(nbytes: int) -> str:
    """``nbytes`` random bytes from the system, in hex (what ``secrets.token_hex`` does,
    without importing secrets, hmac and hashlib at start-up)."""
    return os.urandom(nbytes).hex()


def _alive(pid: int) -> bool:
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except OSError:
        return True
    return True


def _remove(path: Path) -> str | None:
    """Remove a file, link or folder tree. Returns None when it is gone, else why not."""
    errors: list[str] = []
    if path.is_dir() and not path.is_symlink():
        def note(_fn, name, exc):
            exc = exc[1] if isinstance(exc, tuple) else exc
            if not isinstance(exc, FileNotFoundError):
                errors.append(f"{name}: {_text(exc)}")
        shutil.rmtree(path, **{"onexc" if sys.version_info >= (3, 12) else "onerror": note})
    else:
        try:
            path.unlink()
        except FileNotFoundError:
            pass
        except OSError as exc:
            errors.append(_text(exc))
    if errors or os.path.lexists(path):
        return errors[0] if errors else "still there"
    return None


def _ident(path: Path) -> tuple[int, int] | None:
    try:
        st = os.lstat(path)
    except OSError:
        return None
    return st.st_dev, st.st_ino


def _text(exc: BaseException) -> str:
    if isinstance(exc, OSError):
        return exc.strerror or str(exc) or type(exc).__name__
    return str(exc) or type(exc).__name__


# ---------------------------------------------------------------------------
# Leftovers of processes that died: journals, temporaries, set-aside copies
# ---------------------------------------------------------------------------

def _put_back(old: Path, dest: Path, folder: bool) -> None:
    """Put the previous version ``old`` back onto ``dest`` (which holds the new one)."""
    if not folder:
        os.replace(old, dest)
        return
    if _renameat2(old, dest, _RENAME_EXCHANGE):
        _remove(old)                   # ``old`` now names the new folder
        return
    aside = dest.with_name(temp_name(dest.name))
    os.rename(dest, aside)
    os.rename(old, dest)
    _remove(aside)


def _undo(rec: dict) -> str | None:
    """Bring one destination of a commit back to what it was before the commit.

    The new version is recognised by its inode (``rec["ident"]``, the temporary's); the
    previous one lies under the set-aside name or, after a folder exchange, under the
    temporary's name. Returns what was done, if anything was."""
    dest, tmp = Path(rec["dest"]), Path(rec["tmp"])
    backup = Path(rec["backup"]) if rec.get("backup") else None
    new = tuple(rec["ident"])
    old = next((p for p in (backup, tmp) if p is not None
                and _ident(p) not in (None, new)), None)
    done = None
    if _ident(dest) == new:
        if old is not None:
            _put_back(old, dest, rec["folder"])
            done = f"put the previous {dest} back"
        elif not rec["existed"]:
            _remove(dest)
            done = f"removed the new {dest}"
        else:
            done = f"could not put the previous {dest} back: no copy of it is left"
    elif old is not None and not os.path.lexists(dest):
        os.rename(old, dest)
        done = f"put the previous {dest} back"
    for p in (tmp, backup):
        if p is not None and os.path.lexists(p):
            _remove(p)
    return done


def _recover(journal: Path) -> list[str]:
    """Finish the commit a dead process recorded in ``journal``: roll it back whole, or,
    when the first journal (the commit point) is already gone, only remove this copy.
    Returns what it did."""
    try:
        doc = json.loads(journal.read_text(encoding="utf-8"))
        records, master = doc["entries"], Path(doc["journals"][0])
        journals = [Path(p) for p in doc["journals"]]
    except (OSError, ValueError, KeyError, TypeError, IndexError):
        # written only partly: the process died before its first rename
        _remove(journal)
        return [f"removed {journal}, an unfinished journal of a run that stopped"]
    if not os.path.lexists(master):    # the commit was complete
        _remove(journal)
        return [f"removed {journal}, left by a run that stopped after its commit"]
    done = []
    for rec in reversed(records):
        try:
            what = _undo(rec)
        except OSError as exc:
            what = f"could not restore {rec['dest']}: {_text(exc)}"
            journals = []              # kept: the next write tries again
        if what:
            done.append(what)
    for j in journals[1:] + journals[:1]:  # the first one last
        _remove(j)
    return [f"{line}: a run that stopped in the middle of its commit is rolled back"
            for line in done] or [
        f"removed {journal}, the journal of a run that stopped before its commit"]


def clean_stale(folder: str | os.PathLike, dest_name: str) -> list[str]:
    """Repair and remove the leftovers of dead writers in ``folder``.

    A writer is dead when the pid in a leftover's name, on this host, no longer runs.
    First every journal of a dead writer in ``folder`` (a commit of several outputs cut
    short) is rolled back whole. Then each temporary (``.tmp``) or set-aside folder
    (``.old``) of ``dest_name`` is removed; a set-aside folder is first renamed back
    onto the destination if the destination is missing (the owner died between the two
    renames of the fallback swap).

    Parameters
    ----------
    folder : str or os.PathLike
        The destination's folder.
    dest_name : str
        The destination's name.

    Returns
    -------
    list of str
        One line per action (also logged), a leftover that could not be removed
        included.
    """
    folder = Path(folder)
    short, host = _short(dest_name), _host_tag()
    try:
        entries = sorted(e.name for e in os.scandir(folder))
    except OSError:
        return []
    dead = [(n, m) for n in entries if (m := _TEMP.match(n)) is not None
            and m["host"] == host and not _alive(int(m["pid"]))]
    done: list[str] = []
    for name, m in dead:
        if m["kind"] == "txn" and os.path.lexists(folder / name):
            done += [f"{line} (pid {m['pid']})" for line in _recover(folder / name)]
    dest = folder / dest_name
    for name, m in dead:
        path = folder / name
        if m["kind"] == "txn" or m["short"] != short or not os.path.lexists(path):
            continue
        if m["kind"] == "old" and not os.path.lexists(dest):
            try:
                os.rename(path, dest)
            except OSError:
                continue
            done.append(f"restored {dest} from {name}, set aside by a run that "
                        f"stopped (pid {m['pid']})")
            continue
        why = _remove(path)
        done.append(f"removed {path}, left by a run that stopped (pid {m['pid']})"
                    if why is None else
                    f"could not remove {path}, left by a run that stopped (pid "
                    f"{m['pid']}): {why}; remove it by hand")
    for line in done:
        (_log.info if not line.startswith("could not") else _log.warning)(line)
    return done


# ---------------------------------------------------------------------------
# Checks before any work
# ---------------------------------------------------------------------------

def _why(path: Path, exc: OSError, what: str = "cannot write") -> OutputError:
    return OutputError(f"{path}: {what}: {_text(exc)}")


def resolved_path(path: str | os.PathLike) -> Path:
    """The file or folder a path leads to, its symbolic links resolved; a path that
    cannot be resolved (a loop of links) as its absolute self.

    Parameters
    ----------
    path : str or os.PathLike

    Returns
    -------
    pathlib.Path
    """
    try:
        return Path(path).resolve()
    except (OSError, RuntimeError):   # RuntimeError: a loop of links (Python < 3.13)
        return Path(os.path.abspath(path))


def _same(a: Path, b: Path) -> bool:
    try:
        return os.path.samefile(a, b)
    except OSError:
        return resolved_path(a) == resolved_path(b)


def _nearest(path: Path) -> Path:
    """The nearest folder above ``path`` that exists (or something that is not a folder)."""
    p = Path(path).parent
    while not os.path.lexists(p) and p != p.parent:
        p = p.parent
    return p


def _limit(where: Path, name: str, default: int) -> int:
    try:
        return int(os.pathconf(where, name)) if os.path.isdir(where) else default
    except (OSError, ValueError):
        return default


def check_length(path: str | os.PathLike, *, folder: bool = False) -> Path:
    """Refuse an output whose name is over the file system's limit (NAME_MAX, 255 bytes
    on most), or whose path, with the temporary name it needs (and for a folder the
    room for what it holds, :data:`FOLDER_ROOM_BYTES`), is over the system's limit
    (PATH_MAX, 4096 bytes on Linux).

    Parameters
    ----------
    path : str or os.PathLike
        The output.
    folder : bool
        The output is a folder.

    Returns
    -------
    pathlib.Path
        The output.

    Raises
    ------
    OutputError
        Exit 73, naming the path, the length and the limit.
    """
    _check_lengths(Path(path), folder)
    return Path(path)


def _check_lengths(dest: Path, folder: bool) -> None:
    where = _nearest(dest)
    name_max = _limit(where, "PC_NAME_MAX", 255)
    for part in dest.parts:
        n = len(os.fsencode(part))
        if n > name_max and part != os.sep:
            raise OutputError(f"{dest}: cannot write: the name {part[:24]}… is {n} bytes, over "
                              f"the file system's limit of {name_max} bytes "
                              f"({os.strerror(errno.ENAMETOOLONG)})")
    path_max = _limit(where, "PC_PATH_MAX", 4096)
    size = len(os.fsencode(str(dest)))
    longest = len(os.fsencode(str(dest.parent / ("x" * TEMP_NAME_BYTES)))) + max(
        0, len(os.fsencode(dest.name)) - TEMP_NAME_BYTES)
    longest += FOLDER_ROOM_BYTES + 1 if folder else 0
    if size >= path_max:
        raise OutputError(f"{dest}: cannot write: the path is {size} bytes, over the "
                          f"system's limit of {path_max} bytes "
                          f"({os.strerror(errno.ENAMETOOLONG)})")
    if longest >= path_max:
        raise OutputError(f"{dest}: cannot write: the path is {size} bytes; with the "
                          "temporary names armfit writes "
                          + ("inside it" if folder else "beside it")
                          + f", it would be over the system's limit of {path_max} bytes "
                          f"({os.strerror(errno.ENAMETOOLONG)}); give a shorter path")


def _read_only(path: Path) -> bool:
    try:
        return bool(os.statvfs(path).f_flag & os.ST_RDONLY)
    except (OSError, AttributeError):
        return False


def _check_writable(dest: Path) -> None:
    """Refuse an output whose folder (or the nearest existing folder above it, where
    the folder is still to be made) is not a folder, or cannot be written."""
    where = _nearest(dest)
    if not where.is_dir():
        raise OutputError(f"{dest}: cannot write: {where} is a file, not a folder")
    if _read_only(where):
        raise OutputError(f"{dest}: cannot write: {where}: {os.strerror(errno.EROFS)}")
    if not os.access(where, os.W_OK | os.X_OK):
        raise OutputError(f"{dest}: cannot write: {where}: {os.strerror(errno.EACCES)}")


def _check_replaceable(dest: Path) -> None:
    """Refuse to replace a folder that could not be removed whole afterwards: a mount
    point, a folder holding one, or a subfolder that cannot be written."""
    dev = os.lstat(dest).st_dev
    if os.lstat(dest.parent if dest.name else dest).st_dev != dev:
        raise OutputError(f"{dest}: is a mount point; it cannot be replaced: give another "
                          "folder")
    for dirpath, dirs, _files in os.walk(dest):
        here = Path(dirpath)
        if os.lstat(here).st_dev != dev:
            raise OutputError(f"{dest}: holds the mount point {here}, so the old folder "
                              "cannot be removed; nothing replaced")
        why = (os.strerror(errno.EROFS) if _read_only(here) else
               None if os.access(here, os.W_OK | os.X_OK) else os.strerror(errno.EACCES))
        if why is not None:
            raise OutputError(f"{dest}: cannot be replaced: the old folder could not be "
                              f"removed ({here}: {why}); nothing replaced")
        dirs[:] = [d for d in dirs if not os.path.islink(here / d)]


def _check_dest(dest: Path, overwrite: bool, folder: bool) -> None:
    """The checks of a destination shared by :func:`check_output` and the commit."""
    _check_lengths(dest, folder)
    if os.path.lexists(dest) and not overwrite:
        raise OutputError(f"{dest}: exists; pass {{opt}} to replace it", option="overwrite=True")
    if not folder and dest.is_dir() and not dest.is_symlink():
        raise OutputError(f"{dest}: is a folder; give a file name for this output")
    if dest.name in ("", ".", ".."):
        raise OutputError(f"{dest}: the current folder (or a root) is never replaced; give "
                          "the output a name")
    if folder and os.path.islink(dest):
        raise OutputError(f"{dest}: is a symbolic link (to {os.readlink(dest)}); a folder "
                          "output is never written through a link: give the folder itself")
    if folder and dest.exists() and not dest.is_dir():
        raise OutputError(f"{dest}: exists and is not a folder; give a folder name")


def check_output(path: str | os.PathLike, *, overwrite: bool,
                 inputs: Iterable[str | os.PathLike] = (),
                 manifest: str | os.PathLike | None = None, folder: bool = False) -> Path:
    """Check an output before any work is done.

    Refused: an output that exists without ``overwrite``; one that would destroy or
    pollute an input (it is one of the ``inputs`` or the ``manifest``, holds one as a
    folder, is a file or a column map listed in the manifest, or lies inside an input folder under a
    raw-trial name that reading the folder would pick up; these hold even with
    ``overwrite``); a file output that is an existing folder (``-o .``); a folder output
    that is a symbolic link, or that could not be removed whole to be replaced; a name
    or path over the system's limits; an output whose folder is a file, read-only or
    not writable. The leftovers of dead writers beside it are cleaned
    (:func:`clean_stale`).

    Parameters
    ----------
    path : str or os.PathLike
        The output.
    overwrite : bool
        An existing output may be replaced.
    inputs : iterable of str or os.PathLike
        The command's inputs.
    manifest : str or os.PathLike, optional
        The trial manifest, whose listed files are inputs too.
    folder : bool
        The output is a folder.

    Returns
    -------
    pathlib.Path
        The output.

    Raises
    ------
    OutputError
        Exit 73, naming the path and the reason.
    """
    out = Path(path)
    _check_lengths(out, folder)
    _check_inputs(out, inputs, manifest)
    _check_dest(out, overwrite, folder)
    if out.parent.exists() and not out.parent.is_dir():
        raise OutputError(f"{out}: cannot write: {out.parent} is a file, not a folder")
    _check_writable(out)
    if folder and overwrite and out.is_dir():
        _check_replaceable(out)
    clean_stale(out.parent, out.name)
    return out


def _check_inputs(out: Path, inputs, manifest) -> None:
    out_res = resolved_path(out)
    named = [*inputs, *([manifest] if manifest is not None else [])]
    for inp in named:
        inp_path = Path(inp)
        inp_res = resolved_path(inp_path)
        if out_res == inp_res or (out.exists() and inp_path.exists() and _same(out, inp_path)):
            raise OutputError(f"{out}: output path is also an input; choose another output "
                              "(an input is never overwritten, even with {opt:overwrite})")
        if out_res in inp_res.parents:
            raise OutputError(f"{out}: output path is also an input (it holds {inp}); choose "
                              "another output")
        if inp_path.is_dir() and inp_res in out_res.parents and _is_trial_name(out.name):
            raise OutputError(f"{out}: inside the input folder {inp} under a raw-trial name, "
                              "so it is also an input (reading the folder picks it up); "
                              "choose another output "
                              "(an input is never overwritten, even with {opt:overwrite})")
    if manifest is not None:
        from armfit.io.trials import manifest_maps, read_manifest
        try:
            listed = read_manifest(manifest)
            maps = {resolved_path(m) for m in manifest_maps(manifest)}
        except Exception:  # a bad manifest is reported when it is read as an input
            listed, maps = {}, set()
        if out_res in listed:
            raise OutputError(f"{out}: listed as a trial in the manifest {manifest}, so it "
                              "is also an input; choose another output")
        if out_res in maps:
            raise OutputError(f"{out}: a column map named by the manifest {manifest}, so it "
                              "is also an input; choose another output")


def _is_trial_name(name: str) -> bool:
    from armfit.errors import BadInputError
    from armfit.io.trials import parse_name
    try:
        return parse_name(name) is not None
    except BadInputError:
        return True  # a trial name with a bad part: reading the folder would fail on it


# ---------------------------------------------------------------------------
# System calls
# ---------------------------------------------------------------------------

def _fsync_path(path: Path, directory: bool = False) -> None:
    flags = os.O_RDONLY | (getattr(os, "O_DIRECTORY", 0) if directory else 0)
    fd = os.open(path, flags)
    try:
        os.fsync(fd)
    except OSError as exc:  # some file systems cannot fsync a folder
        if exc.errno not in (errno.EINVAL, errno.ENOTSUP, errno.EBADF):
            raise
    finally:
        os.close(fd)


def _fsync_tree(root: Path) -> None:
    for dirpath, _dirs, files in os.walk(root):
        for name in files:
            p = Path(dirpath) / name
            if not p.is_symlink():
                _fsync_path(p)
        _fsync_path(Path(dirpath), directory=True)


_AT_FDCWD = -100
_RENAME_NOREPLACE = 1
_RENAME_EXCHANGE = 2


def _renameat2(src: Path, dst: Path, flags: int) -> bool:
    """renameat2(2) through libc. Returns False when the system or the file system does
    not support it (the caller falls back); raises OSError on other failures."""
    try:
        fn = ctypes.CDLL(None, use_errno=True).renameat2
    except (AttributeError, OSError):
        return False
    fn.argtypes = [ctypes.c_int, ctypes.c_char_p, ctypes.c_int, ctypes.c_char_p,
                   ctypes.c_uint]
    fn.restype = ctypes.c_int
    if fn(_AT_FDCWD, os.fsencode(src), _AT_FDCWD, os.fsencode(dst), flags) == 0:
        return True
    err = ctypes.get_errno()
    if err in (errno.ENOSYS, errno.EINVAL, errno.ENOTSUP):
        return False
    raise OSError(err, os.strerror(err), str(src), None, str(dst))


def _place_new(tmp: Path, dest: Path, folder: bool) -> None:
    """Rename ``tmp`` onto ``dest``, failing (FileExistsError) if ``dest`` exists."""
    if _renameat2(tmp, dest, _RENAME_NOREPLACE):
        return
    if folder:
        os.mkdir(dest)                 # claims the name, or fails if it exists
        try:
            os.rename(tmp, dest)       # replaces the empty folder just made
        except BaseException:
            with contextlib.suppress(OSError):
                os.rmdir(dest)
            raise
        return
    try:
        os.link(tmp, dest, follow_symlinks=False)
    except OSError as exc:
        if exc.errno not in _NO_LINKS:
            raise
        # no hard links on this file system: check, then rename
        if os.path.lexists(dest):
            raise FileExistsError(errno.EEXIST, os.strerror(errno.EEXIST), str(dest)) from None
        os.rename(tmp, dest)
        return
    os.unlink(tmp)


def exchange_folders(new: Path, dest: Path) -> None:
    """Put the folder ``new`` in place of the existing folder ``dest`` and remove the
    old one.

    With renameat2(RENAME_EXCHANGE) the two swap in one step (``dest`` always exists);
    else ``dest`` is renamed aside to a ``.old`` name first, and put back if the second
    rename fails (a crash between the two is repaired by :func:`clean_stale`).

    Parameters
    ----------
    new : pathlib.Path
        The new folder, beside ``dest``.
    dest : pathlib.Path
        The folder replaced.
    """
    old = _swap_in(new, dest, None)
    why = _remove(old)
    if why is not None:
        _log.warning(f"{dest} replaced, but the previous folder, set aside as {old}, "
                     f"could not be removed: {why}; remove it by hand")


def _swap_in(new: Path, dest: Path, backup: Path | None) -> Path:
    """Put the folder ``new`` onto the existing ``dest``; returns where the old one is."""
    if _renameat2(new, dest, _RENAME_EXCHANGE):
        return new                     # ``new`` now names the old folder
    old = backup or dest.with_name(temp_name(dest.name, "old"))
    os.rename(dest, old)
    try:
        os.rename(new, dest)
    except BaseException:
        os.rename(old, dest)
        raise
    return old


# ---------------------------------------------------------------------------
# The commit of one or several outputs
# ---------------------------------------------------------------------------

#: The set of outputs being written in this context (:func:`atomic_outputs`).
_ACTIVE: contextvars.ContextVar[OutputSet | None] = contextvars.ContextVar(
    "armfit_outputs", default=None)


@dataclass
class _Entry:
    """One destination of an :class:`OutputSet`."""

    dest: Path
    tmp: Path
    folder: bool
    overwrite: bool
    made: list[Path] = field(default_factory=list)   # parent folders made for it
    ready: bool = False
    existed: bool = False
    backup: Path | None = None
    old: Path | None = None      # where the previous version lies during the commit
    ident: tuple[int, int] | None = None

    def record(self) -> dict:
        return {"dest": str(self.dest.absolute()), "tmp": str(self.tmp.absolute()),
                "backup": None if self.backup is None else str(self.backup.absolute()),
                "folder": self.folder, "existed": self.existed, "ident": self.ident}


def _make_parent(dest: Path) -> list[Path]:
    """Make the folder of ``dest`` (and those above it); returns the folders made."""
    parent, missing = dest.parent, []
    p = parent
    while not os.path.lexists(p) and p != p.parent:
        missing.append(p)
        p = p.parent
    try:
        parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        for d in missing:
            with contextlib.suppress(OSError):
                d.rmdir()
        raise _why(dest, exc if not isinstance(exc, FileExistsError) else
                   OSError(errno.ENOTDIR, f"{parent} is a file, not a folder")) from None
    return missing


#: Every temporary this process created, recorded before it exists (it may have been
#: renamed into place or removed since): see :func:`remove_temporaries`.
_MADE: list[Path] = []


def _forget(entries) -> None:
    """Drop from :data:`_MADE` the temporaries of ``entries`` that are gone (renamed
    into place or removed), so that a long-lived process does not keep every name."""
    gone = {e.tmp for e in entries if not os.path.lexists(e.tmp)}
    if gone:
        _MADE[:] = [t for t in _MADE if t not in gone]


def remove_temporaries() -> list[str]:
    """Remove every temporary file or folder this process created that is still there
    (neither renamed into place nor removed yet).

    The last act of a command stopped by a signal: whatever it was doing, also between
    creating a temporary and entering the block that removes it on the way out. A
    temporary's name holds this process's id, so no other process's file is touched.

    Returns
    -------
    list of str
        The temporaries removed.
    """
    removed = []
    for tmp in list(_MADE):
        if os.path.lexists(tmp):
            _remove(tmp)
            removed.append(str(tmp))
    return removed


def _create(parent: Path, dest: Path, folder: bool) -> Path:
    for _ in range(100):
        tmp = parent / temp_name(dest.name)
        _MADE.append(tmp)
        try:
            if folder:
                os.mkdir(tmp)
            else:
                fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL
                             | getattr(os, "O_CLOEXEC", 0), 0o666)
                os.close(fd)
            return tmp
        except FileExistsError:
            continue
        except OSError as exc:
            raise _why(dest, exc) from None
    raise OutputError(f"{dest}: cannot create a temporary name in {parent}")


def _is_write_error(exc: OSError, tmp: Path) -> bool:
    names = [n for n in (getattr(exc, "filename", None), getattr(exc, "filename2", None))
             if n is not None]
    if any(str(n) == str(tmp) or str(n).startswith(str(tmp) + os.sep) for n in names):
        return True
    return exc.errno in (errno.ENOSPC, errno.EDQUOT, errno.EFBIG, errno.EROFS)


class _Locks:
    """Advisory locks (flock) of the destination folders, taken in one order, so that
    the commits of armfit processes into a folder take turns."""

    def __init__(self, folders: Iterable[Path]):
        self.fds: list[int] = []
        for folder in sorted({os.path.realpath(f) for f in folders}):
            try:
                fd = os.open(folder, os.O_RDONLY | getattr(os, "O_DIRECTORY", 0))
            except OSError:
                continue
            self.fds.append(fd)
            with contextlib.suppress(OSError, ImportError):
                import fcntl
                fcntl.flock(fd, fcntl.LOCK_EX)

    def release(self) -> None:
        for fd in reversed(self.fds):
            os.close(fd)               # closing the last descriptor drops the lock
        self.fds = []


class OutputSet:
    """The outputs of one command, committed together or not at all.

    :meth:`path` hands out a temporary per destination; :meth:`commit` renames them
    all into place (checking every destination first, setting each replaced one aside,
    and rolling every committed one back if any step fails); :meth:`abort` removes them.
    As a context manager it commits on success and aborts on any exception. See the
    module's description for what a killed process can leave and how it is repaired.

    Parameters
    ----------
    overwrite : bool
        Existing destinations may be replaced (the default of :meth:`path`).
    """

    def __init__(self, *, overwrite: bool = False):
        self.overwrite = overwrite
        self.entries: list[_Entry] = []

    def __enter__(self) -> OutputSet:
        return self

    def __exit__(self, kind, exc, tb) -> None:
        if exc is None:
            self.commit()
        else:
            self.abort()

    def path(self, dest: str | os.PathLike, *, folder: bool = False,
             overwrite: bool | None = None) -> Path:
        """A new, empty temporary (a file, or with ``folder`` a folder) for ``dest``.

        Parameters
        ----------
        dest : str or os.PathLike
            The destination; its folder is made if missing.
        folder : bool
            The output is a folder.
        overwrite : bool, optional
            An existing ``dest`` may be replaced (default: the set's).

        Returns
        -------
        pathlib.Path
            The temporary, beside ``dest``.

        Raises
        ------
        OutputError
            ``dest`` exists without ``overwrite``, is given twice, or cannot be written.
        """
        dest = Path(dest)
        overwrite = self.overwrite if overwrite is None else overwrite
        if any(_same_name(e.dest, dest) for e in self.entries):
            raise OutputError(f"{dest}: given twice as an output of one command")
        _check_dest(dest, overwrite, folder)
        made = _make_parent(dest)
        try:
            clean_stale(dest.parent, dest.name)
            tmp = _create(dest.parent, dest, folder)
        except BaseException:
            _rmdirs(made)
            raise
        self.entries.append(_Entry(dest, tmp, folder, overwrite, made))
        return tmp

    def holds(self, path: str | os.PathLike) -> bool:
        """Whether ``path`` lies inside one of the set's temporary folders."""
        p = os.path.abspath(path)
        return any(e.folder and p.startswith(os.path.abspath(e.tmp) + os.sep)
                   for e in self.entries)

    def finish(self, tmp: Path) -> None:
        """The writer of ``tmp`` is done: check it wrote it, and fsync it."""
        e = self._entry(tmp)
        if not os.path.lexists(tmp):
            raise RuntimeError(f"atomic write of {e.dest} produced nothing")
        if not e.folder and tmp.is_dir():
            raise RuntimeError(f"atomic write of the file {e.dest} made a folder")
        try:
            (_fsync_tree if e.folder else _fsync_path)(tmp)
        except OSError as exc:
            raise _why(e.dest, exc) from None
        e.ready = True

    def discard(self, tmp: Path) -> None:
        """Remove the temporary ``tmp`` (its writer failed) and forget it."""
        e = self._entry(tmp)
        self.entries.remove(e)
        _remove(tmp)
        _rmdirs(e.made)

    def abort(self) -> None:
        """Remove every temporary and the folders made for them; nothing is committed."""
        for e in reversed(self.entries):
            _remove(e.tmp)
            _rmdirs(e.made)
        _forget(self.entries)
        self.entries = []

    def _entry(self, tmp: Path) -> _Entry:
        return next(e for e in self.entries if e.tmp == tmp)

    def commit(self) -> list[Path]:
        """Rename every temporary onto its destination, all or none.

        Returns
        -------
        list of pathlib.Path
            The destinations, in the order they were handed out.

        Raises
        ------
        OutputError
            A destination appeared meanwhile without ``overwrite``, or the system
            refused a step: every destination is as before, nothing new is left.
        """
        entries = self.entries
        try:
            for e in entries:
                if not e.ready:
                    self.finish(e.tmp)
        except BaseException:
            self.abort()
            raise
        locks = _Locks(e.dest.parent for e in entries)
        try:
            journals = self._commit_locked(entries)
        except BaseException:
            self.entries = []
            raise
        finally:
            locks.release()
        self.entries = []
        for j in journals:
            _remove(j)
        for e in entries:
            if e.old is not None:
                why = _remove(e.old)
                if why is not None:
                    _log.warning(f"{e.dest} written, but its previous version, set aside "
                                 f"as {e.old}, could not be removed: {why}; remove it "
                                 "by hand")
        _forget(entries)
        return [e.dest for e in entries]

    def _commit_locked(self, entries: list[_Entry]) -> list[Path]:
        journals: list[Path] = []
        current = None
        try:
            for e in entries:
                current = e
                self._check_at_commit(e)
            if len(entries) > 1:
                journals = _write_journals(entries)
            for e in entries:
                current = e
                _commit_one(e, several=len(entries) > 1)
            for parent in {e.dest.parent for e in entries}:
                current = next(e for e in entries if e.dest.parent == parent)
                _fsync_path(parent, directory=True)
        except BaseException as exc:
            _roll_back(entries, journals)
            if isinstance(exc, OSError) and exc.errno in _WRITE_ERRNOS:
                raise _commit_error(current, exc) from None
            raise
        return journals

    def _check_at_commit(self, e: _Entry) -> None:
        e.existed = os.path.lexists(e.dest)
        if e.existed and not e.overwrite:
            raise OutputError(f"{e.dest}: appeared while it was being written (another "
                              "run?); nothing replaced")
        _check_dest(e.dest, e.overwrite, e.folder)
        if e.folder and e.existed:
            _check_replaceable(e.dest)
        if e.existed:                  # the name its previous version is set aside under
            e.backup = e.dest.with_name(temp_name(e.dest.name, "old"))
        e.ident = _ident(e.tmp)


def _same_name(a: Path, b: Path) -> bool:
    return os.path.abspath(a) == os.path.abspath(b)


def _rmdirs(made: list[Path]) -> None:
    for d in made:                     # deepest first
        with contextlib.suppress(OSError):
            d.rmdir()


def _commit_error(e: _Entry | None, exc: OSError) -> OutputError:
    if e is None:
        return OutputError(_text(exc))
    if exc.errno in (errno.EEXIST, errno.ENOTEMPTY):
        return OutputError(f"{e.dest}: appeared while it was being written (another run?);"
                           " nothing replaced")
    return _why(e.dest, exc)


def _write_journals(entries: list[_Entry]) -> list[Path]:
    """Write the journal of a commit of several outputs into every destination folder
    (fsync'ed, with the folder), before the first rename. The first is the commit
    point: the commit is complete once it is removed."""
    folders = list(dict.fromkeys(e.dest.parent for e in entries))
    written: list[tuple[Path, int]] = []
    try:
        for f in folders:
            written.append(_new_journal(f))
        paths = [p for p, _fd in written]
        data = json.dumps({"entries": [e.record() for e in entries],
                           "journals": [str(p.absolute()) for p in paths]},
                          indent=1).encode("utf-8")
        for p, fd in written:
            view = memoryview(data)
            while view:
                view = view[os.write(fd, view):]
            os.fsync(fd)
            _fsync_path(p.parent, directory=True)
    except BaseException:
        for p, _fd in written:
            _remove(p)
        raise
    finally:
        for _p, fd in written:
            os.close(fd)
    return paths


def _new_journal(folder: Path) -> tuple[Path, int]:
    """An empty journal file in ``folder``, created exclusively, and its descriptor."""
    for _ in range(100):
        path = folder / temp_name(_JOURNAL, "txn")
        try:
            return path, os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL
                                 | getattr(os, "O_CLOEXEC", 0), 0o644)
        except FileExistsError:
            continue
    raise OSError(errno.EEXIST, f"cannot create a journal name in {folder}")


def _commit_one(e: _Entry, *, several: bool) -> None:
    """Rename the temporary of ``e`` onto its destination, setting a replaced one aside."""
    if not e.existed:
        _place_new(e.tmp, e.dest, e.folder)
        return
    if e.folder:
        e.old = _swap_in(e.tmp, e.dest, e.backup)
        return
    try:
        os.link(e.dest, e.backup, follow_symlinks=False)
        e.old = e.backup
    except OSError as exc:
        if exc.errno not in _NO_LINKS:
            raise
        if several:                    # no hard links: the previous file is moved aside
            os.rename(e.dest, e.backup)
            e.old = e.backup
    try:
        os.replace(e.tmp, e.dest)
    except BaseException:
        if e.old is not None and not os.path.lexists(e.dest):
            os.rename(e.old, e.dest)
        raise


def _roll_back(entries: list[_Entry], journals: list[Path]) -> None:
    """Undo a commit cut short: every destination as before, no temporary left. A step
    that fails (or is interrupted) leaves the journals, so the next write repairs it."""
    failed = False
    for e in reversed(entries):
        try:
            if e.ident is None:
                _remove(e.tmp)
            else:
                _undo(e.record())
        except BaseException as exc:  # carry on: every other destination is restored
            failed = True
            _log.warning(f"{e.dest}: could not be restored after a failed commit: "
                         f"{_text(exc)}; the next write beside it repairs it")
    if not failed:
        for j in journals:
            _remove(j)
    for e in reversed(entries):
        _rmdirs(e.made)


@contextlib.contextmanager
def atomic_outputs(*, overwrite: bool = False) -> Iterator[OutputSet]:
    """Commit every output written inside the block together, or none of them.

    Every :func:`atomic_path` (and so every writer of armfit) used inside the block, in
    this thread, joins one :class:`OutputSet`, committed when the block ends; an
    exception removes every temporary and replaces nothing. Blocks nest: an inner one
    joins the outer one.

    Parameters
    ----------
    overwrite : bool
        The default of the outputs handed out directly by the set (each writer passes
        its own).

    Yields
    ------
    OutputSet
        The set (to hand out temporaries directly with :meth:`OutputSet.path`).
    """
    active = _ACTIVE.get()
    if active is not None:
        yield active
        return
    outputs = OutputSet(overwrite=overwrite)
    token = _ACTIVE.set(outputs)
    try:
        with outputs:
            yield outputs
    finally:
        _ACTIVE.reset(token)


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike, *, overwrite: bool = False,
                folder: bool = False) -> Iterator[Path]:
    """Yield a temporary path next to ``path``; on success commit it onto ``path``.

    The temporary is created empty before it is yielded: a file, or with ``folder`` a
    folder, which the caller fills. The parent folder is made if missing (and removed
    again if the write fails). Inside :func:`atomic_outputs` the commit waits for the
    end of that block, together with the other outputs; else it happens when this
    block ends.

    Parameters
    ----------
    path : str or os.PathLike
        The destination.
    overwrite : bool
        An existing ``path`` may be replaced (also one written meanwhile by another
        run); without it the commit never replaces anything.
    folder : bool
        The output is a folder.

    Yields
    ------
    pathlib.Path
        The temporary.

    Raises
    ------
    OutputError
        ``path`` exists without ``overwrite`` (also if it appeared while the temporary
        was written), or the system refused the write (the path and the OS reason).
        On an exception (also KeyboardInterrupt) the temporary is removed and the
        exception re-raised.
    """
    dest = Path(path)
    active = _ACTIVE.get()
    if active is not None and not active.holds(dest):
        outputs, own = active, False
    else:
        outputs, own = OutputSet(overwrite=overwrite), True
    tmp = outputs.path(dest, folder=folder, overwrite=overwrite)
    try:
        yield tmp
        outputs.finish(tmp)
    except BaseException as exc:
        if own:
            outputs.abort()
        elif any(e.tmp == tmp for e in outputs.entries):
            outputs.discard(tmp)
        if isinstance(exc, OSError) and _is_write_error(exc, tmp):
            raise _why(dest, exc) from None
        raise
    if own:
        outputs.commit()


def write_text_atomic(path: str | os.PathLike, text: str, *, overwrite: bool = False) -> Path:
    """Write ``text`` (UTF-8) to ``path`` atomically.

    Parameters
    ----------
    path : str or os.PathLike
        The destination.
    text : str
        The content.
    overwrite : bool
        An existing ``path`` may be replaced.

    Returns
    -------
    pathlib.Path
        ``path``.
    """
    with atomic_path(path, overwrite=overwrite) as tmp:
        tmp.write_text(text, encoding="utf-8")
    return Path(path)


__all__ = [
    "SHORT_BYTES", "TEMP_NAME_BYTES", "FOLDER_ROOM_BYTES", "temp_name", "clean_stale",
    "check_length", "resolved_path", "check_output", "exchange_folders", "OutputSet",
    "atomic_outputs",
    "atomic_path", "write_text_atomic", "remove_temporaries",
]
