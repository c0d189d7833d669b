"""The raw-trial contract: file names, columns, validation; and the canonical dataset.

Raw trials are one file per trial (CSV, CSV.gz or Parquet) named
``sub-<label>_axis-<x|y|z>_grip-<g>N[_run-<k>].<ext>`` or listed in a manifest CSV.
:func:`discover` finds them, :func:`read_trial` reads and validates one, and
:func:`open_trials` streams a whole batch with the cross-trial checks (duplicates,
sampling rate). :func:`write_dataset` writes the canonical dataset: one Parquet file,
one row group per trial, per-trial metadata as JSON in the file's key-value metadata.
Every number (cells, name parts, manifest and metadata fields) is read by
:mod:`armfit.io.numbers`. Only regular files are opened: a FIFO or a device is refused
after a ``stat``, and a symbolic link found in a folder is not followed.

Units: time s, force N, position m (``pos_<a>_mm`` columns are divided by 1000),
sampling rate Hz. A trial may carry the rig's excitation on its stimulated axis, a
``ref_<a>_N`` (commanded force, N) or ``ref_<a>_m`` (reference trajectory, m) column:
:attr:`Trial.ref`, estimated through by :mod:`armfit.spectra`. Rows in messages are
1-based data rows (the header is not counted).
"""

from __future__ import annotations

import contextlib
import csv
import errno
import functools
import gzip
import io
import json
import math
import os
import re
import stat
import threading
from collections import Counter
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass, field
from fractions import Fraction
from pathlib import Path

import numpy as np

from armfit._order import median
from armfit.constants import AXES, FORCE_LIMIT_N, GRID_HZ
from armfit.errors import ArmfitError, BadInputError, NoInputError, UsageError, cell
from armfit.io.arrow import numpy_array
from armfit.io.atomic import atomic_path, check_output, resolved_path
from armfit.io.colmap import ColumnMap, Conversion, read_column_map
from armfit.io.numbers import parse_number, parse_numbers, parse_whole

#: File extensions of raw trials, longest first (".csv.gz" before ".csv"). A MATLAB file
#: (".mat") is read only through a column map (:mod:`armfit.io.colmap`).
TRIAL_EXTENSIONS: tuple[str, ...] = (".csv.gz", ".csv", ".parquet", ".mat")

#: Sample columns of the canonical dataset besides ``trial`` (float64, SI units).
DATASET_COLUMNS: tuple[str, ...] = (
    "force_x_N", "force_y_N", "force_z_N", "pos_x_m", "pos_y_m", "pos_z_m", "grip_N")

#: The reference (excitation) column of the canonical dataset, written only when a trial
#: of the dataset has one; each trial's metadata names what it holds (``reference``).
DATASET_REFERENCE = "ref"

#: Units of a reference column: ``ref_<a>_N`` a commanded force, ``ref_<a>_m`` a reference
#: position (what the rig's controller was asked to do, not what it measured).
REFERENCE_UNITS: tuple[str, ...] = ("N", "m")

#: Parquet key-value metadata keys of the canonical dataset.
DATASET_FORMAT_KEY = "armfit.format"
DATASET_TRIALS_KEY = "armfit.trials"
DATASET_FORMAT_VERSION = "1"

#: Allowed sampling jitter: each interval may differ from the median interval by this
#: fraction of the period.
JITTER_TOLERANCE = 0.01
#: Two sampling rates are the same when they differ by at most this relative amount.
RATE_TOLERANCE = 1e-4
#: Lowest sampling rate (Hz) of a trial. A haptic device's servo loop runs at 0.5-10
#: kHz and its logs at 100 Hz or more (the default grid reaches 30 Hz); a lower rate is
#: a slip of units: time in ms makes a 1 kHz recording 1 Hz.
MIN_SAMPLING_RATE_HZ = 100.0

#: Parquet writer settings of the canonical dataset: zstd (level 3, zstd's own default),
#: forces byte-stream-split and positions and grip dictionary-encoded, float64 kept (the
#: values read back are the values written, bit for bit). A position is a whole number of
#: encoder steps and a grip is held between its sensor's samples, so a trial has few
#: distinct ones and the dictionary's indices compress well (a column with more than the
#: dictionary page holds falls back to plain encoding); a force is a whole number of
#: converter steps, whose low mantissa bytes byte-stream-split turns into runs of zeros.
#: Absent (all-NaN) axes cost next to nothing either way. Measured with
#: benchmarks/bench_memory.py on studies simulated by `armfit simulate` (Parquet files,
#: zstd level 9): the dataset is 0.96-0.98 x the raw files (lz4 without dictionaries, the
#: former settings: 2.3 x).
_PARQUET_WRITE = dict(compression="zstd", compression_level=3,
                      use_dictionary=["trial", "pos_x_m", "pos_y_m", "pos_z_m", "grip_N"],
                      use_byte_stream_split=["force_x_N", "force_y_N", "force_z_N"],
                      write_statistics=False)

_STEM = re.compile(r"sub-(?P<subject>[^_]*)_axis-(?P<axis>[^_]*)_grip-(?P<grip>[^_]*)"
                   r"(?:_run-(?P<run>[^_]*))?")
_GRIP = re.compile(r"([0-9]+(?:\.[0-9]+)?)N")
_LABEL = re.compile(r"[A-Za-z0-9]+")
_NAME_HELP = "sub-<label>_axis-<x|y|z>_grip-<g>N[_run-<k>].<csv|csv.gz|parquet>"

#: A receiver of data warnings (one line each), e.g. the CLI's stderr printer.
Warn = Callable[[str], object]


@dataclass(frozen=True)
class TrialMeta:
    """Identity and sampling of one trial.

    subject: alphanumeric label; axis: stimulated axis 'x'|'y'|'z'; grip_N: target grip
    force (N); run: repeat index or None; fs: sampling rate (Hz); n_samples; t0_s: time of
    the first sample (s); source: the file it was read from; column_map: the map its SI
    columns were made with (None: the file has armfit's own columns); reference: the
    name of the trial's reference column on the stimulated axis (``ref_<a>_N`` or
    ``ref_<a>_m``), None without one.
    """

    subject: str
    axis: str
    grip_N: float
    run: int | None
    fs: float
    n_samples: int
    t0_s: float
    source: str
    column_map: ColumnMap | None = None
    reference: str | None = None

    @property
    def duration_s(self) -> float:
        return self.n_samples / self.fs

    @property
    def key(self) -> tuple[str, str, float, int | None]:
        return (self.subject, self.axis, self.grip_N, self.run)

    @property
    def axis_index(self) -> int:
        return AXES.index(self.axis)


@dataclass(frozen=True)
class Trial:
    """One trial's samples, uniformly sampled at ``meta.fs``.

    force: (n, 3) commanded force in N, columns x, y, z (NaN where not recorded);
    pos: (n, 3) stylus-tip position in m (NaN where not recorded);
    grip: (n,) grip force in N (NaN between sensor samples or where absent), or None;
    ref: (n,) the rig's excitation on the stimulated axis — a commanded force in N or a
    reference position in m, as ``meta.reference`` names — or None.
    """

    meta: TrialMeta
    force: np.ndarray
    pos: np.ndarray
    grip: np.ndarray | None = None
    ref: np.ndarray | None = None

    @property
    def f(self) -> np.ndarray:
        """Force on the stimulated axis (N)."""
        return self.force[:, self.meta.axis_index]

    @property
    def x(self) -> np.ndarray:
        """Position on the stimulated axis (m)."""
        return self.pos[:, self.meta.axis_index]

    @property
    def time_s(self) -> np.ndarray:
        """Sample times (s): ``t0_s + k / fs``, k = 0 … n−1."""
        return self.meta.t0_s + np.arange(self.meta.n_samples) / self.meta.fs


@dataclass(frozen=True)
class TrialSource:
    """Where one trial comes from and who it is.

    path: a raw trial file, or a canonical dataset file when ``index`` (its row group,
    0-based) is set; subject, axis, grip_N (N), run: the trial's identity, from the file
    name, a manifest, or the dataset's metadata; column_map: how the raw file's columns
    become armfit's (None: it has armfit's own columns).
    """

    path: str
    subject: str
    axis: str
    grip_N: float
    run: int | None = None
    index: int | None = None
    column_map: ColumnMap | None = None

    @property
    def key(self) -> tuple[str, str, float, int | None]:
        return (self.subject, self.axis, self.grip_N, self.run)

    @property
    def label(self) -> str:
        """How messages name this trial: the file, plus the trial number in a dataset."""
        return self.path if self.index is None else f"{self.path} (trial {self.index})"


@dataclass(frozen=True)
class Skipped:
    """A trial left out by ``--skip-bad``: its file and why."""

    file: str
    reason: str


# ---------------------------------------------------------------------------
# Discovery
# ---------------------------------------------------------------------------

def _trial_ext(name: str) -> str | None:
    low = name.lower()
    for ext in TRIAL_EXTENSIONS:
        if low.endswith(ext):
            return ext
    return None


def parse_name(path: str | os.PathLike) -> tuple[str, str, float, int | None] | None:
    """Identity (subject, axis, grip_N, run) from a BIDS-style trial file name.

    Returns None when the name does not have the ``sub-…_axis-…_grip-…`` structure or a
    trial extension. Raises BadInputError when it has the structure but a part is wrong
    (e.g. an axis other than x/y/z, a grip or run that is not plain ASCII digits).
    """
    name = Path(path).name
    ext = _trial_ext(name)
    if ext is None:
        return None
    m = _STEM.fullmatch(name[: -len(ext)])
    if m is None:
        return None
    subject, axis, grip, run = m.group("subject", "axis", "grip", "run")
    file = str(path)
    if not _LABEL.fullmatch(subject):
        raise BadInputError(f"subject label '{subject}' in the file name is not alphanumeric; "
                            f"expected {_NAME_HELP}", file=file)
    if axis not in AXES:
        raise BadInputError(f"axis '{axis}' in the file name is not x, y or z; "
                            f"expected {_NAME_HELP}", file=file)
    g = _GRIP.fullmatch(grip)
    if g is None:
        raise BadInputError(f"grip '{grip}' in the file name is not a number of newtons "
                            f"such as 2N or 1.5N; expected {_NAME_HELP}", file=file)
    try:
        run_no = None if run is None else parse_whole(run)
    except ValueError:
        raise BadInputError(f"run '{run}' in the file name is not a whole number (digits "
                            f"0-9); expected {_NAME_HELP}", file=file) from None
    return subject, axis, parse_number(g.group(1)), run_no


