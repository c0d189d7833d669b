"""The armfit version (kept apart so that every module may read it)."""

__version__ = "0.1.0"


__all__ = ["__version__"]
