"""The paper's tables (Fu & Çavuşoğlu 2010, Tables I–IV) as reference data."""

from __future__ import annotations

from importlib import resources

import pandas as pd

TABLES = {
    "grip": "table1_grip_dependent.csv",
    "nominal": "table2_nominal.csv",
    "uncertainty": "table3_uncertainty_weights.csv",
    "literature": "table4_literature.csv",
}


def paper_table(name: str) -> pd.DataFrame:
    """Return one of the paper's tables: 'grip' (I), 'nominal' (II), 'uncertainty' (III),
    'literature' (IV), as printed (SI units)."""
    with resources.files(__name__).joinpath(TABLES[name]).open() as fh:
        return pd.read_csv(fh)


__all__ = [
    "TABLES", "paper_table",
]
