"""Column maps: how a recording in a lab's own names and units becomes armfit's SI columns.

A column map is a small CSV file, one row per armfit quantity::

    quantity,source,unit,gain,lever_m,sign,value
    time_s,t,s
    force_x_N,vir,V,35.15
    pos_x_m,qm,m

``quantity`` is an armfit column (``time_s``, ``force_<a>_N``, ``pos_<a>_m``, ``grip_N``,
and the rig's excitation ``ref_<a>_N``, a commanded force, or ``ref_<a>_m``, a reference
trajectory) or ``rate_Hz`` (the sampling rate of a file without a time column, in the ``value``
column); ``source`` is the file's column, or a MATLAB variable, ``name:k`` for the
k-th column (1-based) of a matrix variable (MATLAB's ``name(:,k)``); ``unit`` is the
source's unit. The value in SI units is ``sign × gain × unit factor × source``
(``× lever_m`` for an angle: the arc length; ``/ lever_m`` for a torque: the force at
the lever's end). Only ``quantity``, ``source`` and ``unit`` are required columns; the
others may be left out of the header.

:func:`read_column_map` reads and checks a map; every fault is refused naming the map
file, the map's column and row and what was expected (BadInputError, exit 65).
"""

from __future__ import annotations

import csv
import functools
import io
import math
import os
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from armfit.constants import AXES
from armfit.errors import BadInputError, NoInputError, cell
from armfit.io.numbers import parse_number

#: Columns of a map file: the required ones, then the optional ones.
MAP_COLUMNS: tuple[str, ...] = ("quantity", "source", "unit", "gain", "lever_m", "sign",
                                "value")
_REQUIRED = MAP_COLUMNS[:3]

#: The quantities a map may give, besides ``rate_Hz``: armfit's raw-trial columns.
MAP_QUANTITIES: tuple[str, ...] = (
    "time_s", *(f"force_{a}_N" for a in AXES), *(f"pos_{a}_m" for a in AXES), "grip_N",
    *(f"ref_{a}_{u}" for a in AXES for u in ("N", "m")))

#: Units understood, by kind: the factor that turns one unit into the SI unit (s, m,
#: rad, N, N·m). 1 lbf = 4.4482216152605 N (exact, from 1 lb = 0.45359237 kg and
#: g = 9.80665 m/s²); 1 in = 0.0254 m (exact).
TIME_UNITS: dict[str, float] = {"s": 1.0, "ms": 1e-3, "us": 1e-6, "µs": 1e-6, "μs": 1e-6}
LENGTH_UNITS: dict[str, float] = {"m": 1.0, "cm": 1e-2, "mm": 1e-3, "um": 1e-6,
                                  "µm": 1e-6, "μm": 1e-6, "in": 0.0254}
ANGLE_UNITS: dict[str, float] = {"rad": 1.0, "deg": math.pi / 180.0}
FORCE_UNITS: dict[str, float] = {"N": 1.0, "mN": 1e-3, "kN": 1e3, "lbf": 4.4482216152605}
TORQUE_UNITS: dict[str, float] = {"N*m": 1.0, "N·m": 1.0, "Nm": 1.0}
#: Raw signals: they become a quantity only through a ``gain`` (N/V, m/V, s/count, ...).
RAW_UNITS: tuple[str, ...] = ("V", "counts")
RATE_UNITS: dict[str, float] = {"Hz": 1.0, "kHz": 1e3}

#: A matrix column of a MATLAB variable: ``name:k``, k 1-based (MATLAB's ``name(:,k)``,
#: whose comma would split a CSV cell).
_MATRIX = re.compile(r"(?P<name>[^:]+?)\s*:\s*(?P<col>[0-9]+)")


def _kind(quantity: str) -> str:
    if quantity == "time_s":
        return "time"
    if quantity == "rate_Hz":
        return "rate"
    length = quantity.startswith("pos_") or (quantity.startswith("ref_")
                                              and quantity.endswith("_m"))
    return "length" if length else "force"


#: What each kind of quantity accepts, as the message lists it.
_EXPECTED = {
    "time": "a time unit (s, ms, us), or counts with a gain in s/count",
    "length": "a length unit (m, cm, mm, um, in), an angle (rad, deg) with lever_m, or a "
              "raw signal (V, counts) with a gain in m per unit",
    "force": "a force unit (N, mN, kN, lbf), a torque (N*m) with lever_m, or a raw signal "
             "(V, counts) with a gain in N per unit",
    "rate": "Hz or kHz, with the rate in the value column",
}


