"""Literature arm models of the paper's Table IV (Fu & Çavuşoğlu 2010, Fig. 7).

Five-parameter models use H_ARM (eq. 3); three-parameter ones (Kosuge, Lawrence, Tsuji)
are X/F = 1/(m s² + b s + k) with m = Ma, k = k1, b = b1.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd

from armfit.data import paper_table
from armfit.models.arm import h_arm, laplace

#: The work each row of Table IV comes from, by model name: (authors as cited, the
#: reference number in Fu & Çavuşoğlu 2010, year of publication or None where armfit does
#: not record it, what the row is within that work). The paper cites "Speich et al. [18],
#: Kosuge et al. [13], Lawrence [12], and Tsuji et al. [10]" for these models (Sec. IV).
SOURCES: dict[str, tuple[str, int, int | None, str]] = {
    "Speich X": ("Speich et al.", 18, 2005, "X axis"),
    "Speich Y": ("Speich et al.", 18, 2005, "Y axis"),
    "Speich Z": ("Speich et al.", 18, 2005, "Z axis"),
    "Speich 1DOF": ("Speich et al.", 18, 2005, "1 DOF"),
    "Kosuge": ("Kosuge et al.", 13, 1993, ""),
    "Lawrence": ("Lawrence", 12, None, ""),
    "Tsuji": ("Tsuji et al.", 10, 1995, ""),
}
#: Where the reference numbers of :data:`SOURCES` point, for a figure's legend.
REFERENCES_NOTE = "[n]: reference n of Fu & Çavuşoğlu, ICRA 2010"


@dataclass(frozen=True)
class LiteratureModel:
    """One model of Table IV: parameters in SI units (kg, N/m, N·s/m); ``k2`` and
    ``b2`` None for a three-parameter model."""

    name: str
    Ma: float
    k1: float
    b1: float
    k2: float | None
    b2: float | None

    @property
    def label(self) -> str:
        """Authors, reference number in Fu & Çavuşoğlu 2010 and year of the model's
        source, with the row within it (e.g. "Speich et al. [18] 2005, X axis"), from
        :data:`SOURCES`; "<name> (Table IV)" for a model with no source recorded."""
        if self.name not in SOURCES:
            return f"{self.name} (Table IV)"
        authors, ref, year, what = SOURCES[self.name]
        return (f"{authors} [{ref}]" + ("" if year is None else f" {year}")
                + (f", {what}" if what else ""))

    def response(self, f_hz) -> np.ndarray:
        """X/F in m/N at ``f_hz`` (Hz)."""
        if self.k2 is None or self.b2 is None:
            s = laplace(f_hz)
            return 1.0 / (self.Ma * s * s + self.b1 * s + self.k1)
        return h_arm(f_hz, self.Ma, self.k1, self.k2, self.b1, self.b2)


def literature_models() -> list[LiteratureModel]:
    """The rows of Table IV as models."""
    df = paper_table("literature")
    out = []
    for r in df.itertuples(index=False):
        k2 = None if pd.isna(r.k2_N_per_m) else float(r.k2_N_per_m)
        b2 = None if pd.isna(r.b2_Ns_per_m) else float(r.b2_Ns_per_m)
        out.append(LiteratureModel(r.model, float(r.Ma_kg), float(r.k1_N_per_m),
                                   float(r.b1_Ns_per_m), k2, b2))
    return out


__all__ = [
    "REFERENCES_NOTE", "LiteratureModel", "SOURCES", "literature_models",
]
