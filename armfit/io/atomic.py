"""Atomic output: write to a temporary file (or folder) in the destination folder, then
rename it into place.

Nothing half-written is ever left at the destination. The temporary is created once,
exclusively (``O_CREAT | O_EXCL``, or ``mkdir`` for a folder), in the destination's own
folder, under a short name that identifies its owner:
``.<first 40 bytes of the name>.<pid>.<host tag><random>.tmp`` (at most 63 bytes, so a
destination name near the 255-byte limit still has a valid temporary name). Before the
rename the file (every file of a folder) and its folder are fsync'ed, and the folder
again after it. On any exception, also on SIGINT and SIGTERM (which the command line
turns into exceptions), the temporary is removed and the destination is untouched.

A folder output (``armfit run``'s OUTDIR, ``armfit simulate``'s study) that already
exists is exchanged with the new one in a single ``renameat2(RENAME_EXCHANGE)`` where the
system has it (Linux), so OUTDIR always exists, old or new; elsewhere the old folder is
renamed aside to ``.<name>.<pid>.<tag>.old`` first. A process killed outright (SIGKILL,
power loss) can leave its temporary, or in the fallback the old folder set aside; the
next write of the same destination removes the temporaries of dead processes of this
host and puts a set-aside folder back if the destination is missing
(:func:`clean_stale`).

Every OS refusal of a write (no space, read-only or unwritable folder, a parent that is a
file, ...) becomes an :class:`~armfit.errors.OutputError` (exit 73) naming the path and
the OS reason.
"""

from __future__ import annotations

import contextlib
import ctypes
import errno
import logging
import os
import re
import secrets
import shutil
import socket
import zlib
from collections.abc import Iterable, Iterator
from pathlib import Path

from armfit.errors import OutputError

_log = logging.getLogger("armfit")

#: Bytes of the destination name kept in a temporary name.
SHORT_BYTES = 40

#: Temporary and set-aside names: .<short>.<pid>.<host tag 4 hex><random 4 hex>.<tmp|old>
_TEMP = re.compile(r"^\.(?P<short>.*)\.(?P<pid>\d+)\.(?P<host>[0-9a-f]{4})[0-9a-f]{4}"
                   r"\.(?P<kind>tmp|old)$", re.DOTALL)

#: errno values that mean "this output cannot be written", whatever wrote it.
_WRITE_ERRNOS = {errno.ENOSPC, errno.EDQUOT, errno.EFBIG, errno.EROFS, errno.EACCES,
                 errno.EPERM, errno.ENOTDIR, errno.EISDIR, errno.ENAMETOOLONG, errno.EEXIST,
                 errno.ENOTEMPTY, errno.EXDEV}


def _host_tag() -> str:
    return f"{zlib.crc32(socket.gethostname().encode()) & 0xFFFF:04x}"


def _short(name: str) -> str:
    """The first SHORT_BYTES bytes of ``name`` (UTF-8, never cutting a character)."""
    return name.encode("utf-8", "surrogateescape")[:SHORT_BYTES].decode("utf-8", "ignore")


def temp_name(dest_name: str, kind: str = "tmp") -> str:
    """A fresh temporary (``kind`` "tmp") or set-aside ("old") name for ``dest_name``."""
    return f".{_short(dest_name)}.{os.getpid()}.{_host_tag()}{secrets.token_hex(2)}.{kind}"


def _alive(pid: int) -> bool:
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    except OSError:
        return True
    return True


def _remove(path: Path) -> None:
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path, ignore_errors=True)
    else:
        with contextlib.suppress(FileNotFoundError):
            path.unlink()


def clean_stale(folder: str | os.PathLike, dest_name: str) -> list[str]:
    """Remove the leftovers of dead writers of ``folder/dest_name``.

    A temporary (``.tmp``) or set-aside folder (``.old``) of ``dest_name`` whose owner
    process (the pid in its name, on this host) no longer runs is removed; a set-aside
    folder is first renamed back onto the destination if the destination is missing (the
    owner died between the two renames of the fallback swap). Returns one line per
    action (also logged).
    """
    folder = Path(folder)
    short, host = _short(dest_name), _host_tag()
    done: list[str] = []
    try:
        entries = list(os.scandir(folder))
    except OSError:
        return done
    dest = folder / dest_name
    for entry in sorted(entries, key=lambda e: e.name):
        m = _TEMP.match(entry.name)
        if (m is None or m["short"] != short or m["host"] != host
                or _alive(int(m["pid"]))):
            continue
        path = folder / entry.name
        if m["kind"] == "old" and not os.path.lexists(dest):
            try:
                os.rename(path, dest)
            except OSError:
                continue
            done.append(f"restored {dest} from {entry.name}, set aside by a run that "
                        f"stopped (pid {m['pid']})")
            continue
        _remove(path)
        done.append(f"removed {path}, left by a run that stopped (pid {m['pid']})")
    for line in done:
        _log.info(line)
    return done


def _reason(exc: OSError) -> str:
    return exc.strerror or str(exc) or type(exc).__name__


def _why(path: Path, exc: OSError, what: str = "cannot write") -> OutputError:
    return OutputError(f"{path}: {what}: {_reason(exc)}")


def _same(a: Path, b: Path) -> bool:
    try:
        return os.path.samefile(a, b)
    except OSError:
        return a.resolve() == b.resolve()