def _key(path: Path) -> Path:
    """The file a path leads to (symbolic links resolved), or the absolute path itself
    when it cannot be resolved (a symbolic-link loop)."""
    return resolved_path(path)


@dataclass(frozen=True)
class _ManifestRow:
    row: int                      # 1-based data row
    given: Path                   # the file as the manifest names it, relative to it
    key: Path                     # the file it leads to (see _key)
    ident: tuple[str, str, float, int | None]
    map: Path | None = None       # its column map (column 'map'), relative to the manifest


def _manifest_rows(path: str | os.PathLike) -> list[_ManifestRow]:
    """The rows of a manifest CSV, checked (see :func:`read_manifest`)."""
    mpath = Path(path)
    file = str(path)
    if not mpath.exists():
        raise NoInputError(f"{file}: no such manifest file")
    _check_regular(mpath, "a manifest is a regular file")
    try:
        text = mpath.read_text(encoding="utf-8-sig")
    except (OSError, UnicodeDecodeError) as exc:
        raise BadInputError(f"cannot read the manifest: {exc}", file=file) from None
    reader = csv.DictReader(io.StringIO(text))
    header = [h.strip() for h in (reader.fieldnames or [])]
    for col in ("file", "subject", "axis", "grip_N"):
        if col not in header:
            raise BadInputError("missing required manifest column; expected columns "
                                "file,subject,axis,grip_N[,run]", file=file, column=col)
    reader.fieldnames = header
    out: list[_ManifestRow] = []
    rows: dict[Path, int] = {}
    for row_no, row in enumerate(reader, start=1):
        vals = {k: (v or "").strip() for k, v in row.items() if k is not None}
        if not vals.get("file"):
            raise BadInputError("empty file path", file=file, column="file", row=row_no)
        subject = vals["subject"]
        if not _LABEL.fullmatch(subject):
            raise BadInputError(f"subject label '{subject}' is not alphanumeric",
                                file=file, column="subject", row=row_no)
        axis = vals["axis"]
        if axis not in AXES:
            raise BadInputError(f"axis '{axis}' is not x, y or z", file=file,
                                column="axis", row=row_no)
        try:
            grip = parse_number(vals["grip_N"])
            if not math.isfinite(grip) or grip < 0:
                raise ValueError
        except ValueError:
            raise BadInputError(f"grip '{vals['grip_N']}' is not a non-negative number of "
                                "newtons", file=file, column="grip_N", row=row_no) from None
        run_txt = vals.get("run", "")
        try:
            run = parse_whole(run_txt) if run_txt else None
        except ValueError:
            raise BadInputError(f"run '{run_txt}' is not a whole number (digits 0-9)",
                                file=file, column="run", row=row_no) from None
        given = mpath.parent / vals["file"]
        target = _key(given)
        if target in rows:
            raise BadInputError(f"file '{vals['file']}' is listed twice (also row "
                                f"{rows[target]})", file=file, column="file", row=row_no)
        cmap = mpath.parent / vals["map"] if vals.get("map") else None
        out.append(_ManifestRow(row_no, given, target, (subject, axis, grip, run), cmap))
        rows[target] = row_no
    return out


def read_manifest(path: str | os.PathLike) -> dict[Path, tuple[str, str, float, int | None]]:
    """Read a manifest CSV (``file,subject,axis,grip_N[,run][,map]``; files and column
    maps relative to it).

    Returns {resolved file path: (subject, axis, grip_N, run)}. Raises BadInputError
    naming the manifest, column and row of a bad entry (a grip that is not a
    non-negative number, a run that is not a whole number, by
    :mod:`armfit.io.numbers`).
    """
    return {r.key: r.ident for r in _manifest_rows(path)}


def manifest_maps(path: str | os.PathLike) -> list[Path]:
    """The column map files a manifest names (its column ``map``, relative to it), each
    once, in the order of the rows; raises as :func:`read_manifest`."""
    return list(dict.fromkeys(r.map for r in _manifest_rows(path) if r.map is not None))


_KINDS = ((stat.S_ISFIFO, "a FIFO (named pipe)"), (stat.S_ISCHR, "a character device"),
          (stat.S_ISBLK, "a block device"), (stat.S_ISSOCK, "a socket"),
          (stat.S_ISDIR, "a folder"))


def _kind(mode: int) -> str | None:
    """What a file that is not a regular file is (None for a regular file)."""
    if stat.S_ISREG(mode):
        return None
    return next((k for test, k in _KINDS if test(mode)), "not a regular file")


def _file_problem(path: Path, *, followed: bool) -> ArmfitError | None:
    """Why ``path`` cannot be read as a trial file, or None: it is missing (NoInputError),
    a symbolic link that is not ``followed`` (NoInputError: a file found in a folder, as
    a symlinked folder), a dangling link or a loop of links (NoInputError), or not a
    regular file (BadInputError: a FIFO, a device, a socket). Only ``stat`` calls: the
    file is never opened (opening a FIFO blocks)."""
    file = str(path)
    try:
        st = os.lstat(path)
    except OSError as exc:
        return NoInputError(f"{file}: {exc.strerror or 'cannot be read'}")
    if stat.S_ISLNK(st.st_mode):
        target = os.readlink(path)
        if not followed:
            return NoInputError(f"{file}: symlinked file (to {target}), not followed (its "
                                "trial would be left out); give it as an input of its own")
        try:
            st = os.stat(path)
        except OSError as exc:
            what = ("a loop of symbolic links" if exc.errno == errno.ELOOP else
                    f"a dangling symbolic link (to {target}: no such file)"
                    if exc.errno == errno.ENOENT else f"a symbolic link to {target} "
                    f"that cannot be followed ({exc.strerror})")
            return NoInputError(f"{file}: {what}")
    kind = _kind(st.st_mode)
    if kind is not None:
        return BadInputError(f"not a regular file but {kind}; it is not opened (a trial "
                             "is a regular file)", file=file)
    return None


def _check_regular(path: Path, what: str = "a trial is a regular file") -> None:
    """Refuse, before it is opened, a file that is not a regular file (a FIFO would block
    the open, a device read without end). One that is missing is left to the open."""
    try:
        kind = _kind(os.stat(path).st_mode)
    except OSError:
        return
    if kind is not None:
        raise BadInputError(f"not a regular file but {kind}; it is not opened ({what})",
                            file=str(path))


def _walk(folder: Path, problems: list[tuple[str, str]]) -> Iterator[Path]:
    """Files under ``folder``, recursively, in sorted (deterministic) order.

    Folders that cannot be read and symlinked folders (not followed: a link may point
    back up the tree) are appended to ``problems`` as (path, reason), never skipped
    silently.
    """
    def onerror(exc: OSError) -> None:
        problems.append((str(exc.filename or folder),
                         f"cannot read the folder: {exc.strerror or exc}; its trials "
                         "would be left out"))

    for root, dirs, files in os.walk(folder, onerror=onerror):
        dirs.sort()
        for d in list(dirs):
            sub = Path(root) / d
            if sub.is_symlink():
                problems.append((str(sub), "symlinked folder, not followed (its trials "
                                 "would be left out); give it as an input of its own"))
        for name in sorted(files):
            yield Path(root) / name


def _skip_or_raise(exc: ArmfitError, bad: list[Skipped] | None, file: str) -> None:
    """Raise ``exc`` (about ``file``), or with ``bad`` a list (``skip_bad``) append it as
    skipped."""
    if bad is None:
        raise exc
    if isinstance(exc, BadInputError):
        bad.append(Skipped(exc.file or file, exc.detail))
        return
    text = str(exc)
    bad.append(Skipped(file, text[len(file):].lstrip(": ") if text.startswith(file)
                       else text))


class _Finder:
    """The search of :func:`discover`: PATHs walked or taken as given, then the manifest
    rows not met under them. With ``bad`` a list (``skip_bad``) problems are appended to
    it, not raised. A raw file is read through its manifest row's column map, else
    through ``column_map`` (a bad map is raised, never skipped: it is no trial's)."""

    def __init__(self, manifest: str | os.PathLike | None, bad: list[Skipped] | None,
                 column_map: str | os.PathLike | None = None):
        self.manifest = manifest
        self.rows = _manifest_rows(manifest) if manifest is not None else []
        self.entries = {r.key: r.ident for r in self.rows}
        self.default_map = None if column_map is None else read_column_map(column_map)
        maps = {m: read_column_map(m) for m in dict.fromkeys(
            r.map for r in self.rows if r.map is not None)}
        self.maps = {r.key: maps[r.map] for r in self.rows if r.map is not None}
        self.bad = bad
        self.sources: list[TrialSource] = []
        self.ignored: list[Path] = []
        self.seen: set[Path] = set()
        self.problems: list[tuple[str, str]] = []

    def fail(self, exc: ArmfitError, path: Path) -> None:
        _skip_or_raise(exc, self.bad, str(path))

    def add(self, path: Path, explicit: bool) -> None:
        """One file: named on the command line or by the manifest (``explicit``: links
        are followed, a dataset is read), or found in a folder."""
        res = _key(path)
        if not explicit and res not in self.entries and path.is_symlink():
            self.linked(path)
            return
        if res in self.seen:
            return
        self.seen.add(res)
        listed = explicit or res in self.entries
        problem = _file_problem(path, followed=True) if listed else None
        if problem is not None:
            self.fail(problem, path)
        elif res in self.entries:       # named by the manifest: read wherever it is
            cmap = self.maps.get(res, self.default_map)
            if _trial_ext(path.name) is None and cmap is None:
                self.fail(BadInputError("unsupported file type; expected .csv, .csv.gz, "
                                        ".parquet, or .mat with a column map",
                                        file=str(path)), path)
            else:
                self.source(path, self.entries[res], cmap)
        elif explicit and is_dataset(path):
            self.sources.extend(dataset_sources(path))
        else:
            self.named(path, explicit)

    def source(self, path: Path, ident: tuple[str, str, float, int | None],
               cmap: ColumnMap | None) -> None:
        """A raw trial: kept, or refused when it cannot be read as it is (a MATLAB file
        without a column map, a map without the stimulated axis)."""
        file = str(path)
        try:
            if cmap is None and _trial_ext(path.name) == ".mat":
                raise BadInputError("a MATLAB file has no column names armfit knows: a "
                                    "column map is needed ({opt:column_map} FILE, or the "
                                    "manifest's column 'map') to say which variables "
                                    "hold time, force and position", file=file)
            if cmap is not None:
                cmap.check_axis(ident[1], file)
        except BadInputError as exc:
            self.fail(exc, path)
            return
        self.sources.append(TrialSource(file, *ident, column_map=cmap))

    def named(self, path: Path, explicit: bool) -> None:
        """A file whose identity is its name."""
        try:
            ident = parse_name(path)
        except BadInputError as exc:
            self.fail(exc, path)
            return
        if ident is not None:
            # a trial name found in a folder: a FIFO or a device is refused unopened
            problem = None if explicit else _file_problem(path, followed=False)
            if problem is not None:
                self.fail(problem, path)
            else:
                self.source(path, ident, self.default_map)
        elif explicit:
            extra = (", and it is not an armfit dataset"
                     if _trial_ext(path.name) == ".parquet" else "")
            self.fail(BadInputError(f"file name matches no pattern ({_NAME_HELP}) and has "
                                    f"no {{opt:manifest}} entry{extra}", file=str(path)), path)
        else:
            self.ignored.append(path)

    def linked(self, path: Path) -> None:
        """A symbolic link found in a folder: not followed, as a symlinked folder; one
        under a trial name is reported (its trial would be left out), others ignored."""
        try:
            trial = parse_name(path) is not None
        except BadInputError:
            trial = True
        if not trial:
            self.ignored.append(path)
            return
        problem = _file_problem(path, followed=False)
        self.problems.append((str(path), str(problem)[len(str(path)):].lstrip(": ")))

    def listed(self, row: _ManifestRow) -> None:
        """A manifest row not met under the PATHs: its file is read all the same."""
        if row.key in self.seen:
            return
        if not os.path.lexists(row.key):
            text = f"{self.manifest}: column 'file', row {row.row}: {row.key}: no such file"
            if self.bad is None:
                raise NoInputError(text)
            self.bad.append(Skipped(str(row.key), f"listed in {self.manifest} (row "
                                    f"{row.row}) but no such file"))
            self.seen.add(row.key)
            return
        self.add(row.key, explicit=True)

    def run(self, inputs: Sequence[str | os.PathLike]) -> tuple[list[TrialSource],
                                                                list[Path]]:
        for inp in inputs:
            p = Path(inp)
            if p.is_dir():
                for f in _walk(p, self.problems):
                    self.add(f, explicit=False)
            elif os.path.lexists(p):
                self.add(p, explicit=True)
            else:
                raise NoInputError(f"{p}: no such file or folder")
        for where, reason in self.problems:
            if self.bad is None:
                raise NoInputError(f"{where}: {reason}; or pass {{opt:skip_bad}} to go on "
                                   "without it")
            self.bad.append(Skipped(where, reason))
        # every manifest row is a trial, one outside the PATHs too (after theirs, in order)
        for row in self.rows:
            self.listed(row)
        return self.sources, self.ignored


