"""The command line's shared options: one band grammar, error messages naming flags."""

from __future__ import annotations

import pytest

from armfit.cli.messages import cli_message
from armfit.cli.options import bands_by_axis, parse_band, parse_bands
from armfit.constants import PAPER_BANDS
from armfit.errors import OutputError, UsageError


def test_band_grammar_lo_hi_in_hz():
    assert parse_band("0.1:30") == (None, 0.1, 30.0)
    assert parse_band("z=0.2:8", per_axis=True) == ("z", 0.2, 8.0)
    for bad in ("30:1", "0:5", "1-5", "a:b", "1:inf"):
        with pytest.raises(UsageError, match="expected LO:HI in Hz with 0 < LO < HI"):
            parse_band(bad)
    # an axis where the command takes one band for every axis
    with pytest.raises(UsageError, match="expected LO:HI"):
        parse_band("z=0.1:10")
    for bad in ("w=0.1:3", "x=3:1", "x=", "x"):
        with pytest.raises(UsageError, match="expected AXIS=LO:HI or LO:HI"):
            parse_band(bad, per_axis=True)


def test_bands_by_axis_keeps_the_papers_bands_for_axes_not_named():
    # the paper's bands (X, Y 0.1-30 Hz; Z 0.1-10 Hz) unless overridden
    assert bands_by_axis([], PAPER_BANDS) == {"x": (0.1, 30.0), "y": (0.1, 30.0),
                                              "z": (0.1, 10.0)}
    got = bands_by_axis(parse_bands(["z=0.2:8"]), PAPER_BANDS)
    assert got["z"] == (0.2, 8.0) and got["x"] == (0.1, 30.0)
    # a band without an axis applies to every axis; later items win
    got = bands_by_axis(parse_bands(["0.5:20,y=1:2"]), PAPER_BANDS)
    assert got == {"x": (0.5, 20.0), "y": (1.0, 2.0), "z": (0.5, 20.0)}


def test_library_messages_name_options_not_flags():
    exc = OutputError("out.csv: exists; pass {opt} to replace it", option="overwrite=True")
    assert str(exc) == "out.csv: exists; pass overwrite=True to replace it"
    assert cli_message(exc) == "out.csv: exists; pass --overwrite to replace it"
    exc = UsageError("spectra holds several estimators (chebwin, h1); choose one with {opt}",
                     option="method=")
    assert "choose one with method=" in str(exc)
    assert cli_message(exc).endswith("choose one with --method")
    assert cli_message(UsageError("plain")) == "plain"
