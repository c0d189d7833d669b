"""Which numerical libraries differ from the locked versions of requirements.lock.

Exact output (file bytes, printed numbers of an optimiser's result) is recorded with the
locked set; tests that compare it skip, or compare less, on another set (``make
test-latest`` / ``make test-oldest``).
"""

from __future__ import annotations

from importlib import metadata
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]

#: Libraries whose versions decide the bytes and digits of armfit's outputs.
LOCKED = ("numpy", "scipy", "pandas", "pyarrow", "matplotlib")


def locked_versions(lock: Path = REPO / "requirements.lock") -> dict[str, str]:
    """{name: version} of :data:`LOCKED` in the lock file (names compared lower-case)."""
    out = {}
    for line in lock.read_text(encoding="utf-8").splitlines():
        name, sep, version = line.strip().partition("==")
        if sep and name.lower() in LOCKED:
            out[name.lower()] = version
    return out


def unlocked() -> dict[str, tuple[str, str | None]]:
    """{name: (installed, locked)} of the :data:`LOCKED` libraries whose installed version
    is not the locked one (empty on the locked set)."""
    locked = locked_versions()
    installed = {name: metadata.version(name) for name in LOCKED}
    return {n: (installed[n], locked.get(n)) for n in LOCKED if installed[n] != locked.get(n)}