def _discover(inputs: Sequence[str | os.PathLike], manifest: str | os.PathLike | None,
              bad: list[Skipped] | None, column_map: str | os.PathLike | None = None
              ) -> tuple[list[TrialSource], list[Path]]:
    """:func:`discover`; with ``bad`` a list, bad names are appended to it, not raised."""
    return _Finder(manifest, bad, column_map).run(inputs)


def discover(inputs: Sequence[str | os.PathLike], *,
             manifest: str | os.PathLike | None = None,
             column_map: str | os.PathLike | None = None,
             ) -> tuple[list[TrialSource], list[Path]]:
    """Find the trials in ``inputs`` (raw files, folders, canonical dataset files).

    Folders are searched recursively in sorted order; their files whose names are not
    trial names (and not in the manifest) are returned as ignored. A file named
    explicitly must be a trial name, a manifest entry, or a canonical dataset. With a
    manifest and no inputs, the manifest's files are the inputs. The manifest's identity
    wins over the file name. A raw file is read through the column map of its manifest
    row (column ``map``), else through ``column_map`` (a map file,
    :func:`armfit.io.colmap.read_column_map`); a MATLAB file needs one. Returns
    (sources, ignored files).
    """
    return _discover(inputs, manifest, None, column_map)


# ---------------------------------------------------------------------------
# Reading raw files
# ---------------------------------------------------------------------------

def _gzipped(path: Path) -> bool:
    return path.name.lower().endswith(".gz")


def _csv_header(path: Path) -> list[str]:
    """The header row of a CSV (or CSV.gz) file, each name stripped of blanks."""
    opener = gzip.open if _gzipped(path) else open
    with opener(path, "rt", encoding="utf-8-sig", newline="") as fh:
        line = fh.readline()
    if not line.strip():
        raise BadInputError("unreadable file: it is empty (a header row is required)",
                            file=str(path))
    return [c.strip() for c in next(csv.reader([line]))]


def _first_short_row(path: Path, width: int) -> int | None:
    """The 1-based data row of the first CSV line with a different field count."""
    opener = gzip.open if _gzipped(path) else open
    try:
        with opener(path, "rt", encoding="utf-8-sig", newline="") as fh:
            for row_no, fields in enumerate(csv.reader(fh)):
                if row_no and len(fields) != width:
                    return row_no
    except (OSError, EOFError, UnicodeDecodeError, csv.Error):
        return None
    return None


def _read_csv(path: Path, names: list[str], header: list[str], text: bool):
    """The columns ``names`` of a CSV file as a pyarrow table: float64 converted by Arrow
    (which reads exactly the numbers of :mod:`armfit.io.numbers`), or with ``text`` as
    strings. The header is replaced by ``header`` (its names stripped; the columns not
    read get names of their own), so ``time_s, force_x_N`` finds ``force_x_N``."""
    import pyarrow as pa
    import pyarrow.csv as pcsv
    wanted = set(names)
    cols = [h if h in wanted else f"\0{i}" for i, h in enumerate(header)]
    # only a blank cell (or NaN) is a missing value: 'n/a', 'NA' or 'null' are text, and
    # refused as non-numeric rather than guessed
    convert = pcsv.ConvertOptions(
        include_columns=names, null_values=[""], strings_can_be_null=True,
        column_types={n: pa.string() if text else pa.float64() for n in names})
    # the compression is the extension's, in any case (.CSV.GZ too)
    stream = pa.input_stream(str(path), compression="gzip" if _gzipped(path) else None)
    with stream:
        return pcsv.read_csv(stream, read_options=pcsv.ReadOptions(column_names=cols,
                                                                  skip_rows=1),
                             convert_options=convert)


def _read_table(path: Path, names: list[str]) -> dict[str, np.ndarray]:
    """Read the columns ``names`` (header names stripped of blanks) of a raw trial file
    as float64 arrays; every text cell is read by :func:`armfit.io.numbers.parse_numbers`
    (blank: NaN)."""
    import pyarrow as pa

    file = str(path)
    _check_regular(path)
    if _trial_ext(path.name) == ".parquet":
        actual = {n.strip(): n for n in _parquet_names(path)}
        try:
            table = _parquet_file(path).read(columns=[actual[n] for n in names],
                                             use_threads=False)
        except (pa.ArrowException, OSError) as exc:
            raise BadInputError(f"unreadable or truncated Parquet file: {_first_line(exc)}",
                                file=file) from None
        return {n: parse_numbers(table.column(actual[n]), file=file, column=n,
                                 hint=_MISSING_HINT.get(n, "")) for n in names}

    header = _csv_header(path)
    try:
        table = _read_csv(path, names, header, text=False)
    except pa.ArrowInvalid as exc:
        msg = _first_line(exc)
        if "conversion error" not in msg:
            row = _first_short_row(path, len(header)) if "columns" in msg else None
            raise BadInputError(f"unreadable or truncated CSV file: {msg}", file=file,
                                row=row) from None
        try:   # the cell Arrow could not convert: found and named by the parser
            table = _read_csv(path, names, header, text=True)
        except (pa.ArrowException, OSError, EOFError) as exc2:
            raise BadInputError(f"unreadable or truncated CSV file: {_first_line(exc2)}",
                                file=file) from None
        return {n: parse_numbers(table.column(n), file=file, column=n,
                                 hint=_MISSING_HINT.get(n, "")) for n in names}
    except (pa.ArrowException, OSError, EOFError) as exc:
        raise BadInputError(f"unreadable or truncated file: {_first_line(exc)}",
                            file=file) from None
    # parse_numbers reads numeric columns from their buffers: Arrow's to_numpy would
    # import pandas for a chunked column
    return {name: parse_numbers(table.column(name), file=file, column=name)
            for name in names}


_MISSING_HINT = {"grip_N": " (a grip sample that is missing is a blank cell or NaN)"}


def _first_line(exc: BaseException) -> str:
    text = str(exc).strip()
    return text.splitlines()[0] if text else type(exc).__name__


def _parquet_names(path: Path) -> list[str]:
    import pyarrow as pa
    try:
        return list(_parquet_file(path).schema_arrow.names)
    except (pa.ArrowException, OSError) as exc:
        raise BadInputError(f"unreadable or truncated Parquet file: {_first_line(exc)}",
                            file=str(path)) from None


def _parquet_file(path: Path):
    """``pyarrow.parquet.ParquetFile`` of ``path``, opened once for the schema, the
    footer and the columns of a trial read one after the other (kept while the file is
    unchanged: same inode, size and modification time)."""
    st = os.stat(path)
    return _open_parquet(str(path), (st.st_ino, st.st_size, st.st_mtime_ns))


@functools.lru_cache(maxsize=2)
def _open_parquet(path: str, stamp: tuple[int, int, int]):
    import pyarrow.parquet as pq
    return pq.ParquetFile(path)


def _column_names(path: Path) -> list[str]:
    """The column names of a raw trial file, stripped of blanks (as the CSV header)."""
    file = str(path)
    _check_regular(path)
    if _trial_ext(path.name) == ".parquet":
        return [n.strip() for n in _parquet_names(path)]
    try:
        return _csv_header(path)
    except (OSError, EOFError, UnicodeDecodeError, csv.Error) as exc:
        raise BadInputError(f"unreadable or truncated file: {_first_line(exc)}",
                            file=file) from None


