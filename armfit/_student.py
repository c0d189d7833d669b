"""Student's t quantiles for whole degrees of freedom, without :mod:`scipy.special`.

The intervals of the fits take t quantiles (t₀.₉₇₅ with m − p, G − 1 or subjects − 1
degrees of freedom). ``scipy.special.stdtrit`` would cost the process that needs one a
seventh of a second of imports: the fits' and the diagnosis's workers, and their fork
server, would import scipy for nothing else.

The distribution function of t with ν whole degrees of freedom is a finite sum
(Abramowitz & Stegun 26.7.3 and 26.7.4): with θ = arctan(t/√ν) and c = cos²θ,

- ν odd:  A(t|ν) = (2/π) [θ + sinθ cosθ (1 + (2/3) c + (2·4)/(3·5) c² + …)], ν − 1 terms
  in all after θ, none for ν = 1;
- ν even: A(t|ν) = sinθ [1 + (1/2) c + (1·3)/(2·4) c² + …], ν/2 terms,

where A(t|ν) = P(|T| ≤ t). The quantile solves A(t|ν) = 2p − 1 by Newton's method
(A is concave for t > 0, so the steps from below rise to the root without overshooting),
started from the Cornish–Fisher expansion about the normal quantile; ν = 1 and ν = 2
have closed forms (tan, and (2p − 1)/√(2p(1 − p))). The result agrees with
``scipy.special.stdtrit`` to within 1e-12 relative for ν from 1 to 1000 and p from
0.001 to 0.999 (``tests/test_student.py``; further out, the tail's t is as ill
conditioned in A for both); above 1000 degrees of freedom (the series grow with ν) the
quantile is scipy's.
"""

from __future__ import annotations

import functools
import math

import numpy as np

__all__ = ["t_quantile"]

#: Degrees of freedom above which the quantile is scipy's (``scipy.special.stdtrit``,
#: imported then): the sums here grow with ν and lose accuracy beyond (a fit of more
#: than a thousand residuals, its magnitudes and phases counted).
MAX_SERIES_DOF = 1000


def _normal_quantile(p: float) -> float:
    """The standard normal quantile of ``p`` (0.5 < p < 1): Newton's method on
    ``math.erfc`` from the rational approximation of A&S 26.2.23."""
    q = 1.0 - p
    z = math.sqrt(-2.0 * math.log(q))
    z -= (2.515517 + z * (0.802853 + z * 0.010328)) / (
        1.0 + z * (1.432788 + z * (0.189269 + z * 0.001308)))   # A&S 26.2.23, |ε| < 4.5e-4
    for _ in range(50):
        f = 0.5 * math.erfc(z / math.sqrt(2.0)) - q           # upper tail, accurate
        step = f / (math.exp(-0.5 * z * z) / math.sqrt(2.0 * math.pi))
        z += step
        if abs(step) <= 1e-16 * z:
            break
    return z


def _two_sided(t: float, nu: int) -> tuple[float, float]:
    """A(t|ν) = P(|T| ≤ t) for t ≥ 0 (A&S 26.7.3–4), and its derivative dA/dt."""
    theta = math.atan(t / math.sqrt(nu))
    s, c1 = math.sin(theta), math.cos(theta)
    c = c1 * c1
    odd = nu % 2
    total, term = 0.0, 1.0
    for j in range(1, nu // 2 + 1):   # ν odd: (ν − 1)/2 terms; even: ν/2
        total += term
        term *= c * ((2 * j) / (2 * j + 1) if odd else (2 * j - 1) / (2 * j))
    a = 2.0 / math.pi * (theta + s * c1 * total) if odd else s * total
    log_pdf = (math.lgamma((nu + 1) / 2) - math.lgamma(nu / 2) - 0.5 * math.log(nu * math.pi)
               - (nu + 1) / 2 * math.log1p(t * t / nu))
    return a, 2.0 * math.exp(log_pdf)


@functools.lru_cache(maxsize=256)
def _upper(p: float, nu: int) -> float:
    """The quantile for 0.5 < p < 1, kept for the next call with the same ``p`` and ν
    (a fit's intervals take it for its residuals' degrees of freedom: the trials of a
    study share a few, and a Newton solve at 200 degrees of freedom takes about 1 ms)."""
    if nu == 1:
        return math.tan(math.pi * (p - 0.5))
    if nu == 2:
        return (2.0 * p - 1.0) / math.sqrt(2.0 * p * (1.0 - p))
    z = _normal_quantile(p)
    z2 = z * z
    t = z + z * (z2 + 1) / (4 * nu) + z * (5 * z2 * z2 + 16 * z2 + 3) / (96 * nu * nu) \
        + z * ((3 * z2 + 19) * z2 * z2 + 17 * z2 - 15) / (384 * nu ** 3)
    target = 2.0 * p - 1.0
    for _ in range(100):   # a step from above lands below the root; from below, they rise
        a, da = _two_sided(t, nu)
        step = (target - a) / da
        t += step
        if abs(step) <= 2e-16 * t:
            break
    return t


def t_quantile(df, p):
    """Student's t quantile: the t with P(T ≤ t) = ``p`` for ``df`` degrees of freedom.

    Parameters
    ----------
    df : int or array_like of int
        Degrees of freedom, whole numbers ≥ 1.
    p : float or array_like
        Probabilities in (0, 1).

    Returns
    -------
    float or ndarray
        The quantiles (broadcast shape of ``df`` and ``p``; a float for scalars).

    Raises
    ------
    ValueError
        A degree of freedom that is not a whole number ≥ 1, or p outside (0, 1).
    """
    dfs, ps = np.broadcast_arrays(np.asarray(df, float), np.asarray(p, float))
    if np.any((dfs < 1) | (dfs != np.floor(dfs))):
        raise ValueError(f"degrees of freedom must be whole numbers >= 1, got {df!r}")
    if np.any(~((ps > 0) & (ps < 1))):
        raise ValueError(f"probabilities must lie in (0, 1), got {p!r}")
    if np.any(dfs > MAX_SERIES_DOF):
        from scipy.special import stdtrit
        return stdtrit(df, p)
    out = np.empty(dfs.shape)
    for i in np.ndindex(dfs.shape):
        nu, q = int(dfs[i]), float(ps[i])
        out[i] = 0.0 if q == 0.5 else (_upper(q, nu) if q > 0.5 else -_upper(1.0 - q, nu))
    return float(out) if out.ndim == 0 else out
