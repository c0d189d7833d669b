"""Atomic output: write to a temporary file in the destination folder, then rename.

Nothing half-written is ever left at the destination: on any exception the temporary
file (or folder) is removed and the destination is untouched.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import tempfile
from collections.abc import Iterable, Iterator
from pathlib import Path

from armfit.errors import OutputError


def check_output(path: str | os.PathLike, *, overwrite: bool,
                 inputs: Iterable[str | os.PathLike] = ()) -> Path:
    """Refuse an output that exists without ``overwrite``, or that is (or, as a folder,
    contains) one of the ``inputs`` — replacing it would destroy the input.

    Returns the output as a Path. Raises OutputError (exit 73).
    """
    out = Path(path)
    out_res = out.resolve()
    for inp in inputs:
        inp_res = Path(inp).resolve()
        if out_res == inp_res or out_res in inp_res.parents:
            raise OutputError(f"{out}: output path is also an input (or holds one); choose "
                              "another output")
    if out.exists() and not overwrite:
        raise OutputError(f"{out}: exists; pass {{opt}} to replace it", option="overwrite=True")
    return out


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike, *, overwrite: bool = False) -> Iterator[Path]:
    """Yield a temporary path next to ``path``; on success rename it onto ``path``.

    The caller writes the temporary path (file or folder). The parent folder is created
    if missing. On an exception the temporary is removed and the exception re-raised.
    """
    dest = Path(path)
    if dest.exists() and not overwrite:
        raise OutputError(f"{dest}: exists; pass {{opt}} to replace it", option="overwrite=True")
    dest.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp_name = tempfile.mkstemp(prefix=f".{dest.name}.", suffix=".tmp", dir=dest.parent)
    os.close(fd)
    os.unlink(tmp_name)
    tmp = Path(tmp_name)
    try:
        yield tmp
        if not tmp.exists():
            raise RuntimeError(f"atomic write of {dest} produced nothing")
        if dest.is_dir() and not tmp.is_dir():
            raise OutputError(f"{dest}: is a folder; give a file name for this output")
        if dest.is_dir() and not dest.is_symlink():
            old = dest.with_name(f".{dest.name}.old")
            shutil.rmtree(old, ignore_errors=True)
            dest.rename(old)
            tmp.rename(dest)
            shutil.rmtree(old, ignore_errors=True)
        else:
            os.replace(tmp, dest)
    except BaseException:
        if tmp.is_dir():
            shutil.rmtree(tmp, ignore_errors=True)
        else:
            with contextlib.suppress(FileNotFoundError):
                tmp.unlink()
        raise


def write_text_atomic(path: str | os.PathLike, text: str, *, overwrite: bool = False) -> Path:
    """Write ``text`` (UTF-8) to ``path`` atomically. Returns the path."""
    with atomic_path(path, overwrite=overwrite) as tmp:
        tmp.write_text(text, encoding="utf-8")
    return Path(path)