def _select_columns(names: list[str], axis: str, file: str) -> dict[str, str]:
    """Map canonical names (force_x_N, pos_x_m, grip_N, time_s) to the file's columns.

    A recognised column named twice, or a position given both in m and in mm, is
    refused: which one is meant cannot be known.
    """
    have = set(names)
    known = {"time_s", "grip_N"} | {f"{q}_{a}_{u}" for a in AXES
                                    for q, u in (("force", "N"), ("pos", "m"), ("pos", "mm"),
                                                 ("ref", "N"), ("ref", "m"))}
    counts = Counter(names)
    for name in names:
        if name in known and counts[name] > 1:
            cols = [i + 1 for i, n in enumerate(names) if n == name]
            raise BadInputError(f"duplicate column header (columns {', '.join(map(str, cols))}"
                                " of the header); which one holds the data is ambiguous",
                                file=file, column=name)
    for a in AXES:
        if f"pos_{a}_m" in have and f"pos_{a}_mm" in have:
            raise BadInputError(f"both pos_{a}_m and pos_{a}_mm are present; keep one",
                                file=file, column=f"pos_{a}_mm")
    if "time_s" not in have:
        raise BadInputError("missing required column; expected sample times in s",
                            file=file, column="time_s")
    if f"force_{axis}_N" not in have:
        raise BadInputError(f"missing required column; expected the force on the "
                            f"stimulated axis {axis} in N", file=file, column=f"force_{axis}_N")
    if f"pos_{axis}_m" not in have and f"pos_{axis}_mm" not in have:
        raise BadInputError(f"missing required column (or pos_{axis}_mm); expected the "
                            f"position on the stimulated axis {axis}", file=file,
                            column=f"pos_{axis}_m")
    pick = {"time_s": "time_s"}
    for a in AXES:
        if f"force_{a}_N" in have:
            pick[f"force_{a}_N"] = f"force_{a}_N"
        if f"pos_{a}_m" in have:
            pick[f"pos_{a}_m"] = f"pos_{a}_m"
        elif f"pos_{a}_mm" in have:
            pick[f"pos_{a}_m"] = f"pos_{a}_mm"
    if "grip_N" in have:
        pick["grip_N"] = "grip_N"
    refs = [f"ref_{axis}_{u}" for u in REFERENCE_UNITS if f"ref_{axis}_{u}" in have]
    if len(refs) > 1:
        raise BadInputError(f"both {refs[0]} and {refs[1]} are present: a trial's reference "
                            "is a commanded force or a reference position, not both; keep "
                            "one", file=file, column=refs[1])
    if refs:
        pick["ref"] = refs[0]
    return pick


def check_reference(v: np.ndarray, name: str, file: str) -> np.ndarray:
    """Refuse a reference column ``name`` (``ref_<a>_N`` or ``ref_<a>_m``) whose samples
    are not finite or absurd (as :func:`check_values`) or constant throughout (it would
    excite nothing): BadInputError naming the file, column and row."""
    v = check_values(v, name, file)
    if v.size and v.max() == v.min():
        raise BadInputError(f"the reference is constant ({cell(float(v[0]))}) throughout: it "
                            "excites nothing; drop the column, or give the commanded force "
                            "or the reference trajectory", file=file, column=name)
    return v


def _nice_rate(fs: float) -> float:
    """Round a measured rate to whole Hz when within RATE_TOLERANCE, else 6 digits."""
    r = round(fs)
    if r > 0 and abs(fs - r) <= RATE_TOLERANCE * fs:
        return float(r)
    return float(f"{fs:.6g}")


def sampling_rate(time_s: np.ndarray, *, file: str = "?") -> float:
    """Validate sample times (s) and return the sampling rate (Hz).

    Times must be finite, strictly increasing and uniform: every interval within
    JITTER_TOLERANCE (1 %) of the median interval. The rate is 1 / mean interval
    ((t_last − t_first) / (n − 1)), rounded to whole Hz when within 0.01 %, and at
    least :data:`MIN_SAMPLING_RATE_HZ` (a lower rate is a unit slip: times in ms give
    1 Hz for a 1 kHz recording). Raises BadInputError naming the 1-based row of the first
    offending sample.
    """
    t = np.asarray(time_s, dtype=np.float64)
    if t.size == 0:
        raise BadInputError("no data rows after the header", file=file)
    if t.size < 2:
        raise BadInputError("too short: 1 sample; a trial needs many samples", file=file)
    with np.errstate(over="ignore", invalid="ignore"):
        total = t.sum()
    if not np.isfinite(total):      # a finite sum: every sample is finite
        bad = np.flatnonzero(~np.isfinite(t))
        if bad.size:
            raise BadInputError(f"non-finite time {cell(t[bad[0]])}; expected a number",
                                file=file, column="time_s", row=int(bad[0]) + 1)
    dt = np.diff(t)
    shortest, longest = float(dt.min()), float(dt.max())
    if not shortest > 0:
        i = int(np.flatnonzero(dt <= 0)[0])
        raise BadInputError(f"non-monotonic time: {cell(t[i + 1])} s follows {cell(t[i])} s; "
                            "sample times must increase", file=file, column="time_s",
                            row=i + 2)
    # every interval within 1 % of the median one: sure without the median when the
    # intervals spread over less (each then lies within that spread of the median,
    # which is at least the shortest)
    if longest - shortest > 0.99 * JITTER_TOLERANCE * shortest:
        period = float(median(dt))
        off = np.flatnonzero(np.abs(dt - period) > JITTER_TOLERANCE * period)
        if off.size:
            i = int(off[0])
            raise BadInputError(f"non-uniform time: interval {dt[i]:.6g} s vs period "
                                f"{period:.6g} s (jitter over 1 % of the period; dropped "
                                "or repeated samples?)", file=file, column="time_s",
                                row=i + 2)
    fs = _nice_rate((t.size - 1) / (t[-1] - t[0]))
    if fs < MIN_SAMPLING_RATE_HZ:
        unit = ("is time in ms? time_s must be in seconds"
                if fs * 1000.0 >= MIN_SAMPLING_RATE_HZ else "time_s must be in seconds")
        period = float(median(dt))
        raise BadInputError(f"sampling rate {fs:g} Hz (a sample every {period:.6g} s) is "
                            f"below {MIN_SAMPLING_RATE_HZ:g} Hz, implausible for a haptic "
                            f"device: {unit}", file=file, column="time_s")
    return fs


def _provenance(path: Path) -> str:
    """The file a trial was read from, as its metadata records it: the path as given,
    or for a symbolic link the file it leads to."""
    return os.path.realpath(path) if path.is_symlink() else str(path)


def read_trial(source: TrialSource, *, f_min_hz: float = GRID_HZ[0],
               force_limit_N: float = FORCE_LIMIT_N,
               warn: Warn | None = None, grip: bool = True) -> Trial:
    """Read and validate one trial (a raw file, or one row group of a dataset).

    Checks, in order: a regular file (a FIFO or a device is refused unopened); required
    columns (names stripped of blanks) (``time_s``, the stimulated axis's
    force and position); numeric values; finite time, force and position; increasing,
    uniform time; duration ≥ 2 / ``f_min_hz`` (two periods of the lowest frequency);
    non-constant force on the stimulated axis. |force| at or above ``force_limit_N`` (N)
    on any axis (:func:`saturated_samples`) is reported through ``warn`` (saturation),
    not raised. Positions in mm are
    converted to m. A source with a column map is read through it (its columns or
    MATLAB variables, converted to SI units; the same checks follow, their messages
    naming the source column). ``grip`` False leaves the grip force unread
    (``Trial.grip`` None).
    The metadata's ``source`` is the file read (for a symbolic link, the file it leads
    to). Raises BadInputError naming file, column and row.
    """
    if source.index is not None:
        trial = _read_dataset_trial(source, grip=grip)
    elif source.column_map is not None:
        trial = _read_mapped_trial(source, grip=grip)
    else:
        path = Path(source.path)
        file = source.path
        pick = _select_columns(_column_names(path), source.axis, file)
        if not grip:
            pick.pop("grip_N", None)
        cols = _read_table(path, list(dict.fromkeys(pick.values())))
        t = cols[pick["time_s"]]
        n = t.size
        force = np.empty((n, 3), order="F")
        pos = np.empty((n, 3), order="F")
        for j, a in enumerate(AXES):
            for arr, canon, scale in ((force, f"force_{a}_N", None),
                                      (pos, f"pos_{a}_m", 1000.0)):
                if canon not in pick:
                    arr[:, j] = np.nan        # not recorded
                    continue
                name = pick[canon]
                v = check_values(cols[name], name, file)
                arr[:, j] = v / scale if name.endswith("_mm") else v
        grip = check_grip(cols["grip_N"], file) if "grip_N" in pick else None
        ref = check_reference(cols[pick["ref"]], pick["ref"], file).copy() \
            if "ref" in pick else None
        fs = sampling_rate(t, file=file)
        meta = TrialMeta(source.subject, source.axis, float(source.grip_N), source.run,
                         fs, int(n), float(t[0]), _provenance(path),
                         reference=pick.get("ref"))
        trial = Trial(meta, force, pos, None if grip is None else np.array(grip), ref)
        nbytes = 8 * n * len(cols)
        del cols, t, grip
        _release_arrow_memory(nbytes)
    if source.column_map is not None:
        _check_mapped(trial, source, f_min_hz=f_min_hz, force_limit_N=force_limit_N,
                      warn=warn)
    else:
        _check_trial(trial, source.label, f_min_hz=f_min_hz, force_limit_N=force_limit_N,
                     warn=warn)
    return trial


# ---------------------------------------------------------------------------
# Reading through a column map
# ---------------------------------------------------------------------------

def _source_columns(path: Path, convs: Sequence[Conversion], file: str
                    ) -> dict[str, np.ndarray]:
    """{source text: raw samples} of the conversions ``convs``: MATLAB variables, or the
    columns of a CSV or Parquet file (a missing one named with the file's columns)."""
    _check_regular(path)
    wanted = list(dict.fromkeys(c.source for c in convs))
    if _trial_ext(path.name) == ".mat":
        from armfit.io.matlab import read_matlab
        spec = {c.source: (c.name, c.column) for c in convs}
        return read_matlab(path, [(s, spec[s]) for s in wanted], file=file)
    names = _column_names(path)
    counts = Counter(names)
    for c in convs:
        if c.source not in counts:
            have = ", ".join(n for n in names if n) or "none"
            raise BadInputError(f"no such column, named by the column map for {c.quantity} "
                                f"(map row {c.row}); the file's columns: {have}",
                                file=file, column=c.source)
        if counts[c.source] > 1:
            raise BadInputError("duplicate column header; which one holds the data is "
                                "ambiguous", file=file, column=c.source)
    return _read_table(path, wanted)