@dataclass(frozen=True)
class Conversion:
    """One row of a column map: how ``quantity`` (SI) is made from ``source``.

    quantity: armfit's column (``force_x_N``, ...); source: the map's text
    (``io:2``); name: the file's column or variable (``io``); column: the 1-based
    column of a MATLAB matrix, or None; unit: the source's unit as written; gain: SI
    units per raw unit (V, counts), or None; lever_m: the lever arm (m) of an angle or a
    torque, or None; sign: +1 or −1; row: the map's 1-based data row.
    """

    quantity: str
    source: str
    name: str
    column: int | None
    unit: str
    gain: float | None
    lever_m: float | None
    sign: int
    row: int

    @property
    def factor(self) -> float:
        """SI value per source value: sign × gain × unit factor (× or / lever_m)."""
        f = float(self.sign) * (self.gain if self.gain is not None else 1.0)
        f *= _UNIT_FACTOR.get(self.unit, 1.0)
        if self.unit in ANGLE_UNITS:
            f *= self.lever_m  # type: ignore[operator]
        elif self.unit in TORQUE_UNITS:
            f /= self.lever_m  # type: ignore[operator]
        return f

    def apply(self, values: np.ndarray) -> np.ndarray:
        """The source's samples in the quantity's SI unit (float64; the identity
        conversion returns the samples themselves)."""
        v = np.asarray(values, dtype=np.float64)
        f = self.factor
        return v if f == 1.0 else v * f

    def describe(self) -> str:
        """The conversion in words, e.g. ``force_x_N = 35.15 N/V × vir (V)``."""
        si = {"time": "s", "length": "m", "force": "N"}[_kind(self.quantity)]
        minus = "−" if self.sign < 0 else ""
        src = f"{self.source} ({self.unit})"
        if self.gain is not None:
            per = "count" if self.unit == "counts" else self.unit
            return f"{self.quantity} = {minus}{self.gain:.15g} {si}/{per} × {src}"
        parts = [src]
        scale = _UNIT_FACTOR[self.unit]
        if scale != 1.0:
            base = "rad" if self.unit in ANGLE_UNITS else si
            parts.insert(0, f"{scale:.15g} {base}/{self.unit}")
        text = " × ".join(parts)
        if self.unit in ANGLE_UNITS:
            text += f" × {self.lever_m:.15g} m"
        elif self.unit in TORQUE_UNITS:
            text += f" / {self.lever_m:.15g} m"
        return f"{self.quantity} = {minus}{text}"


_UNIT_FACTOR: dict[str, float] = {**TIME_UNITS, **LENGTH_UNITS, **ANGLE_UNITS,
                                  **FORCE_UNITS, **TORQUE_UNITS, **dict.fromkeys(RAW_UNITS, 1.0)}


