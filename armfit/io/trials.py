"""The raw-trial contract: file names, columns, validation; and the canonical dataset.

(Types below are the interface the rest of armfit uses; reading and writing follow.)
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

AXES: tuple[str, ...] = ("x", "y", "z")


@dataclass(frozen=True)
class TrialMeta:
    """Identity and sampling of one trial.

    subject: alphanumeric label; axis: stimulated axis 'x'|'y'|'z'; grip_N: target grip
    force (N); run: repeat index or None; fs: sampling rate (Hz); n_samples; t0_s: time of
    the first sample (s); source: the file it was read from.
    """

    subject: str
    axis: str
    grip_N: float
    run: int | None
    fs: float
    n_samples: int
    t0_s: float
    source: str

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
    grip: (n,) grip force in N (NaN between sensor samples or where absent), or None.
    """

    meta: TrialMeta
    force: np.ndarray
    pos: np.ndarray
    grip: np.ndarray | None = None

    @property
    def f(self) -> np.ndarray:
        """Force on the stimulated axis (N)."""
        return self.force[:, self.meta.axis_index]

    @property
    def x(self) -> np.ndarray:
        """Position on the stimulated axis (m)."""
        return self.pos[:, self.meta.axis_index]
