"""Tests of armfit.io.atomic: outputs appear whole or not at all, and never destroy an
input or a folder."""

import pytest

from armfit.errors import OutputError
from armfit.io.atomic import atomic_path, check_output, write_text_atomic


def test_write_then_refuse_without_overwrite(tmp_path):
    out = write_text_atomic(tmp_path / "a.txt", "one")
    assert out.read_text() == "one"
    with pytest.raises(OutputError, match="exists; pass overwrite=True"):
        write_text_atomic(out, "two")
    write_text_atomic(out, "two", overwrite=True)
    assert out.read_text() == "two"
    assert [p.name for p in tmp_path.iterdir()] == ["a.txt"]  # no temporary left


def test_failure_leaves_nothing(tmp_path):
    with pytest.raises(RuntimeError, match="interrupted"):
        with atomic_path(tmp_path / "b.txt") as tmp:
            tmp.write_text("half")
            raise RuntimeError("interrupted")
    assert list(tmp_path.iterdir()) == []


def test_file_never_replaces_a_folder(tmp_path):
    folder = tmp_path / "results"
    folder.mkdir()
    (folder / "keep.txt").write_text("mine")
    with pytest.raises(OutputError, match="is a folder"):
        write_text_atomic(folder, "x", overwrite=True)
    assert (folder / "keep.txt").read_text() == "mine"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["results"]


def test_output_that_is_or_holds_an_input(tmp_path):
    inp = tmp_path / "data" / "trials.parquet"
    inp.parent.mkdir()
    inp.write_text("x")
    with pytest.raises(OutputError, match="also an input"):
        check_output(inp, overwrite=True, inputs=[inp])
    with pytest.raises(OutputError, match="also an input"):
        check_output(tmp_path / "data", overwrite=True, inputs=[inp])
    assert check_output(tmp_path / "new.csv", overwrite=False, inputs=[inp]).name == "new.csv"


def test_an_existing_path_inside_the_temporary_is_no_concurrent_writer(tmp_path):
    # an EEXIST raised while the folder is being filled is the filler's own error: the
    # message names OUTDIR and the reason, and does not blame another run
    dest = tmp_path / "out"
    with pytest.raises(OutputError) as err:
        with atomic_path(dest, folder=True) as tmp:
            (tmp / "figures").mkdir()
            (tmp / "figures").mkdir()
    assert str(dest) in str(err.value) and "another run" not in str(err.value)
    assert not dest.exists() and list(tmp_path.iterdir()) == []