@dataclass(frozen=True)
class ColumnMap:
    """A checked column map.

    path: the map file as given; conversions: its rows other than ``rate_Hz``, in the
    map's order; rate_Hz: the sampling rate (Hz) of files without a time column, or
    None (a ``time_s`` row is then among the conversions); cells: each row's cells as
    written (quantity, source, unit, gain, lever_m, sign, value), the map's parsed form
    kept in a dataset's provenance.
    """

    path: str
    conversions: tuple[Conversion, ...]
    rate_Hz: float | None
    cells: tuple[tuple[str, ...], ...]

    def get(self, quantity: str) -> Conversion | None:
        """The conversion giving ``quantity``, or None."""
        return next((c for c in self.conversions if c.quantity == quantity), None)

    def describe(self) -> str:
        """Every conversion in words, joined by ``; `` (the map's order)."""
        out = []
        for cells in self.cells:
            if cells[0] == "rate_Hz":
                out.append(f"time_s = sample index / {self.rate_Hz:.15g} Hz")
            else:
                out.append(self.get(cells[0]).describe())  # type: ignore[union-attr]
        return "; ".join(out)

    def check_axis(self, axis: str, file: str) -> None:
        """Refuse the map for a trial of the stimulated ``axis`` (read from ``file``)
        when it gives no force or no position on that axis (BadInputError naming the map
        and the trial's file)."""
        for q, what in ((f"force_{axis}_N", "force"), (f"pos_{axis}_m", "position")):
            if self.get(q) is None:
                given = ", ".join(c.quantity for c in self.conversions
                                  if c.quantity.startswith(("force_", "pos_")))
                raise BadInputError(f"the column map {self.path} has no row for {q}, the "
                                    f"{what} on the stimulated axis {axis} (it gives "
                                    f"{given}); add a row {q},<source>,<unit>", file=file)

    def to_dict(self) -> dict[str, object]:
        """The map as a JSON object: ``file``, ``rows`` (each row's cells as written,
        by column name) and ``conversions`` (:meth:`describe`)."""
        rows = [{k: v for k, v in zip(MAP_COLUMNS, cells, strict=True) if v}
                for cells in self.cells]
        return {"file": self.path, "rows": rows, "conversions": self.describe()}

    @classmethod
    def from_dict(cls, data: Mapping[str, object], *, where: str) -> ColumnMap:
        """The map of :meth:`to_dict`, checked again (BadInputError naming ``where``,
        e.g. a dataset's metadata, when it is not a map)."""
        rows = data.get("rows") if isinstance(data, Mapping) else None
        path = data.get("file") if isinstance(data, Mapping) else None
        if not isinstance(path, str) or not isinstance(rows, list) or not all(
                isinstance(r, Mapping) for r in rows):
            raise BadInputError(f"{where}: the column map is not an object with 'file' and "
                                "a list of 'rows'")
        try:
            return _parse([[str(r.get(k, "")) for k in MAP_COLUMNS] for r in rows],
                          list(MAP_COLUMNS), path)
        except BadInputError as exc:
            raise BadInputError(f"{where}: {exc}") from None


def _number(text: str, *, file: str, column: str, row: int, what: str,
            positive: bool = True) -> float:
    try:
        v = parse_number(text)
    except ValueError:
        v = math.nan
    if not (math.isfinite(v) and (v > 0 or not positive)):
        raise BadInputError(f"{cell(text)} is not {what}", file=file, column=column, row=row)
    return v


def _sign(text: str, *, file: str, row: int) -> int:
    t = text.strip()
    if t in ("", "1", "+1"):
        return 1
    if t == "-1":
        return -1
    raise BadInputError(f"{cell(text)} is not a sign; expected 1 or -1 (blank: 1)",
                        file=file, column="sign", row=row)


def _unit_problem(quantity: str, unit: str) -> bool:
    """True when ``unit`` cannot give ``quantity``."""
    kind = _kind(quantity)
    allowed = {"time": (*TIME_UNITS, "counts"),
               "length": (*LENGTH_UNITS, *ANGLE_UNITS, *RAW_UNITS),
               "force": (*FORCE_UNITS, *TORQUE_UNITS, *RAW_UNITS),
               "rate": tuple(RATE_UNITS)}[kind]
    return unit not in allowed


