"""Physical ranges of the values armfit reads back from its own files, and the one check
every reader applies to them.

A params file's arm and effect parameters are checked against their own bounds
(:data:`armfit.models.arm.BASE_PARAMS` and each effect's parameters); the ranges below
are those of the other values: the device mass and grip force of a params row, and the
gain, zeros and poles of an uncertainty weight Wu, and the frequencies of a spectra
file. Each is wide enough for any real arm
or device (several decades around the paper's values) and refuses what no measurement
can give: a negative mass, NaN, infinity, 1e300. The table is documented in
docs/formats.md ("Physical ranges").
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from armfit.errors import BadInputError, cell


@dataclass(frozen=True)
class PhysicalRange:
    """The closed range ``[lower, upper]`` (in ``unit``) a value read from a file must lie
    in; ``what`` names the value in messages (e.g. "device mass")."""

    what: str
    unit: str
    lower: float
    upper: float

    def words(self) -> str:
        """'[lower, upper] unit' as a message shows it."""
        unit = f" {self.unit}" if self.unit else ""
        return f"[{self.lower:g}, {self.upper:g}]{unit}"


#: The device's moving mass ``mp_kg`` of a params row (kg): the paper's PHANToM moves
#: about 0.09 kg; a fingertip device a few grams, an admittance robot tens of kilograms.
DEVICE_MASS_RANGE = PhysicalRange("device mass", "kg", 1e-4, 1e3)

#: The grip force ``grip_N`` of a grip or per-trial params row (N): the paper holds 1-3 N;
#: a human power grip stays below about 1000 N.
GRIP_FORCE_RANGE = PhysicalRange("grip force", "N", 0.0, 1e3)

#: The gain K of a weight Wu (eq. 7): its high-frequency magnitude, a relative
#: uncertainty, for a weight with as many zero pairs as pole pairs (as fit-uncertainty
#: writes them and Table III lists them: 0.6-1.8); 1e-6 to 1e6 is -120 to +120 dB.
WU_GAIN_RANGE = PhysicalRange("Wu gain K", "", 1e-6, 1e6)

#: The magnitude |r| of a zero or pole r of Wu (rad/s): Table III's lie between 2 and
#: 250 rad/s; 1e-4 rad/s is a period of 17 hours, 1e7 rad/s far beyond any servo rate.
WU_ROOT_RANGE = PhysicalRange("|zero| or |pole| of Wu", "rad/s", 1e-4, 1e7)


#: A frequency of a spectra file (Hz): armfit's grids start at 0.1 Hz by default and stay
#: below the Nyquist frequency of the recording.
FREQUENCY_RANGE = PhysicalRange("frequency", "Hz", 1e-6, 1e6)


def check_in_range(values, rng: PhysicalRange, *, file: str | None, column: str | None,
                   rows=None, where=None, shown=None, name: str | None = None,
                   tolerance: float = 0.0) -> None:
    """Refuse the first value outside ``rng`` (NaN and infinity included).

    Parameters
    ----------
    values : array_like of float
        The values, one per row of the file.
    rng : PhysicalRange
        Their range.
    file, column : str or None
        Where they were read (named in the message).
    rows : array_like of int, optional
        The 1-based file row of each value (default 1, 2, …).
    where : array_like of bool, optional
        Which values to check (default all).
    shown : sequence, optional
        The cells as the file holds them, for the message (default the values).
    name : str, optional
        The value's name in the message (default ``rng.what``).
    tolerance : float
        Relative slack at the bounds (a bound rounded to 10 digits stays inside).

    Raises
    ------
    BadInputError
        Naming the file, column and row, the value and the range.
    """
    v = np.asarray(values, dtype=float)
    check = np.ones(v.shape, bool) if where is None else np.asarray(where, bool)
    slack = tolerance * max(abs(rng.lower), abs(rng.upper))
    with np.errstate(invalid="ignore"):
        inside = np.isfinite(v) & (v >= rng.lower - slack) & (v <= rng.upper + slack)
    bad = np.flatnonzero(check & ~inside)
    if not bad.size:
        return
    i = int(bad[0])
    row = i + 1 if rows is None else int(np.asarray(rows)[i])
    if column is None and v.size == 1 and rows is None:
        row = None          # a single value that is no cell of a table
    text = _number_text(v[i] if shown is None else shown[i])
    unit = f" {rng.unit}" if rng.unit and np.isfinite(v[i]) else ""
    raise BadInputError(f"{name or rng.what} = {text}{unit} is outside its physical "
                        f"range {rng.words()}", file=file, column=column, row=row)


def _number_text(value) -> str:
    """A value as a message shows it: the text of a cell that holds a number as written,
    any other value as :func:`armfit.errors.cell` shows it (a number plainly, with every
    digit Python keeps, so that a value just outside a bound shows it; text quoted)."""
    if isinstance(value, str):
        try:
            float(value)
        except ValueError:
            return cell(value)
        return value.strip()
    return cell(value)


__all__ = [
    "PhysicalRange", "DEVICE_MASS_RANGE", "GRIP_FORCE_RANGE", "WU_GAIN_RANGE",
    "WU_ROOT_RANGE", "FREQUENCY_RANGE", "check_in_range",
]