def _by_source(exc: BadInputError, conv: Conversion, cmap: ColumnMap) -> BadInputError:
    """``exc``, about ``conv.quantity``, naming the source column instead (the user's own
    name) and the conversion that made the quantity."""
    return BadInputError(f"{exc.reason} ({conv.describe()}, column map {cmap.path} row "
                         f"{conv.row})", file=exc.file, column=conv.source, row=exc.row,
                         option=exc.option)


@contextlib.contextmanager
def _named_by_source(conv: Conversion, cmap: ColumnMap):
    """A check's error in the ``with`` block re-raised by :func:`_by_source`."""
    try:
        yield
    except BadInputError as exc:
        raise _by_source(exc, conv, cmap) from None


def _check_mapped(trial: Trial, source: TrialSource, *, f_min_hz: float,
                  force_limit_N: float, warn: Warn | None) -> None:
    """:func:`_check_trial` of a trial read through its column map: its messages and
    warnings name the source column of a quantity (``column 'vir' (force_x_N)``)."""
    cmap = source.column_map
    assert cmap is not None
    convs = {c.quantity: c for c in cmap.conversions}

    def renamed(text: str) -> None:
        for q, c in convs.items():
            text = text.replace(f"column '{q}'", f"column '{c.source}' ({q})")
        warn(text)  # type: ignore[misc]

    try:
        _check_trial(trial, source.label, f_min_hz=f_min_hz, force_limit_N=force_limit_N,
                     warn=None if warn is None else renamed)
    except BadInputError as exc:
        conv = convs.get(exc.column or "")
        if conv is None:
            raise
        raise _by_source(exc, conv, cmap) from None


def _mapped_rate(source: TrialSource) -> float:
    """The sampling rate (Hz) of a trial read through its column map (the map's rate, or
    its time column's)."""
    cmap = source.column_map
    if cmap.rate_Hz is not None:  # type: ignore[union-attr]
        return cmap.rate_Hz  # type: ignore[union-attr]
    conv = cmap.get("time_s")  # type: ignore[union-attr]
    raw = _source_columns(Path(source.path), [conv], source.path)[conv.source]
    with _named_by_source(conv, cmap):  # type: ignore[arg-type]
        return sampling_rate(conv.apply(raw), file=source.path)


def _read_mapped_trial(source: TrialSource, *, grip: bool) -> Trial:
    """One raw trial read through its column map: the sources converted to SI units and
    checked as armfit's own columns, each message naming the source column."""
    cmap = source.column_map
    assert cmap is not None
    file = source.path
    path = Path(file)
    convs = [c for c in cmap.conversions if (grip or c.quantity != "grip_N") and not (
        c.quantity.startswith("ref_") and c.quantity.split("_")[1] != source.axis)]
    raw = _source_columns(path, convs, file)
    sizes = {c.source: raw[c.source].size for c in convs}
    first = convs[0].source
    for src, size in sizes.items():
        if size != sizes[first]:
            raise BadInputError(f"{size} samples, but {first} has {sizes[first]}; the "
                                "signals of a trial have one length", file=file, column=src)
    n = sizes[first]
    force = np.full((n, 3), np.nan, order="F")
    pos = np.full((n, 3), np.nan, order="F")
    grip_N = ref = None
    for c in convs:
        with _named_by_source(c, cmap):
            v = c.apply(raw[c.source])
            if c.quantity == "grip_N":
                grip_N = check_grip(v, file).copy()
            elif c.quantity.startswith("ref_"):
                ref = check_reference(v, c.quantity, file).copy()
            elif c.quantity != "time_s":
                check_values(v, c.quantity, file, unit_hint="; check the unit in the map")
                (force if c.quantity.startswith("force_") else pos)[
                    :, AXES.index(c.quantity.split("_")[1])] = v
    if cmap.rate_Hz is None:
        conv = cmap.get("time_s")
        with _named_by_source(conv, cmap):  # type: ignore[arg-type]
            t = conv.apply(raw[conv.source])  # type: ignore[union-attr]
            fs, t0 = sampling_rate(t, file=file), float(t[0])
    else:
        fs, t0 = cmap.rate_Hz, 0.0
        if n < 2:
            raise BadInputError(f"too short: {n} sample(s); a trial needs many samples",
                                file=file)
        if fs < MIN_SAMPLING_RATE_HZ:
            raise BadInputError(f"sampling rate {fs:g} Hz (rate_Hz of the column map "
                                f"{cmap.path}) is below {MIN_SAMPLING_RATE_HZ:g} Hz, "
                                "implausible for a haptic device", file=file)
    nbytes = 8 * n * len(raw)
    del raw
    _release_arrow_memory(nbytes)
    meta = TrialMeta(source.subject, source.axis, float(source.grip_N), source.run, fs,
                     int(n), t0, _provenance(path), cmap,
                     next((c.quantity for c in convs if c.quantity.startswith("ref_")), None))
    return Trial(meta, force, pos, grip_N, ref)


#: Largest |value| of a force (N) or any sample: squares and sums of the samples in the
#: spectra overflow float64 (1.8e308) long before 1e150; no instrument records 1e100.
MAX_ABS_VALUE = 1e100
#: Largest |position| (m) on a desktop haptic device; larger values in a ``pos_*_m``
#: column are millimetres (or another unit) by mistake.
MAX_POSITION_M = 0.5


def peak_abs(v: np.ndarray) -> float:
    """max |v| of a float array from its two extremes; NaN when a sample is NaN (min and
    max spread it) or there is none, so that a caller's test on it fails and it looks
    sample by sample."""
    if not v.size:
        return math.nan
    return max(abs(float(v.min())), abs(float(v.max())))


def check_values(v: np.ndarray, name: str, file: str, *,
                 unit_hint: str | None = None) -> np.ndarray:
    """Refuse non-finite or absurd samples of a force or position column ``name``.

    Non-finite (blank, NaN, inf) → BadInputError; |value| ≥ :data:`MAX_ABS_VALUE`
    (would overflow the spectra) → BadInputError; a position beyond
    :data:`MAX_POSITION_M` (m; a ``pos_*_mm`` column converted) → BadInputError saying it
    looks like millimetres (or, given, ``unit_hint``). Each names the file, column and
    first offending row.
    """
    v = np.asarray(v, dtype=np.float64)
    top = peak_abs(v)   # the usual case, all in range, from the extremes alone
    scale = 1000.0 if name.endswith("_mm") else 1.0
    if top < MAX_ABS_VALUE and not (name.startswith("pos_") and top / scale > MAX_POSITION_M):
        return v
    badv = np.flatnonzero(~np.isfinite(v))
    if badv.size:
        k = int(badv[0])
        what = "blank value (or NaN)" if np.isnan(v[k]) else cell(float(v[k])) + " value"
        raise BadInputError(f"{what}; force and position must be finite numbers",
                            file=file, column=name, row=k + 1)
    with np.errstate(over="ignore"):
        big = np.flatnonzero(np.abs(v) >= MAX_ABS_VALUE)
    if big.size:
        k = int(big[0])
        raise BadInputError(f"value {cell(float(v[k]))} is far outside any physical force or "
                            "position and would overflow the spectra", file=file, column=name,
                            row=k + 1)
    if name.startswith("pos_"):
        scale = 1000.0 if name.endswith("_mm") else 1.0
        far = np.flatnonzero(np.abs(v) / scale > MAX_POSITION_M)
        if far.size:
            k = int(far[0])
            hint = (f"; the values look like millimetres: name the column "
                    f"{name[:-2]}_mm" if scale == 1.0 and np.abs(v).max() < 5000 else "")
            if unit_hint is not None:
                hint = unit_hint
            raise BadInputError(f"position {cell(float(v[k]))} {'mm' if scale > 1 else 'm'} "
                                f"is beyond {MAX_POSITION_M:g} m, outside a desktop "
                                f"device's workspace{hint}", file=file, column=name,
                                row=k + 1)
    return v


def check_grip(g: np.ndarray, file: str) -> np.ndarray:
    """Refuse infinite or absurd grip samples (NaN, a missing sample, is allowed)."""
    g = np.asarray(g, dtype=np.float64)
    if g.size:   # the usual case, from the extremes of the samples that are not NaN
        top = max(abs(float(np.fmin.reduce(g))), abs(float(np.fmax.reduce(g))))
        if top < MAX_ABS_VALUE:
            return g
    bad = np.flatnonzero(np.isinf(g) | (np.abs(np.nan_to_num(g)) >= MAX_ABS_VALUE))
    if bad.size:
        k = int(bad[0])
        raise BadInputError(f"grip value {cell(float(g[k]))} is not a physical force",
                            file=file, column="grip_N", row=k + 1)
    return g


#: A trial's measured grip (median of the grip_N column) may differ from the grip named
#: by its file name or manifest by this much (N) or this fraction of it, whichever is
#: larger, before a warning: the subject holds a target, not an exact force.
GRIP_TOLERANCE_N = 0.5
GRIP_TOLERANCE_FRACTION = 0.25


def _check_trial(trial: Trial, file: str, *, f_min_hz: float, force_limit_N: float,
                 warn: Warn | None) -> None:
    """Length and excitation checks; saturation warning."""
    meta = trial.meta
    if f_min_hz > 0 and meta.duration_s < 2.0 / f_min_hz:
        raise BadInputError(f"too short: {meta.duration_s:.6g} s; reaching the lowest "
                            f"frequency {f_min_hz:g} Hz needs at least "
                            f"{2.0 / f_min_hz:.6g} s (two periods){{?; lower "
                            "{opt:f_min_hz} or drop the trial}", file=file)
    f = trial.f
    col = f"force_{meta.axis}_N"
    if f.size and f.max() == f.min():
        level = "zero" if f[0] == 0 else f"constant ({f[0]:g} N)"
        raise BadInputError(f"force on the stimulated axis is {level} throughout: no "
                            "excitation", file=file, column=col)
    x = trial.x
    if x.size and x.max() == x.min():
        raise BadInputError(f"position on the stimulated axis is constant ({cell(float(x[0]))}"
                            " m) throughout: no response was recorded", file=file,
                            column=f"pos_{meta.axis}_m")
    if warn is None:
        return
    if trial.grip is not None:
        g = trial.grip[np.isfinite(trial.grip)]
        if g.size:
            med = float(median(g))
            tol = max(GRIP_TOLERANCE_N, GRIP_TOLERANCE_FRACTION * meta.grip_N)
            if abs(med - meta.grip_N) > tol:
                warn(f"{file}, column 'grip_N': the measured grip ({med:.3g} N, median) "
                     f"differs from the {meta.grip_N:g} N the file name or manifest gives; "
                     f"the trial is kept at {meta.grip_N:g} N (if it is mislabelled, rename "
                     "it or correct the manifest)")
    for j, a in enumerate(AXES):
        v = trial.force[:, j]
        over = saturated_samples(v, force_limit_N)
        if over.any():
            k = int(np.argmax(over))
            warn(f"{file}, column 'force_{a}_N', row {k + 1}: |force| reaches the device "
                 f"limit {force_limit_N:g} N in {int(over.sum())} sample(s) (peak "
                 f"{np.nanmax(np.abs(v)):.3g} N); saturation distorts the estimate")