def check_output(path: str | os.PathLike, *, overwrite: bool,
                 inputs: Iterable[str | os.PathLike] = (),
                 manifest: str | os.PathLike | None = None, folder: bool = False) -> Path:
    """Refuse an output that exists without ``overwrite``, or that would destroy or
    pollute an input: the output is one of the ``inputs`` (or the ``manifest``), holds
    one (as a folder), is a file listed in the manifest, or lies inside an input folder
    under a raw-trial name that reading the folder would pick up. The refusals about
    inputs hold even with ``overwrite``. A file output (``folder`` False) that is an
    existing folder (``-o .``) is refused before any work.

    Returns the output as a Path. Raises OutputError (exit 73).
    """
    out = Path(path)
    out_res = out.resolve()
    named = [*inputs, *([manifest] if manifest is not None else [])]
    for inp in named:
        inp_path = Path(inp)
        inp_res = inp_path.resolve()
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
        from armfit.io.trials import read_manifest
        try:
            listed = read_manifest(manifest)
        except Exception:  # a bad manifest is reported when it is read as an input
            listed = {}
        if out_res in listed:
            raise OutputError(f"{out}: listed as a trial in the manifest {manifest}, so it "
                              "is also an input; choose another output")
    if out.exists() and not overwrite:
        raise OutputError(f"{out}: exists; pass {{opt}} to replace it", option="overwrite=True")
    if not folder and out.is_dir():
        raise OutputError(f"{out}: is a folder; give a file name for this output")
    if out.parent.exists() and not out.parent.is_dir():
        raise OutputError(f"{out}: cannot write: {out.parent} is a file, not a folder")
    clean_stale(out.parent, out.name)
    return out


def _is_trial_name(name: str) -> bool:
    from armfit.errors import BadInputError
    from armfit.io.trials import parse_name
    try:
        return parse_name(name) is not None
    except BadInputError:
        return True  # a trial name with a bad part: reading the folder would fail on it


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


def exchange_folders(new: Path, dest: Path) -> None:
    """Put the folder ``new`` in place of the existing folder ``dest`` and remove the
    old one. With renameat2(RENAME_EXCHANGE) the two swap in one step (``dest`` always
    exists); else ``dest`` is renamed aside to a ``.old`` name first, and put back if
    the second rename fails (a crash between the two is repaired by
    :func:`clean_stale`)."""
    if _renameat2(new, dest, _RENAME_EXCHANGE):
        shutil.rmtree(new, ignore_errors=True)  # ``new`` now holds the old folder
        return
    old = dest.with_name(temp_name(dest.name, "old"))
    os.rename(dest, old)
    try:
        os.rename(new, dest)
    except BaseException:
        os.rename(old, dest)
        raise
    shutil.rmtree(old, ignore_errors=True)


#: Every temporary this process created, recorded before it exists (it may have been
#: renamed into place or removed since): see :func:`remove_temporaries`.
_MADE: list[Path] = []


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


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike, *, overwrite: bool = False,
                folder: bool = False) -> Iterator[Path]:
    """Yield a temporary path next to ``path``; on success rename it onto ``path``.

    The temporary is created empty before it is yielded: a file, or with ``folder`` a
    folder, which the caller fills. The parent folder is created if missing. On an
    exception (also KeyboardInterrupt) the temporary is removed and the exception
    re-raised; an OSError of the write (no space, permission, ...) is re-raised as
    OutputError naming ``path`` and the OS reason.
    """
    dest = Path(path)
    if dest.name in ("", ".", ".."):
        raise OutputError(f"{dest}: the current folder (or a root) is never replaced; give "
                          "the output a name")
    if dest.exists() and not overwrite:
        raise OutputError(f"{dest}: exists; pass {{opt}} to replace it", option="overwrite=True")
    if not folder and dest.is_dir() and not dest.is_symlink():
        raise OutputError(f"{dest}: is a folder; give a file name for this output")
    if folder and dest.exists() and not dest.is_dir():
        raise OutputError(f"{dest}: exists and is not a folder; give a folder name")
    parent = dest.parent
    try:
        parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise _why(dest, exc if not isinstance(exc, FileExistsError) else
                   OSError(errno.ENOTDIR, f"{parent} is a file, not a folder")) from None
    clean_stale(parent, dest.name)
    tmp = _create(parent, dest, folder)
    committing = False
    try:
        yield tmp
        committing = True
        if not tmp.exists():
            raise RuntimeError(f"atomic write of {dest} produced nothing")
        if folder:
            _fsync_tree(tmp)
        else:
            if tmp.is_dir():
                raise RuntimeError(f"atomic write of the file {dest} made a folder")
            _fsync_path(tmp)
        if dest.is_dir() and not dest.is_symlink():
            if not folder:
                raise OutputError(f"{dest}: is a folder; give a file name for this output")
            exchange_folders(tmp, dest)
        elif folder:
            if os.path.lexists(dest):
                os.replace(tmp, dest)  # a file or a symlink in the way, with overwrite
            elif not _renameat2(tmp, dest, _RENAME_NOREPLACE):
                os.rename(tmp, dest)
        else:
            os.replace(tmp, dest)
        _fsync_path(parent, directory=True)
    except OSError as exc:
        _remove(tmp)
        if not (_is_write_error(exc, tmp) or (committing and exc.errno in _WRITE_ERRNOS)):
            raise
        if committing and exc.errno in (errno.EEXIST, errno.ENOTEMPTY):
            raise OutputError(f"{dest}: appeared while it was being written (another run?);"
                              " nothing replaced") from None
        raise _why(dest, exc) from None
    except BaseException:
        _remove(tmp)
        raise


def write_text_atomic(path: str | os.PathLike, text: str, *, overwrite: bool = False) -> Path:
    """Write ``text`` (UTF-8) to ``path`` atomically. Returns the path."""
    with atomic_path(path, overwrite=overwrite) as tmp:
        tmp.write_text(text, encoding="utf-8")
    return Path(path)


__all__ = [
    "SHORT_BYTES", "temp_name", "clean_stale", "check_output",
    "exchange_folders", "atomic_path", "write_text_atomic", "remove_temporaries",
]
