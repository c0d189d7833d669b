"""Modules asked for without importing them (armfit._lazy.loaded): a module another
thread is still importing counts as not imported, so code running beside that import
never reaches for a name the module has not defined yet."""

from __future__ import annotations

import sys
import threading
import types
from importlib.machinery import ModuleSpec

import numpy as np

from armfit._lazy import loaded


def test_a_module_half_imported_by_another_thread_is_not_loaded(tmp_path, monkeypatch):
    # a module whose import stops half-way (one name defined, the next not yet) until
    # this thread lets it go on: meanwhile it is in sys.modules but not loaded; once its
    # import has ended it is, with both names
    (tmp_path / "armfit_test_slow_import.py").write_text(
        "import threading\n"
        "FIRST = 1\n"
        "threading.current_thread().halfway.set()\n"
        "threading.current_thread().go_on.wait(30)\n"
        "SECOND = 2\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    name = "armfit_test_slow_import"
    monkeypatch.delitem(sys.modules, name, raising=False)
    assert loaded(name) is None                                  # not imported at all
    importer = threading.Thread(target=__import__, args=(name,), daemon=True)
    importer.halfway, importer.go_on = threading.Event(), threading.Event()
    importer.start()
    assert importer.halfway.wait(30)
    try:
        assert name in sys.modules and not hasattr(sys.modules[name], "SECOND")
        assert loaded(name) is None
    finally:
        importer.go_on.set()
        importer.join(30)
    module = loaded(name)
    assert module is sys.modules[name] and (module.FIRST, module.SECOND) == (1, 2)
    monkeypatch.delitem(sys.modules, name)


def test_numbers_are_read_while_another_thread_imports_pandas(monkeypatch):
    # armfit run's diagnosis read a number of spectra.parquet's metadata (parse_numbers)
    # while the main thread imported pandas: pandas, half made, had no Series yet, the
    # read failed and fell back to reading the whole file. Here pandas is in sys.modules
    # half made (an import under way, no Series): the numbers are read as with no pandas
    from armfit.io.numbers import parse_numbers
    spec = ModuleSpec("pandas", None)
    spec._initializing = True            # as importlib marks a module it is importing
    half = types.ModuleType("pandas")
    half.__spec__ = spec
    monkeypatch.setitem(sys.modules, "pandas", half)
    got = parse_numbers([1.5, 2000, float("nan")], errors="coerce")
    np.testing.assert_array_equal(got, [1.5, 2000.0, np.nan])