def saturated_samples(force, limit_N: float) -> np.ndarray:
    """Which force samples are saturated: |F| ≥ ``limit_N`` (N).

    The one saturation rule of every check (the warning of :func:`read_trial`, the
    ``saturation`` flag of the spectra): a force clipped by the device sits exactly at
    its limit, so a plateau at the limit is saturation.

    Parameters
    ----------
    force : array_like
        Force samples, N (NaN: not recorded, never saturated).
    limit_N : float
        The device's peak force, N.

    Returns
    -------
    numpy.ndarray
        bool, one per sample.
    """
    f = np.abs(np.asarray(force, dtype=np.float64))
    with np.errstate(invalid="ignore"):
        return f >= limit_N


# ---------------------------------------------------------------------------
# The canonical dataset
# ---------------------------------------------------------------------------

def _dataset_schema(reference: bool = False):
    """The dataset's columns, every one required (not nullable): an absent value is a
    NaN, never a null, so the file holds no definition levels, which the writer would
    otherwise compute and encode for every value (writing a study took 1.2 times as
    long). Readers read a dataset written with nullable columns the same."""
    import pyarrow as pa
    return pa.schema([pa.field("trial", pa.int32(), nullable=False)]
                     + [pa.field(c, pa.float64(), nullable=False) for c in DATASET_COLUMNS]
                     + ([pa.field(DATASET_REFERENCE, pa.float64(), nullable=False)]
                        if reference else []))


def is_dataset(path: str | os.PathLike) -> bool:
    """True if ``path`` is a canonical dataset written by :func:`write_dataset`."""
    p = Path(path)
    if not p.is_file() or _trial_ext(p.name) != ".parquet":
        return False
    try:
        return DATASET_TRIALS_KEY.encode() in (_dataset_footer(p).metadata or {})
    except Exception:  # not Parquet, or unreadable: then it is not a dataset
        return False


def _dataset_footer(path: Path):
    return _parquet_file(path).metadata


def _checked_record(index: int, rec: object, file: str) -> dict:
    """One trial's metadata record, checked and typed (numbers by
    :mod:`armfit.io.numbers`); BadInputError naming the file, the trial and the field."""
    where = f"metadata '{DATASET_TRIALS_KEY}', trial {index}"

    def bad(text: str) -> BadInputError:
        return BadInputError(f"{where}: {text}; the dataset is damaged (write it again with "
                             "armfit ingest)", file=file)

    if not isinstance(rec, dict):
        raise bad(f"the record is {type(rec).__name__}, not an object")
    for key in ("trial", "subject", "axis", "grip_N", "fs", "n_samples", "t0_s", "source"):
        if key not in rec:
            raise bad(f"no '{key}'")

    def number(key: str, ok: Callable[[float], bool], what: str) -> float:
        try:
            v = parse_number(rec[key])
        except ValueError:
            v = math.nan
        if not ok(v):
            raise bad(f"'{key}' is {cell(rec[key])}, not {what}")
        return v

    def whole(key: str, least: int) -> int:
        try:
            v = parse_whole(rec[key])
        except ValueError:
            v = -1
        if v < least:
            raise bad(f"'{key}' is {cell(rec[key])}, not a whole number >= {least}")
        return v

    out = dict(rec)
    out["trial"] = whole("trial", 0)
    if out["trial"] != index:
        raise bad(f"'trial' is {out['trial']}; the records follow the row groups, so it "
                  f"must be {index}")
    if not (isinstance(rec["subject"], str) and _LABEL.fullmatch(rec["subject"])):
        raise bad(f"subject {cell(rec['subject'])} is not an alphanumeric label")
    if rec["axis"] not in AXES:
        raise bad(f"axis {cell(rec['axis'])} is not x, y or z")
    out["grip_N"] = number("grip_N", lambda v: math.isfinite(v) and v >= 0,
                           "a non-negative number of newtons")
    out["run"] = None if rec.get("run") is None else whole("run", 0)
    out["fs"] = number("fs", lambda v: math.isfinite(v) and v >= MIN_SAMPLING_RATE_HZ,
                       f"a sampling rate of at least {MIN_SAMPLING_RATE_HZ:g} Hz")
    out["n_samples"] = whole("n_samples", 2)
    out["t0_s"] = number("t0_s", math.isfinite, "a finite time in s")
    if not isinstance(rec["source"], str):
        raise bad(f"source {cell(rec['source'])} is not a file name")
    cols = rec.get("columns", list(DATASET_COLUMNS))
    if not (isinstance(cols, list) and all(c in DATASET_COLUMNS for c in cols)):
        raise bad(f"columns {cell(cols)} are not among {', '.join(DATASET_COLUMNS)}")
    out["columns"] = cols
    ref = rec.get("reference")
    if ref is not None and ref not in tuple(f"ref_{rec['axis']}_{u}" for u in REFERENCE_UNITS):
        raise bad(f"reference {cell(ref)} is not ref_{rec['axis']}_N or ref_{rec['axis']}_m "
                  "(the stimulated axis's commanded force or reference position)")
    if rec.get("column_map") is not None:
        out["column_map"] = ColumnMap.from_dict(rec["column_map"], where=f"{file}: {where}")
    return out


def dataset_metadata(path: str | os.PathLike) -> list[dict]:
    """The per-trial metadata records of a canonical dataset (one per row group).

    Each record is checked and its numbers typed (``trial``, ``run``, ``n_samples`` int;
    ``grip_N``, ``fs``, ``t0_s`` float, read by :mod:`armfit.io.numbers`). Raises
    BadInputError naming the file and what is wrong: not a dataset, an unsupported
    format version, metadata that is not a JSON list, a record count other than the row
    groups' (trials would be left out), a missing or bad field of a record.
    """
    import pyarrow as pa
    p = Path(path)
    file = str(p)
    try:
        footer = _dataset_footer(p)
    except (pa.ArrowException, OSError) as exc:
        raise BadInputError(f"unreadable or truncated dataset: {_first_line(exc)}",
                            file=file) from None
    kv = footer.metadata or {}
    if DATASET_TRIALS_KEY.encode() not in kv:
        raise BadInputError(f"not an armfit dataset (no '{DATASET_TRIALS_KEY}' metadata)",
                            file=file)
    version = kv.get(DATASET_FORMAT_KEY.encode(), b"").decode("utf-8", "replace")
    if version != DATASET_FORMAT_VERSION:
        raise BadInputError(f"dataset format version '{version}' is not supported (expected "
                            f"{DATASET_FORMAT_VERSION})", file=file)
    try:
        records = json.loads(kv[DATASET_TRIALS_KEY.encode()])
    except (ValueError, RecursionError) as exc:  # JSONDecodeError, bad UTF-8
        raise BadInputError(f"metadata '{DATASET_TRIALS_KEY}' is not valid JSON "
                            f"({_first_line(exc)}); the dataset is damaged (write it again "
                            "with armfit ingest)", file=file) from None
    if not isinstance(records, list):
        raise BadInputError(f"metadata '{DATASET_TRIALS_KEY}' is a JSON "
                            f"{type(records).__name__}, not a list of trials; the dataset "
                            "is damaged (write it again with armfit ingest)", file=file)
    if len(records) != footer.num_row_groups:
        raise BadInputError(f"metadata '{DATASET_TRIALS_KEY}' lists {len(records)} "
                            f"trial(s) but the file holds {footer.num_row_groups} row "
                            "group(s), one per trial; the dataset is damaged (write it "
                            "again with armfit ingest)", file=file)
    return [_checked_record(i, r, file) for i, r in enumerate(records)]


def dataset_sources(path: str | os.PathLike) -> list[TrialSource]:
    """One TrialSource per trial (row group) of a canonical dataset (its metadata checked
    by :func:`dataset_metadata`)."""
    return [TrialSource(str(path), r["subject"], r["axis"], r["grip_N"], r["run"],
                        index=r["trial"]) for r in dataset_metadata(path)]


@functools.lru_cache(maxsize=4)
def _open_dataset(path: str, stamp: tuple[int, int, int]):
    """(ParquetFile, per-trial records) of a dataset, kept while the file is unchanged
    (``stamp``: inode, size, mtime), so that reading trial after trial parses the footer
    and the trials' metadata once, not once per trial."""
    import pyarrow as pa
    records = dataset_metadata(path)
    try:
        pf = _open_parquet(path, stamp)
    except (pa.ArrowException, OSError) as exc:
        raise BadInputError(f"unreadable or truncated dataset: {_first_line(exc)}",
                            file=path) from None
    return pf, records


#: Bytes of trial columns read (float64 values) between two returns of Arrow's freed
#: buffers to the system (:func:`_release_arrow_memory`): about ten trials of 60 s at
#: 1 kHz (seven columns).
RELEASE_ARROW_BYTES = 32 << 20
_read_since_release = 0
_release_lock = threading.Lock()


def _release_arrow_memory(nbytes: int) -> None:
    """Note that a trial's columns (``nbytes`` of values) were read and copied out of its
    table, and return the pages of Arrow's freed buffers to the system once
    :data:`RELEASE_ARROW_BYTES` were read since the last return. Arrow's allocator
    (the C library's in armfit's commands and workers,
    :data:`armfit.workers.ARROW_SYSTEM_POOL`; else pyarrow's mimalloc) keeps the pages
    of the buffers it freed and reuses them for the next trial's; returned after every
    trial, they were taken back from the system at the next (the page faults made
    reading 81 trials of 50-100 s 1.5 times slower: 0.80 s against 0.52 s). Kept
    throughout, they stay bounded by the sizes of buffer met (the same 176 MB after 81
    and 810 trials), and returned every 16 trials, the process held no more (170 MB) and
    read as fast."""
    global _read_since_release
    with _release_lock:
        _read_since_release += nbytes
        if _read_since_release < RELEASE_ARROW_BYTES:
            return
        _read_since_release = 0
    import pyarrow as pa
    pa.default_memory_pool().release_unused()