def _conversion(cells: dict[str, str], row: int, file: str) -> Conversion:
    """One row other than ``rate_Hz``, checked."""
    q, unit = cells["quantity"], cells["unit"]
    source = cells["source"]
    if not source:
        raise BadInputError(f"no source for {q}; expected the file's column or MATLAB "
                            "variable holding it", file=file, column="source", row=row)
    if cells["value"]:
        raise BadInputError(f"a value is given for {q}; only rate_Hz takes a value (the "
                            f"samples of {q} come from its source)", file=file,
                        column="value", row=row)
    if not unit:
        raise BadInputError(f"no unit for {q}; expected {_EXPECTED[_kind(q)]}", file=file,
                            column="unit", row=row)
    if _unit_problem(q, unit):
        raise BadInputError(f"unit {cell(unit)} cannot give {q}; expected "
                            f"{_EXPECTED[_kind(q)]}", file=file, column="unit", row=row)
    gain = None
    if cells["gain"]:
        if unit not in RAW_UNITS:
            raise BadInputError(f"a gain is given for unit {unit}, whose conversion is "
                                f"known; a gain applies to a raw signal ({', '.join(RAW_UNITS)})"
                                "; give the direction in the sign column", file=file,
                                column="gain", row=row)
        gain = _number(cells["gain"], file=file, column="gain", row=row,
                       what="a positive number (SI units per raw unit; give the direction "
                            "in the sign column)")
    elif unit in RAW_UNITS:
        raise BadInputError(f"unit {unit} needs a gain: the SI units of {q} per {unit} "
                            "(e.g. N/V)", file=file, column="gain", row=row)
    lever = None
    levered = unit in ANGLE_UNITS or unit in TORQUE_UNITS
    if cells["lever_m"]:
        if not levered:
            raise BadInputError(f"lever_m is given for unit {unit}; a lever applies only "
                                "to an angle (rad, deg) or a torque (N*m)", file=file,
                                column="lever_m", row=row)
        lever = _number(cells["lever_m"], file=file, column="lever_m", row=row,
                        what="a positive length in m")
    elif levered:
        what = ("the arc length is angle × lever" if unit in ANGLE_UNITS
                else "the force is torque / lever")
        raise BadInputError(f"unit {unit} needs lever_m, the lever arm in m ({what})",
                            file=file, column="lever_m", row=row)
    m = _MATRIX.fullmatch(source)
    name, col = (m["name"].strip(), int(m["col"])) if m else (source, None)
    if col == 0:
        raise BadInputError(f"column 0 of {name}: matrix columns count from 1, as in "
                            f"MATLAB ({name}:1 is the first)", file=file, column="source",
                            row=row)
    return Conversion(q, source, name, col, unit, gain, lever,
                      _sign(cells["sign"], file=file, row=row), row)


def _rate(cells: dict[str, str], row: int, file: str) -> float:
    """The ``rate_Hz`` row: its value in Hz."""
    for key in ("source", "gain", "lever_m", "sign"):
        if cells[key]:
            raise BadInputError(f"rate_Hz takes no {key}; give the sampling rate in the "
                                "value column", file=file, column=key, row=row)
    unit = cells["unit"] or "Hz"
    if unit not in RATE_UNITS:
        raise BadInputError(f"unit {cell(unit)} is not a rate; expected {_EXPECTED['rate']}",
                            file=file, column="unit", row=row)
    if not cells["value"]:
        raise BadInputError("no value for rate_Hz; expected the sampling rate (e.g. 1000)",
                            file=file, column="value", row=row)
    return RATE_UNITS[unit] * _number(cells["value"], file=file, column="value", row=row,
                                      what="a positive sampling rate")


def _parse(rows: Sequence[Sequence[str]], header: list[str], file: str) -> ColumnMap:
    """The checked map of ``rows`` (cells in the order of ``header``)."""
    convs: list[Conversion] = []
    cells_kept: list[tuple[str, ...]] = []
    seen: dict[str, int] = {}
    rate: float | None = None
    for row_no, values in enumerate(rows, start=1):
        cells = dict.fromkeys(MAP_COLUMNS, "")
        cells.update({h: (v or "").strip() for h, v in zip(header, values, strict=False)})
        if len(values) > len(header) and any(v.strip() for v in values[len(header):]):
            split = next((v for v in values if "(:" in v), None)
            hint = (f" (the comma of a source {split.strip()},…) splits it: name a matrix "
                    f"column as {split.split('(')[0].strip()}:k)" if split else "")
            raise BadInputError(f"{len(values)} cells for {len(header)} columns of the "
                                f"header{hint}", file=file, row=row_no)
        q = cells["quantity"]
        if not q and not any(cells.values()):
            continue        # a blank line
        if q != "rate_Hz" and q not in MAP_QUANTITIES:
            raise BadInputError(f"unknown quantity {cell(q)}; expected one of rate_Hz, "
                                f"{', '.join(MAP_QUANTITIES)}", file=file,
                                column="quantity", row=row_no)
        if q in seen:
            raise BadInputError(f"{q} is given twice (also row {seen[q]}); which one is "
                                "meant cannot be known", file=file, column="quantity",
                                row=row_no)
        seen[q] = row_no
        if q == "rate_Hz":
            rate = _rate(cells, row_no, file)
        else:
            convs.append(_conversion(cells, row_no, file))
        cells_kept.append(tuple(cells[k] for k in MAP_COLUMNS))
    for a in AXES:
        if f"ref_{a}_N" in seen and f"ref_{a}_m" in seen:
            raise BadInputError(f"both ref_{a}_N (row {seen[f'ref_{a}_N']}) and ref_{a}_m "
                                f"(row {seen[f'ref_{a}_m']}) are given: a trial's reference "
                                "is a commanded force or a reference position, not both",
                                file=file, column="quantity",
                                row=max(seen[f"ref_{a}_N"], seen[f"ref_{a}_m"]))
    if "time_s" in seen and "rate_Hz" in seen:
        raise BadInputError(f"both time_s (row {seen['time_s']}) and rate_Hz (row "
                            f"{seen['rate_Hz']}) are given; give one: the time column, or "
                            "the rate of a file without one", file=file,
                            column="quantity", row=max(seen["time_s"], seen["rate_Hz"]))
    if "time_s" not in seen and "rate_Hz" not in seen:
        raise BadInputError("no time_s row and no rate_Hz row; expected the time column "
                            "(time_s,<source>,<unit>) or the sampling rate of a file "
                            "without one (rate_Hz with the rate in the value column)",
                            file=file, column="quantity")
    if not any(c.quantity.startswith("force_") for c in convs) or not any(
            c.quantity.startswith("pos_") for c in convs):
        raise BadInputError("the map gives no force or no position; expected a "
                            "force_<a>_N and a pos_<a>_m row for the stimulated axis",
                            file=file, column="quantity")
    return ColumnMap(file, tuple(convs), rate, tuple(cells_kept))