def _read_dataset_trial(source: TrialSource, *, grip: bool = True) -> Trial:
    import pyarrow as pa
    idx = int(source.index)  # type: ignore[arg-type]
    try:
        st = os.stat(source.path)
    except OSError as exc:
        raise BadInputError(f"unreadable dataset: {_first_line(exc)}", file=source.path) \
            from None
    _check_regular(Path(source.path))
    pf, records = _open_dataset(str(source.path), (st.st_ino, st.st_size, st.st_mtime_ns))
    if not 0 <= idx < len(records):
        raise BadInputError(f"no trial {idx} (the dataset holds {len(records)})",
                            file=source.path)
    rec = records[idx]
    # only the columns the trial has (the others are NaN throughout), grip if asked
    present = set(rec.get("columns", DATASET_COLUMNS))
    names = [c for c in DATASET_COLUMNS if c in present and (grip or c != "grip_N")]
    try:
        table = pf.read_row_group(idx, columns=names, use_threads=False)
    except (pa.ArrowException, OSError) as exc:
        raise BadInputError(f"unreadable or truncated dataset: {_first_line(exc)}",
                            file=source.label) from None
    n = table.num_rows
    force = np.empty((n, 3), order="F")
    pos = np.empty((n, 3), order="F")
    for j, c in enumerate(DATASET_COLUMNS[:6]):
        (force if j < 3 else pos)[:, j % 3] = parse_numbers(
            table.column(c), file=source.label, column=c) if c in names else np.nan
    grip_N = parse_numbers(table.column("grip_N"), file=source.label, column="grip_N"
                           ).copy() if "grip_N" in names else None
    del table
    ref = None
    if rec.get("reference") is not None:
        if DATASET_REFERENCE not in pf.schema_arrow.names:
            raise BadInputError(f"trial {idx} names a reference ({rec['reference']}) but the "
                                f"dataset has no '{DATASET_REFERENCE}' column; the dataset is "
                                "damaged (write it again with armfit ingest)", file=source.path)
        try:
            column = pf.read_row_group(idx, columns=[DATASET_REFERENCE],
                                     use_threads=False).column(0)
        except (pa.ArrowException, OSError) as exc:
            raise BadInputError(f"unreadable or truncated dataset: {_first_line(exc)}",
                                file=source.label) from None
        ref = check_reference(parse_numbers(column, file=source.label,
                                            column=DATASET_REFERENCE).copy(),
                              rec["reference"], source.label)
    _release_arrow_memory(8 * n * (len(names) + (ref is not None)))
    meta = TrialMeta(source.subject, source.axis, float(source.grip_N), source.run,
                     rec["fs"], rec["n_samples"], rec["t0_s"], rec["source"],
                     rec.get("column_map"), rec.get("reference"))
    for j, a in enumerate(AXES):  # a dataset may have been written by other software
        for arr, name in ((force, f"force_{a}_N"), (pos, f"pos_{a}_m")):
            if not _all_nan(arr[:, j]):
                check_values(arr[:, j], name, source.label)
    if grip_N is not None:
        check_grip(grip_N, source.label)
    if n != meta.n_samples:
        raise BadInputError(f"row group has {n} rows, metadata says "
                            f"{meta.n_samples}", file=source.label)
    return Trial(meta, force, pos, grip_N, ref)


def _all_nan(v: np.ndarray) -> bool:
    """True if every value of ``v`` is NaN (a column the trial does not have); a
    column whose first value is a number is settled without a pass over it."""
    return bool(v.size == 0 or (np.isnan(v[0]) and np.isnan(v).all()))


def _record(index: int, trial: Trial) -> dict:
    m = trial.meta
    present = [c for j, c in enumerate(DATASET_COLUMNS[:3]) if not _all_nan(trial.force[:, j])]
    present += [c for j, c in enumerate(DATASET_COLUMNS[3:6]) if not _all_nan(trial.pos[:, j])]
    if trial.grip is not None:
        present.append("grip_N")
    rec = {"trial": index, "subject": m.subject, "axis": m.axis, "grip_N": m.grip_N,
           "run": m.run, "fs": m.fs, "n_samples": m.n_samples, "duration_s": m.duration_s,
           "t0_s": m.t0_s, "source": m.source, "columns": present}
    if m.column_map is not None:
        rec["column_map"] = m.column_map.to_dict()
    if trial.ref is not None:
        rec["reference"] = m.reference
    return rec


def write_dataset(trials: Iterable[Trial], path: str | os.PathLike, *,
                  overwrite: bool = False, reference: bool = False) -> list[TrialMeta]:
    """Write trials to one canonical Parquet dataset, streaming and atomically.

    One row group per trial: ``trial`` (int32) and the float64 columns of
    DATASET_COLUMNS (SI units, NaN where absent), and with ``reference`` the column
    :data:`DATASET_REFERENCE` (each trial's reference, NaN for a trial without one).
    Per-trial metadata (identity, fs, n_samples, duration_s, t0_s, source, columns
    present, the reference's name) is JSON under the key-value metadata key
    ``armfit.trials``; ``armfit.format`` holds the format version. Only one trial is held
    in memory at a time, and one more while it is written: a thread encodes and writes
    each trial's row group (pyarrow does it without the interpreter's lock) while the
    next trial is read and checked, in the order of ``trials``. Raises NoInputError if
    ``trials`` is empty (no file is left), UsageError for a trial with a reference when
    ``reference`` is False (the schema is fixed before the first trial is written:
    :func:`has_reference` of the sources tells). Returns the metadata of the trials
    written.
    """
    import pyarrow as pa
    import pyarrow.parquet as pq

    schema = _dataset_schema(reference)
    metas: list[TrialMeta] = []
    records: list[dict] = []
    with atomic_path(path, overwrite=overwrite) as tmp:
        writer = pq.ParquetWriter(tmp, schema, **_PARQUET_WRITE)
        background = _RowGroupWriter()
        try:
            for i, trial in enumerate(trials):
                n = trial.meta.n_samples
                grip = trial.grip if trial.grip is not None else np.full(n, np.nan)
                # from the arrays' buffers: pyarrow.array would import pandas
                arrays = [numpy_array(np.full(n, i, dtype=np.int32))]
                arrays += [numpy_array(trial.force[:, j]) for j in range(3)]
                arrays += [numpy_array(trial.pos[:, j]) for j in range(3)]
                arrays.append(numpy_array(np.asarray(grip, dtype=np.float64)))
                if reference:
                    arrays.append(numpy_array(np.full(n, np.nan) if trial.ref is None
                                              else np.asarray(trial.ref, dtype=np.float64)))
                elif trial.ref is not None:
                    raise UsageError(f"{trial.meta.source}: the trial has a reference "
                                     f"({trial.meta.reference}) but the dataset is written "
                                     "without a reference column (reference=False)")
                background.write(writer, pa.Table.from_arrays(arrays, schema=schema),
                                 row_group_size=max(n, 1))
                metas.append(trial.meta)
                records.append(_record(i, trial))
            background.wait()
            if not metas:
                raise NoInputError(f"{path}: no trials to write")
            writer.add_key_value_metadata({DATASET_FORMAT_KEY: DATASET_FORMAT_VERSION,
                                           DATASET_TRIALS_KEY: json.dumps(records)})
        finally:
            background.stop()
            writer.close()
    return metas


class _RowGroupWriter:
    """One thread that writes :func:`write_dataset`'s row groups, one at a time and in
    the order given, while the caller reads the next trial. :meth:`write` first waits
    for the row group before (so that at most one trial waits in memory) and raises its
    error; :meth:`wait` waits for the last; :meth:`stop` (before the file is closed,
    whatever happened) waits for the one being written, its outcome no longer wanted."""

    def __init__(self):
        self._pool = None
        self._pending = None

    def write(self, writer, table, **kwargs) -> None:
        from concurrent.futures import ThreadPoolExecutor
        self.wait()
        if self._pool is None:
            self._pool = ThreadPoolExecutor(1, thread_name_prefix="armfit-write")
        self._pending = self._pool.submit(writer.write_table, table, **kwargs)

    def wait(self) -> None:
        pending, self._pending = self._pending, None
        if pending is not None:
            pending.result()

    def stop(self) -> None:
        self._pending = None
        if self._pool is not None:
            self._pool.shutdown(wait=True)
            self._pool = None


# ---------------------------------------------------------------------------
# Streaming a batch
# ---------------------------------------------------------------------------

@dataclass
class TrialStream:
    """Trials of a batch, read one at a time as it is iterated.

    ``sources`` are the trials to read, ``ignored`` the files found but not trials,
    ``skipped`` the trials left out (with ``skip_bad``), filled while iterating.
    Iterating checks that every trial has the reference sampling rate (the first good
    trial's, or with ``resample`` the most common one, to which the others are
    resampled with scipy.signal.resample_poly), and that no two trials read have the
    same identity (:meth:`admit`): a trial that could not be read is no duplicate.
    """

    sources: list[TrialSource]
    ignored: list[Path]
    skipped: list[Skipped] = field(default_factory=list)
    skip_bad: bool = False
    resample: bool = False
    f_min_hz: float = GRID_HZ[0]
    force_limit_N: float = FORCE_LIMIT_N
    warn: Warn | None = None
    #: The source of the trial the iteration yielded last.
    current: TrialSource | None = field(default=None, init=False, repr=False)
    _read: dict[tuple, str] = field(default_factory=dict, init=False, repr=False)

    def __len__(self) -> int:
        return len(self.sources)

    def admit(self, key: tuple[str, str, float, int | None], label: str) -> None:
        """Count the trial ``key`` (subject, axis, grip_N, run), read from ``label``, as
        read. Raises BadInputError naming both files if a trial of the same identity was
        read before (duplicates are counted among the trials read, so a good copy is
        kept when an earlier copy could not be read)."""
        other = self._read.get(key)
        if other is not None:
            subject, axis, grip_N, run = key
            raise BadInputError(f"duplicate trial (subject {subject}, axis {axis}, grip "
                                f"{grip_N:g} N, run {'-' if run is None else run}): also "
                                f"in {other}", file=label)
        self._read[key] = label

    def __iter__(self) -> Iterator[Trial]:
        ref_fs: float | None = self._common_rate() if self.resample else None
        ref_file = "the most common rate"
        for src in self.sources:
            try:
                trial = read_trial(src, f_min_hz=self.f_min_hz,
                                   force_limit_N=self.force_limit_N, warn=self.warn)
                fs = trial.meta.fs
                if ref_fs is None:
                    ref_fs, ref_file = fs, src.label
                elif abs(fs - ref_fs) > RATE_TOLERANCE * ref_fs:
                    if not self.resample:
                        raise BadInputError(
                            f"sampling rate {fs:g} Hz differs from {ref_fs:g} Hz of "
                            f"{ref_file}{{?; pass {{opt:resample}} to resample to a common "
                            "rate}",
                            file=src.label, column="time_s")
                    trial = resample_trial(trial, ref_fs)
                    if self.warn is not None:
                        self.warn(f"{src.label}: resampled from {fs:g} Hz to {ref_fs:g} Hz")
                self.admit(src.key, src.label)
            except BadInputError as exc:
                if not self.skip_bad:
                    raise
                self.skipped.append(Skipped(src.label, exc.detail))
                continue
            self.current = src
            yield trial

    def _common_rate(self) -> float | None:
        """The most common sampling rate among the sources (ties: the first seen)."""
        rates: Counter[float] = Counter()
        for src in self.sources:
            try:
                if src.index is not None:
                    rates[dataset_metadata(src.path)[src.index]["fs"]] += 1
                elif src.column_map is not None:
                    rates[_mapped_rate(src)] += 1
                else:
                    t = _read_table(Path(src.path), ["time_s"])["time_s"]
                    rates[sampling_rate(t, file=src.path)] += 1
            except (BadInputError, KeyError, IndexError):
                continue  # reported when the trial itself is read
        return rates.most_common(1)[0][0] if rates else None