def read_column_map(path: str | os.PathLike) -> ColumnMap:
    """Read and check a column map file (see the module's docstring for its columns).

    Parameters
    ----------
    path : str or os.PathLike
        The map, a CSV file (UTF-8) with a header row.

    Returns
    -------
    ColumnMap

    Raises
    ------
    NoInputError
        The file does not exist (exit 66).
    BadInputError
        Exit 65, naming the map file, its column and row and what was expected: an
        unknown column or quantity, a quantity given twice, both a time and a rate (or
        neither), no force or position, a unit that cannot give the quantity, a raw
        signal without a gain, an angle or torque without a lever, a gain, lever or
        sign that is not a number of the right kind.
    """
    p = Path(path)
    file = str(path)
    if not p.exists():
        raise NoInputError(f"{file}: no such column map file")
    if not p.is_file():
        raise BadInputError("a column map is a regular file (a CSV)", file=file)
    st = p.stat()
    return _read_cached(file, (st.st_ino, st.st_size, st.st_mtime_ns))


@functools.lru_cache(maxsize=16)
def _read_cached(file: str, stamp: tuple[int, int, int]) -> ColumnMap:
    """The map ``file``, read once while it is unchanged (``stamp``: inode, size, mtime)."""
    try:
        text = Path(file).read_text(encoding="utf-8-sig")
    except (OSError, UnicodeDecodeError) as exc:
        raise BadInputError(f"cannot read the column map: {exc}", file=file) from None
    try:
        rows = list(csv.reader(io.StringIO(text)))
    except csv.Error as exc:
        raise BadInputError(f"not a CSV file: {exc}", file=file) from None
    if not rows:
        raise BadInputError("empty; expected a header row quantity,source,unit[,gain]"
                            "[,lever_m][,sign][,value]", file=file)
    header = [h.strip() for h in rows[0]]
    while header and not header[-1]:
        header.pop()        # a trailing comma
    for h in header:
        if h not in MAP_COLUMNS:
            raise BadInputError(f"unknown map column {cell(h)}; expected the columns "
                                f"{', '.join(MAP_COLUMNS)} (the first three required)",
                                file=file, column=h or "(blank)")
        if header.count(h) > 1:
            raise BadInputError("the map column is named twice", file=file, column=h)
    for h in _REQUIRED:
        if h not in header:
            raise BadInputError("missing map column; expected the columns quantity,source,"
                                "unit[,gain][,lever_m][,sign][,value]", file=file, column=h)
    return _parse(rows[1:], header, file)


__all__ = [
    "MAP_COLUMNS", "MAP_QUANTITIES", "TIME_UNITS", "LENGTH_UNITS", "ANGLE_UNITS",
    "FORCE_UNITS", "TORQUE_UNITS", "RAW_UNITS", "RATE_UNITS", "Conversion", "ColumnMap",
    "read_column_map",
]