def with_map(inputs: Iterable[str | os.PathLike], column_map: str | os.PathLike | None
             ) -> list[str | os.PathLike]:
    """``inputs`` and the column map, if any: the files an output must not replace."""
    return [*inputs, *([column_map] if column_map is not None else [])]


def resample_trial(trial: Trial, fs: float) -> Trial:
    """Resample a trial to ``fs`` (Hz) with scipy.signal.resample_poly (force, position).

    The up/down ratio is fs_new / fs_old as a fraction with denominator ≤ 1000. Grip
    (a slow, sample-and-hold signal, possibly NaN between samples) takes the last
    sample at or before each new time.
    """
    from scipy.signal import resample_poly

    ratio = Fraction(fs / trial.meta.fs).limit_denominator(1000)
    up, down = ratio.numerator, ratio.denominator
    force = resample_poly(trial.force, up, down, axis=0)
    pos = resample_poly(trial.pos, up, down, axis=0)
    n = force.shape[0]
    grip = None
    if trial.grip is not None:
        idx = np.minimum((np.arange(n) * down) // up, trial.meta.n_samples - 1)
        grip = trial.grip[idx]
    ref = None if trial.ref is None else resample_poly(trial.ref, up, down)
    m = trial.meta
    meta = TrialMeta(m.subject, m.axis, m.grip_N, m.run, float(fs), int(n), m.t0_s, m.source,
                     m.column_map, m.reference)
    return Trial(meta, force, pos, grip, ref)


def map_notes(sources: Iterable[TrialSource]) -> list[str]:
    """One line per distinct column map of ``sources``: the files it is read for and its
    conversions, e.g. ``DATA_EMPS.mat (column map emps.csv): time_s = t (s); force_x_N =
    35.15 N/V × vir (V); pos_x_m = qm (m)``."""
    files: dict[ColumnMap, list[str]] = {}
    for src in sources:
        if src.column_map is not None:
            files.setdefault(src.column_map, []).append(src.path)
    out = []
    for cmap, paths in files.items():
        more = f" and {len(paths) - 1} more file(s)" if len(paths) > 1 else ""
        out.append(f"{paths[0]}{more} (column map {cmap.path}): {cmap.describe()}")
    return out


def open_trials(inputs: Sequence[str | os.PathLike], *,
                manifest: str | os.PathLike | None = None, skip_bad: bool = False,
                resample: bool = False, f_min_hz: float = GRID_HZ[0],
                force_limit_N: float = FORCE_LIMIT_N,
                warn: Warn | None = None,
                column_map: str | os.PathLike | None = None,
                note: Warn | None = None) -> TrialStream:
    """Discover the trials in ``inputs`` and return a stream that reads them one by one.

    Duplicate trials (same subject, axis, grip, run) are refused naming both files,
    before any is read. With ``skip_bad``, files with bad names go to ``skipped``, and a
    duplicate is one of a trial read before (:meth:`TrialStream.admit`): a good copy is
    read when an earlier copy is bad, and a later copy of a good trial is skipped.
    ``column_map`` is the map of every raw file without one of its own (see
    :func:`discover`); ``note`` receives once per distinct map the conversions it makes
    (:func:`map_notes`). Raises NoInputError when nothing is found.
    """
    bad: list[Skipped] | None = [] if skip_bad else None
    kept, ignored = _discover(inputs, manifest, bad, column_map)
    if note is not None:
        for line in map_notes(kept):
            note(line)
    skipped = list(bad or [])
    if not skip_bad:
        first = TrialStream([], [])
        for src in kept:
            first.admit(src.key, src.label)
    if not kept and not skipped:
        where = ", ".join(str(p) for p in inputs) or str(manifest)
        raise NoInputError(f"{where}: no trial files found (expected names like "
                           f"{_NAME_HELP}, or a {{opt:manifest}})")
    return TrialStream(kept, ignored, skipped, skip_bad=skip_bad, resample=resample,
                       f_min_hz=f_min_hz, force_limit_N=force_limit_N, warn=warn)


# ---------------------------------------------------------------------------
# Ingest: raw trials in, canonical dataset out
# ---------------------------------------------------------------------------

@dataclass(frozen=True)
class IngestResult:
    """What :func:`ingest` wrote: the output, the trials' metadata, what it left out."""

    output: str
    trials: tuple[TrialMeta, ...]
    skipped: tuple[Skipped, ...]
    ignored: tuple[str, ...]


def has_reference(source: TrialSource) -> bool:
    """Whether the trial of ``source`` has a reference column on its stimulated axis (its
    header, column map or dataset metadata says; the samples are not read). A source
    that cannot be read says no (reading it reports the fault)."""
    axis = source.axis
    names = {f"ref_{axis}_{u}" for u in REFERENCE_UNITS}
    try:
        if source.index is not None:
            return dataset_metadata(source.path)[source.index].get("reference") is not None
        if source.column_map is not None:
            return any(source.column_map.get(q) is not None for q in names)
        return bool(names & set(_column_names(Path(source.path))))
    except (ArmfitError, IndexError, OSError):
        return False


def _write_streamed(stream: TrialStream, trials: Iterator[Trial], out: Path,
                    overwrite: bool) -> list:
    """:func:`write_dataset` of ``trials`` (read from ``stream``); "every trial was bad"
    when the stream skipped every one."""
    try:
        return write_dataset(trials, out, overwrite=overwrite,
                             reference=any(has_reference(s) for s in stream.sources))
    except NoInputError:
        if not stream.skipped:
            raise
        first = stream.skipped[0]
        raise BadInputError(f"every trial was bad ({len(stream.skipped)} skipped, the first "
                            f"{first.file}: {first.reason}); nothing written",
                            file=str(out)) from None


def ingest(inputs: Sequence[str | os.PathLike], output: str | os.PathLike, *,
           manifest: str | os.PathLike | None = None, skip_bad: bool = False,
           resample: bool = False, f_min_hz: float = GRID_HZ[0],
           force_limit_N: float = FORCE_LIMIT_N,
           overwrite: bool = False, warn: Warn | None = None,
           advance: Callable[[], object] | None = None,
           on_open: Callable[[TrialStream], object] | None = None,
           column_map: str | os.PathLike | None = None,
           note: Warn | None = None,
           on_trial: Callable[[TrialSource, Trial], object] | None = None) -> IngestResult:
    """Read and validate raw trials and write them as one canonical dataset (Parquet).

    The output is refused (OutputError) if it exists without ``overwrite`` or is also
    an input (a column map included). Trials stream from :func:`open_trials` into
    :func:`write_dataset`; the first bad trial stops the run (BadInputError, nothing
    written) unless ``skip_bad``. ``advance`` is called after each trial, ``on_open``
    once with the stream (e.g. to size a progress bar or list ignored files);
    ``column_map`` and ``note`` as in :func:`open_trials`. ``on_trial(source, trial)``
    is given each trial kept, as it is read (before it is written): e.g. to estimate it
    meanwhile without reading its file again (:class:`armfit.spectra.EstimateAlongside`).
    """
    out = Path(output)
    if _trial_ext(out.name) != ".parquet":
        raise UsageError(f"{out}: the dataset is a Parquet file; give an output ending "
                         "in .parquet")
    check_output(out, overwrite=overwrite, inputs=with_map(inputs, column_map),
                 manifest=manifest)
    stream = open_trials(inputs, manifest=manifest, skip_bad=skip_bad, resample=resample,
                         f_min_hz=f_min_hz, force_limit_N=force_limit_N, warn=warn,
                         column_map=column_map, note=note)
    if on_open is not None:
        on_open(stream)

    def counted() -> Iterator[Trial]:
        for trial in stream:
            if on_trial is not None:
                on_trial(stream.current, trial)
            yield trial
            if advance is not None:
                advance()

    try:
        metas = _write_streamed(stream, counted(), out, overwrite)
    except ArmfitError as exc:  # the trials left out so far are listed with it
        if not exc.skipped:
            exc.skipped = tuple((s.file, s.reason) for s in stream.skipped)
        raise
    return IngestResult(str(out), tuple(metas), tuple(stream.skipped),
                        tuple(str(p) for p in stream.ignored))


__all__ = [
    "TRIAL_EXTENSIONS", "DATASET_COLUMNS", "DATASET_FORMAT_KEY", "DATASET_TRIALS_KEY",
    "DATASET_FORMAT_VERSION", "JITTER_TOLERANCE", "RATE_TOLERANCE",
    "MIN_SAMPLING_RATE_HZ", "saturated_samples", "Warn", "TrialMeta",
    "Trial", "TrialSource", "Skipped", "parse_name", "read_manifest", "discover",
    "sampling_rate", "read_trial", "MAX_ABS_VALUE", "MAX_POSITION_M", "check_values",
    "check_grip", "GRIP_TOLERANCE_N", "GRIP_TOLERANCE_FRACTION", "is_dataset",
    "dataset_metadata", "dataset_sources", "write_dataset", "TrialStream",
    "resample_trial", "open_trials", "IngestResult", "ingest", "manifest_maps", "map_notes",
    "with_map", "DATASET_REFERENCE", "REFERENCE_UNITS", "check_reference", "has_reference",
]
