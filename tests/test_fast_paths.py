"""The estimator's fast paths give the numbers of the library calls they replace, and the
commands import only what they use.

Each replacement is checked against the computation it stands for: scipy's windows,
``scipy.ndimage.uniform_filter1d``, ``scipy.stats.qmc.Sobol``, ``pyarrow.array`` and
``Array.to_numpy``, the pandas writer of the spectra file; the serial estimate, which
reads the next trial in a thread, against the task the worker processes run. The import
checks run a fresh interpreter and read its ``sys.modules`` after the command.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
from conftest import fresh_json, modules_after
from scipy import ndimage, signal
from scipy.stats import qmc

import armfit
from armfit import _shared
from armfit.data import sobol_points
from armfit.errors import BadInputError
from armfit.io.arrow import arrow_array
from armfit.io.numbers import parse_numbers
from armfit.io.trials import (
    MAX_ABS_VALUE,
    MAX_POSITION_M,
    check_values,
    dataset_sources,
    saturated_samples,
)
from armfit.noise import _moving_mean as _moving_mean_exact
from armfit.spectra import (
    EstimateConfig,
    Response,
    Spectra,
    TrialResponses,
    _block,
    _cached_bands,
    _cached_window,
    _installed_version,
    _majority_flags,
    _pandas_metadata,
    _subject_means,
    _trial_blocks,
    aggregate,
    derived_spectra,
    drift_flags,
    drifting,
    estimate_trial_checked,
    h2_to_grid,
    moving_mean,
    saturated,
    to_grid,
    welch_spectra,
    write_parts,
)

REPO = Path(__file__).resolve().parents[1]
TRIAL = REPO / "sample_data/study/sub-01_axis-x_grip-1N.parquet"


@pytest.mark.parametrize("name", ["hann", "hamming"])
@pytest.mark.parametrize("n", [1, 2, 3, 255, 256, 32768, 36001])
@pytest.mark.parametrize("periodic", [True, False])
def test_windows_are_scipys_to_the_bit(name, n, periodic):
    # the reference: scipy.signal.get_window, which these windows replace
    assert np.array_equal(_cached_window(name, n, periodic),
                          signal.get_window(name, n, fftbins=periodic))


def test_other_windows_come_from_scipy():
    assert np.array_equal(_cached_window("blackman", 64, True),
                          signal.get_window("blackman", 64, fftbins=True))


@pytest.mark.parametrize("width", [1, 2, 7, 10, 1000, 4999, 5000])
def test_moving_mean_is_uniform_filter1d(width):
    # the reference: scipy.ndimage.uniform_filter1d(mode="nearest"), the filter replaced;
    # a record with a posture offset and drift, as the drift check sees it
    rng = np.random.default_rng(3)
    x = 0.1 + np.cumsum(rng.normal(0, 1e-4, 5000)) + rng.normal(0, 1e-3, 5000)
    ref = ndimage.uniform_filter1d(x, width, mode="nearest")
    np.testing.assert_allclose(moving_mean(x, width), ref, rtol=1e-12, atol=1e-15)


@pytest.mark.parametrize("size", [1, 2, 3, 8, 9, 31])
def test_pooled_noise_mean_is_uniform_filter1d_to_the_bit(size):
    # the standard errors are pooled over neighbouring bins (armfit.noise) by a running
    # sum in numpy; the reference is scipy.ndimage.uniform_filter1d(mode="nearest"), the
    # filter it replaces, which it must equal exactly (the outputs' bits depend on it).
    # Rows of squared standard errors spanning decades, a row of NaN, short rows.
    rng = np.random.default_rng(11)
    for n in (1, 2, 5, 40, 397):
        x = rng.lognormal(sigma=3.0, size=(4, n)) * 1e-3
        x[1] = np.nan
        ref = ndimage.uniform_filter1d(x, size, axis=-1, mode="nearest")
        assert np.array_equal(_moving_mean_exact(x, size), ref, equal_nan=True)


def test_welch_up_to_fmax_keeps_the_full_spectra_bins():
    # bins above fmax are dropped, the kept ones unchanged to the bit; the full spectra
    # are themselves scipy.signal.csd/welch (tests/test_spectra.py)
    rng = np.random.default_rng(0)
    f = rng.normal(size=20000)
    x = np.stack([np.convolve(f, [0.5, 0.3, 0.2])[:20000] + 0.1 * rng.normal(size=20000),
                  rng.normal(size=20000)], axis=1)
    full = welch_spectra(f, x, 1000.0, nperseg=4096)
    cut = welch_spectra(f, x, 1000.0, nperseg=4096, fmax_hz=30.0)
    nb = cut.freq_hz.size
    assert cut.freq_hz[-2] <= 30.0 < cut.freq_hz[-1]           # one bin above fmax kept
    assert np.array_equal(cut.freq_hz, full.freq_hz[:nb])
    for a in ("p_ff", "p_fx", "p_xx"):
        assert np.array_equal(getattr(cut, a), getattr(full, a)[..., :nb]), a
    _, p_ref = signal.welch(f, 1000.0, nperseg=4096)
    np.testing.assert_allclose(cut.p_ff, p_ref[:nb], rtol=1e-12)


def test_welch_of_a_list_of_signals_is_welch_of_their_columns():
    # the estimate passes a trial's position columns as they are, not stacked: the
    # same spectra as the (n, k) array of the same signals
    rng = np.random.default_rng(2)
    f = rng.normal(size=20000)
    pos = np.asfortranarray(rng.normal(size=(20000, 3)))
    cols = [pos[:, 1], pos[:, 0], pos[:, 2]]
    a = welch_spectra(f, np.stack(cols, axis=1), 1000.0, nperseg=2048, fmax_hz=30.0)
    b = welch_spectra(f, cols, 1000.0, nperseg=2048, fmax_hz=30.0)
    for name in ("freq_hz", "p_ff", "p_fx", "p_xx"):
        assert np.array_equal(getattr(a, name), getattr(b, name)), name
    assert b.p_fx.shape == (3, a.freq_hz.size)


def test_derived_spectra_up_to_fmax_keep_the_full_spectra_bins():
    # tfestimate's nfft puts most bins far above the grid: those above fmax are dropped,
    # the kept ones unchanged to the bit (the full spectra are checked against Octave's
    # tfestimate in tests/test_bench_octave.py)
    rng = np.random.default_rng(1)
    f = rng.normal(size=30001)
    x = 1e-3 * np.convolve(f, [0.5, 0.3, 0.2])[:30001] + 1e-5 * rng.normal(size=30001)
    full = derived_spectra(f, x, 1000.0, 0.12)
    cut = derived_spectra(f, x, 1000.0, 0.12, fmax_hz=30.0)
    nb = cut.freq_hz.size
    assert cut.freq_hz[-2] <= 30.0 < cut.freq_hz[-1] and nb < full.freq_hz.size // 10
    for a in ("freq_hz", "p_ff", "p_fx", "p_xx"):
        assert np.array_equal(getattr(cut, a), getattr(full, a)[..., :nb]), a
    assert (cut.n_avg, cut.enbw_bins, cut.first_bin) == (
        full.n_avg, full.enbw_bins, full.first_bin)


def test_grid_bands_shared_between_spectra_leave_each_ones_numbers_unchanged():
    # the bands are made once per bins and reused (H1 and H2, trial after trial): each
    # spectrum brought to the grid with the bands already made gives the numbers it
    # gives with none made yet
    rng = np.random.default_rng(4)
    grid = np.geomspace(0.5, 30.0, 60)
    spectra = []
    for k in range(3):
        f = rng.normal(size=40000)
        x = np.convolve(f, [0.4, 0.3, 0.2, 0.1])[:40000] + (0.05 + k) * rng.normal(size=40000)
        spectra.append(welch_spectra(f, x, 1000.0, nperseg=2048, fmax_hz=30.0))

    def responses(sp):
        return [to_grid(sp, grid, max_avg=32.0), h2_to_grid(sp, grid, max_avg=32.0)]

    fresh = []
    for sp in spectra:
        _cached_bands.cache_clear()
        fresh.append(responses(sp))
    _cached_bands.cache_clear()
    shared = [responses(sp) for sp in spectra]
    assert _cached_bands.cache_info().hits >= len(spectra)
    for a, b in zip(fresh, shared, strict=True):
        for ra, rb in zip(a, b, strict=True):
            for name in ("h", "coherence", "se_db", "se_deg", "n_avg"):
                assert np.array_equal(getattr(ra, name), getattr(rb, name),
                                      equal_nan=True), name


def test_drift_flags_found_while_reading_are_the_estimates_own():
    # the serial estimate finds the drift flags in its reading thread: given to the
    # trial's estimate, the responses are those it gives finding them itself; a flag
    # given is the one used (the estimate does not find it again)
    trial = pq.read_table(TRIAL).to_pandas()
    force = np.asfortranarray(trial[[f"force_{a}_N" for a in "xyz"]].to_numpy(float))
    pos = np.array(trial[[f"pos_{a}_m" for a in "xyz"]].to_numpy(float), order="F")
    pos[:, 1] += np.linspace(0.0, 0.05, pos.shape[0])      # y drifts 5 cm
    fs = 1.0 / float(np.median(np.diff(trial["time_s"].to_numpy())))
    config = EstimateConfig()
    flags = drift_flags(pos, fs, config)
    assert flags == {j: drifting(pos[:, j], fs, config.fmin, config.drift_factor)
                     for j in range(3)}
    assert flags[1] and not flags[0]
    own, _ = estimate_trial_checked(force, pos, fs, "x", config)
    given, _ = estimate_trial_checked(force, pos, fs, "x", config, drift=flags)
    assert [r.flags for r in own] == [r.flags for r in given]
    assert any("drift" in f for r in own if r.out_axis == "y" for f in r.flags)
    said, _ = estimate_trial_checked(force, pos, fs, "x", config,
                                     drift={0: True, 1: False, 2: True})
    for r in said:
        assert all(("drift" in f) == (r.out_axis != "y") for f in r.flags), r.out_axis


def test_trial_estimate_does_not_depend_on_the_arrays_memory_layout():
    # trials are read into column-major (n, 3) arrays, each signal contiguous; a caller's
    # row-major arrays give the same responses to the bit
    trial = pq.read_table(TRIAL).to_pandas()
    force = np.ascontiguousarray(trial[[f"force_{a}_N" for a in "xyz"]].to_numpy(float))
    pos = np.ascontiguousarray(trial[[f"pos_{a}_m" for a in "xyz"]].to_numpy(float))
    fs = 1.0 / float(np.median(np.diff(trial["time_s"].to_numpy())))
    config = EstimateConfig()
    rows, _ = estimate_trial_checked(force, pos, fs, "x", config)
    cols, _ = estimate_trial_checked(np.asfortranarray(force), np.asfortranarray(pos), fs,
                                     "x", config)
    assert len(rows) == len(cols) >= 3
    for r, c in zip(rows, cols, strict=True):
        for a in ("h", "coherence", "se_db", "se_deg"):
            assert np.array_equal(getattr(r, a), getattr(c, a), equal_nan=True), a
        assert r.flags == c.flags


def test_subject_means_are_each_subjects_aggregate_to_the_bit():
    # the reference: aggregate(runs, "mean") subject by subject; single runs (done all
    # at once) whose phase turns through several cycles, a subject with two runs, one
    # with a cell without signal (NaN) and one with a zero
    rng = np.random.default_rng(7)
    f = np.geomspace(0.1, 30.0, 100)
    base = 1e-3 / (1.0 + 1j * f / 3.0) ** 2 * np.exp(-2j * np.pi * f * 0.04)
    runs = [(base * (1.0 + 0.1 * rng.normal(size=(1, f.size)))
             * np.exp(0.2j * rng.normal(size=(1, f.size)))) for _ in range(6)]
    runs.append(np.concatenate([runs[0], runs[1] * 1.1]))
    runs.append(runs[2].copy())
    runs[-1][0, 40] = np.nan
    runs.append(runs[3].copy())
    runs[-1][0, 7] = 0.0
    got = _subject_means(runs)
    ref = np.array([aggregate(h, "mean") for h in runs])
    assert got.shape == (9, f.size)
    assert got.tobytes() == ref.tobytes()


@pytest.mark.parametrize("batch", [1, 3, 64])
def test_trial_rows_made_in_batches_are_each_responses_own(batch):
    # the reference: each response's row made alone (_block: its magnitude and its
    # phase unwrapped over its finite cells); responses whose phase turns through
    # several cycles, one with cells without signal (NaN) and one with a zero
    rng = np.random.default_rng(5)
    f = np.geomspace(0.1, 30.0, 100)
    base = 1e-3 / (1.0 + 1j * f / 3.0) ** 2 * np.exp(-2j * np.pi * f * 0.05)
    trials = []
    for t in range(4):
        hs = [base * (1.0 + 0.1 * rng.normal(size=f.size)) for _ in range(3)]
        if t == 1:
            hs[1][[0, 40, 41]] = np.nan
        if t == 2:
            hs[2][7] = 0.0
        rs = tuple(Response(kind, "x", "h1", h, np.full(f.size, 0.9), np.full(f.size, 0.1),
                            np.full(f.size, 1.0), ("",) * f.size)
                   for kind, h in zip(("measured", "derived", "cross"), hs, strict=True))
        trials.append(TrialResponses(f"{t:02d}", "x", 1.0, None, f"t{t}", f, rs))
    got = list(_trial_blocks(trials, batch=batch))
    ref = [_block("trial", tr.subject, tr.axis, tr.grip_N, tr.run, r.kind, r.out_axis,
                  r.method, tr.freq_hz, r.h, r.coherence, r.se_db, r.se_deg, 1, r.flags)
           for tr in trials for r in tr.responses]
    assert len(got) == len(ref) == 12
    for g, r in zip(got, ref, strict=True):
        assert g.keys() == r.keys()
        for key in g:
            if isinstance(r[key], np.ndarray):
                assert g[key].tobytes() == r[key].tobytes(), key
            else:
                assert g[key] == r[key] or (g[key] != g[key] and r[key] != r[key]), key


@pytest.mark.parametrize("members", [1, 2, 3, 4, 9, 27])
def test_majority_flags_count_each_flag_of_each_response(members):
    # the reference: the definition, frequency by frequency, each comma-separated flag
    # of each response counted (an unknown flag too, though never written; a flag
    # repeated in one string counts twice), those above half of the responses written
    # in the fixed order
    order = ("low_coherence", "saturation", "drift", "no_signal", "not_excitation")
    pool = ["", "drift", "low_coherence", "low_coherence,drift", "saturation,drift",
            "no_signal", "not_excitation", "drift,drift", "other", "low_coherence,other"]
    rng = np.random.default_rng(members)
    rows = [[pool[k] for k in rng.integers(0, len(pool), 40)] for _ in range(members)]
    expected = []
    for per_freq in zip(*rows, strict=True):
        flags = [f for s in per_freq for f in s.split(",") if f]
        expected.append(",".join(f for f in order if 2 * flags.count(f) > members))
    assert _majority_flags(rows) == expected
    assert _majority_flags([]) == []


@pytest.mark.parametrize("kind, values", [
    ("float64", [1.5, np.nan, -0.0, 1e300, np.nan]),
    ("float64", []),
    ("int64", [3, None, 0, -7]),
    ("int64", [1, 2]),
    ("large_string", ["x", None, "", "µ,ß", "trial"]),
    ("large_string", ["a", "b"]),
])
def test_arrow_arrays_equal_pyarrows(kind, values):
    # the reference: pyarrow.array(..., from_pandas=True), which they replace
    ref = pa.array(np.array(values, dtype=float) if kind == "float64" else values,
                   type=getattr(pa, kind)(), from_pandas=True)
    got = arrow_array(np.array(values, dtype=float) if kind == "float64" else values, kind)
    assert got.type == ref.type and got.null_count == ref.null_count
    assert got.equals(ref)


@pytest.mark.parametrize("kind, values, repeats", [
    ("large_string", ["x", None, "", "µ,ß", "trial"], [3, 2, 4, 0, 1]),
    ("large_string", ["ab", "c"], [0, 0]),
    ("large_string", [], []),
    ("large_string", [None, None], [2, 1]),
    ("int64", [3, None, 0], [2, 3, 1]),
    ("float64", [1.5, None, np.nan, -0.0], [1, 2, 3, 4]),
])
def test_arrow_arrays_of_repeated_values_equal_pyarrows(kind, values, repeats):
    # the reference: pyarrow.array of the cells repeated one by one (from_pandas=True)
    cells = [v for v, r in zip(values, repeats, strict=True) for _ in range(r)]
    if kind == "float64":
        cells = [np.nan if v is None else v for v in cells]
    ref = pa.array(cells, type=getattr(pa, kind)(), from_pandas=True)
    got = arrow_array(values, kind, repeats=repeats)
    assert len(got) == sum(repeats)
    assert got.type == ref.type and got.null_count == ref.null_count
    assert got.equals(ref)
    if kind == "large_string":   # the same buffers as the cells made one by one
        flat = arrow_array(cells, kind)
        assert [b and b.to_pybytes() for b in got.buffers()] == \
            [b and b.to_pybytes() for b in flat.buffers()]


@pytest.mark.parametrize("typ", [pa.float64(), pa.float32(), pa.int8(), pa.int32(),
                                 pa.int64(), pa.uint16(), pa.uint64()])
def test_numeric_columns_read_as_to_numpy_reads_them(typ):
    # the reference: Array.to_numpy, with nulls as NaN; slices have an offset
    cells = [None if i % 4 == 0 else i for i in range(40)]
    arr = pa.array(cells, type=typ)
    for a in (arr, arr.slice(5, 17), pa.chunked_array([arr.slice(0, 9), arr.slice(9)])):
        flat = a.combine_chunks() if isinstance(a, pa.ChunkedArray) else a
        ref = np.asarray(flat.to_numpy(zero_copy_only=False), dtype=np.float64)
        assert np.array_equal(parse_numbers(a), ref, equal_nan=True)


@pytest.mark.parametrize("name, bad", [
    ("force_x_N", None), ("pos_y_m", None), ("pos_z_mm", None),
    ("force_x_N", np.nan), ("force_y_N", -np.inf), ("force_z_N", 1e100),
    ("force_x_N", -1e100), ("pos_x_m", 0.5), ("pos_x_m", np.nextafter(0.5, 1.0)),
    ("pos_y_m", -0.6), ("pos_x_mm", 500.0), ("pos_x_mm", -500.001), ("pos_z_m", np.nan),
])
def test_sample_checks_refuse_exactly_the_samples_their_rule_names(name, bad):
    # the rule, sample by sample: finite, |v| < MAX_ABS_VALUE, and for a position
    # |v| / (1000 if mm else 1) <= MAX_POSITION_M; the first sample breaking it is named
    v = np.random.default_rng(3).uniform(-0.4, 0.4, 1000) * (1000.0 if "_mm" in name else 1)
    if bad is not None:
        v[[417, 802]] = bad
    scale = 1000.0 if name.endswith("_mm") else 1.0
    with np.errstate(invalid="ignore"):
        broken = ~np.isfinite(v) | (np.abs(v) >= MAX_ABS_VALUE)
        if name.startswith("pos_"):
            broken |= np.abs(v) / scale > MAX_POSITION_M
    if not broken.any():
        assert check_values(v, name, "t.csv") is v
        return
    with pytest.raises(BadInputError) as err:
        check_values(v, name, "t.csv")
    assert err.value.row == int(np.flatnonzero(broken)[0]) + 1 == 418
    assert err.value.column == name


@pytest.mark.parametrize("limit", [7.0, 8.0, 0.5, np.inf, -1.0])
@pytest.mark.parametrize("force", [[3.0, -8.0, 1.0], [8.0], [-7.999], [], [np.nan, 9.0],
                                   [np.nan, 1.0], [np.inf], [-np.inf, np.nan]])
def test_saturation_from_the_extremes_is_the_sample_rule(force, limit):
    # the reference: any sample with |F| >= the limit (saturated_samples; NaN never is)
    f = np.array(force, dtype=float)
    assert saturated(f, limit) == bool(saturated_samples(f, limit).any())


@pytest.mark.parametrize("n, d", [(512, 5), (512, 13), (1, 3), (100, 32), (4096, 2)])
def test_sobol_points_are_scipys(n, d):
    # the reference: scipy.stats.qmc.Sobol, unscrambled (the fits' global-search starts)
    with pytest.warns(UserWarning) if n & (n - 1) else _nothing():
        ref = qmc.Sobol(d=d, scramble=False).random(n)
    assert np.array_equal(sobol_points(n, d), ref)


def test_sobol_points_beyond_the_table_are_left_to_scipy():
    assert sobol_points(8, 33) is None and sobol_points(4097, 2) is None


class _nothing:
    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return False


def test_spectra_file_is_what_the_pandas_writer_made(spectra, tmp_path):
    # the reference: pyarrow's Table.from_pandas of Spectra.to_frame(), as the file was
    # written before; same table, same schema metadata (pandas reads it back as before)
    s = Spectra.read(spectra)
    part = s.take(np.arange(min(len(s), 40)))
    out = write_parts([part], s.meta, tmp_path / "s.parquet")
    frame = part.to_frame()
    frame.attrs = {}
    ref = pa.Table.from_pandas(frame, preserve_index=False)
    got = pq.read_table(out)
    assert got.schema.metadata[b"pandas"] == ref.schema.metadata[b"pandas"]
    assert got.select(ref.column_names).cast(ref.schema).equals(ref.replace_schema_metadata())
    assert _pandas_metadata() == ref.schema.metadata[b"pandas"]
    back = pq.read_table(out).to_pandas()
    assert str(back["level"].dtype) == str(frame["level"].dtype)
    assert str(back["run"].dtype) == "Int64"


@pytest.mark.parametrize("name", ["pandas", "numpy", "pyarrow", "click",
                                  "python-dateutil"])
def test_installed_versions_are_importlib_metadatas(name):
    # the reference: importlib.metadata.version (python-dateutil's package is named
    # dateutil: its version comes from importlib.metadata itself)
    from importlib.metadata import version
    assert _installed_version(name) == version(name)


def test_estimate_loads_neither_pandas_nor_scipy(tmp_path):
    # estimating and writing spectra needs numpy and pyarrow only (start-up of a
    # command a shell script runs once per trial file)
    loaded = modules_after(["-q", "estimate", str(TRIAL), "-o", str(tmp_path / "s.parquet")])
    assert "armfit.spectra" in loaded
    assert not loaded & {"pandas", "scipy", "matplotlib", "rich", "armfit.fitting"}


def test_ingest_loads_no_pandas_and_writes_what_pyarrow_array_would(tmp_path):
    # the dataset's columns are made from the numpy arrays' buffers (pyarrow.array
    # imports pandas, about 0.15 s of a one-trial ingest's 0.27 s); the reference is
    # pyarrow.array itself: the same values (NaN a number, not a null), type and nulls
    import pyarrow as pa

    from armfit.io.arrow import numpy_array
    out = tmp_path / "t.parquet"
    loaded = modules_after(["-q", "ingest", str(TRIAL), "-o", str(out)])
    assert "armfit.io.trials" in loaded and not loaded & {"pandas", "scipy"}
    import pyarrow.parquet as pq
    raw = pq.read_table(TRIAL, columns=["force_x_N"]).column(0).to_numpy()
    np.testing.assert_array_equal(armfit.read_trials(out).trials[0].force[:, 0], raw)
    x = np.array([0.5, np.nan, -np.inf, 2.0])
    for values in (x, np.arange(5, dtype=np.int32), np.arange(12.0).reshape(3, 4)[:, 1]):
        ours, theirs = numpy_array(values), pa.array(values)
        assert ours.type == theirs.type and ours.null_count == theirs.null_count == 0
        assert ours.to_numpy(zero_copy_only=False).tobytes() == \
            theirs.to_numpy(zero_copy_only=False).tobytes()


def test_fit_nominal_loads_no_figures_no_scipy_package_and_no_pandas(spectra, tmp_path,
                                                                    monkeypatch):
    # reading the medians, fitting them and writing the params file: no pandas (its
    # import is a third of the command), no pyarrow.compute, no scipy.optimize (the
    # fits' solver is armfit._trf; importing scipy.optimize took half the command) and
    # no scipy.special (the intervals' t quantiles are armfit._student's: 0.13 s)
    out = tmp_path / "n.csv"
    loaded = modules_after(["-q", "fit-nominal", str(spectra), "-o", str(out)])
    assert "armfit.fitting" in loaded and "armfit._trf" in loaded
    assert not loaded & {"matplotlib", "scipy.stats", "scipy.signal", "armfit.figures",
                         "armfit.diagnosis.search", "armfit.loop", "pandas",
                         "pyarrow.compute", "scipy.optimize", "scipy.linalg",
                         "scipy.special"}
    # the intervals are those of scipy's t quantiles (an independent computation:
    # scipy.special.stdtrit, cephes) to within the last bits of a float
    from scipy.special import stdtrit

    import armfit.fitting
    ours = armfit.fit_nominal(spectra).table
    monkeypatch.setattr(armfit.fitting, "t_quantile", stdtrit)
    theirs = armfit.fit_nominal(spectra).table
    ends = [c for c in ours.columns if c.endswith(("_lo", "_hi"))]
    assert ends and np.isfinite(ours[ends].to_numpy(float)).any()
    np.testing.assert_allclose(ours[ends].to_numpy(float), theirs[ends].to_numpy(float),
                               rtol=1e-12, atol=0)
    # the reference: the same fits' DataFrame written by pandas, as the file was written
    # before; and the model's table is that DataFrame
    model = armfit.fit_nominal(spectra)
    frame = model.table
    assert isinstance(frame, pd.DataFrame) and len(frame) == len(model.fits) > 0
    assert out.read_text() == frame.to_csv(index=False, float_format="%.10g")


def test_the_wall_crossings_take_lapack_ggev_without_importing_scipy_linalg():
    # the stability stage's one LAPACK routine (ggev, the pencils' generalised
    # eigenvalues) is the function scipy.linalg.get_lapack_funcs chooses, taken from
    # scipy's LAPACK module loaded alone: importing scipy.linalg took about 0.13 s of
    # `run`'s and `stability`'s start-up. Reference: scipy's own choice, and the gain
    # of a loop whose crossing is known (M0 = 0.5, b = c = 1: the eigenvalue 0.5 + K
    # reaches z = 1 at K = 0.5, and z = -1 only at K = -1.5 < 0)
    from scipy import linalg

    from armfit.loop import _lapack_ggev
    for dtype in (float, complex):
        a = np.eye(3, dtype=dtype)
        assert _lapack_ggev(a) is linalg.get_lapack_funcs(("ggev",), (a,))[0]
    got = fresh_json("import sys, json, numpy as np\n"
                     "from armfit.loop import crossing_gains\n"
                     "K, th = crossing_gains(np.array([[0.5]]), np.array([1.0]), "
                     "np.array([1.0]))\n"
                     "print(json.dumps([sorted(K.tolist()), 'scipy.linalg' in sys.modules]))")
    np.testing.assert_allclose(np.unique(np.round(got[0], 12)), [0.5], rtol=1e-12)
    assert got[1] is False


def test_the_diagnose_and_compare_commands_import_rich_only_to_print():
    # their module loads without rich (about a tenth of a second): the tables are drawn
    # once the work is done, and the work's start-up does not wait for them
    got = fresh_json("import sys, json\nimport armfit.cli.diagnose\n"
                     "print(json.dumps(sorted(m for m in sys.modules if m.startswith('rich'))))")
    assert got == []


def test_diagnose_imports_no_optimiser_until_it_refits_a_trial_alone():
    # `armfit diagnose --help` and the diagnosis's modules (its joint fits are
    # armfit.blocklsq's) need neither scipy.optimize, scipy.special nor scipy.ndimage:
    # importing them took about 1 s of the command's start-up. A trial refitted alone
    # takes its solver from armfit._trf, which needs no scipy either.
    heavy = {"scipy.optimize", "scipy.ndimage", "scipy.special", "matplotlib"}
    loaded = modules_after(["diagnose", "--help"])
    assert "armfit.cli.diagnose" in loaded and not loaded & heavy
    loaded = set(fresh_json("import sys, json\nimport armfit.diagnosis.search, "
                            "armfit.fitting, armfit.uncertainty\n"
                            "print(json.dumps(sorted(sys.modules)))"))
    assert "armfit.diagnosis.joint" in loaded and not loaded & heavy


def test_uncertainty_fits_on_worker_processes_import_no_optimiser_here(spectra, nominal,
                                                                      tmp_path):
    # the axes' Wu fits run in the worker processes, each holding BLAS on one thread
    # itself: the command's process has no optimiser to run, and importing
    # scipy.optimize there (about 0.2-0.4 s) delayed the fits. The weights are those of
    # the fits in one process, to the byte.
    out = {jobs: tmp_path / f"wu-{jobs}.csv" for jobs in (1, 2)}
    args = ["-q", "fit-uncertainty", str(spectra), "--nominal", str(nominal)]
    loaded = modules_after([*args, "-o", str(out[2]), "--jobs", "2"])
    assert "armfit.uncertainty" in loaded and "scipy.optimize" not in loaded
    modules_after([*args, "-o", str(out[1]), "--jobs", "1"])
    axes = {line.split(",")[0] for line in out[2].read_text().splitlines()[1:]}
    assert len(axes) > 1                                      # the pool ran the fits
    for a, b in zip(sorted(tmp_path.glob("wu-1*.csv")), sorted(tmp_path.glob("wu-2*.csv")),
                    strict=True):
        assert a.read_bytes() == b.read_bytes()


@pytest.mark.parametrize("pool", ["estimate", "diagnosis", "fit", "uncertainty", "run"])
def test_the_workers_modules_load_no_pandas(pool):
    # the fork server of a pool imports these before its workers start
    # (armfit.workers.POOL_PRELOAD; run's one pool: PRELOAD, every engine module), while
    # the command's own process imports pandas to read its inputs: pandas (about a third
    # of a second of CPU) would delay the workers, and in run take CPU from the estimate
    from armfit.workers import POOL_PRELOAD, PRELOAD
    names = [m for m in (PRELOAD if pool == "run" else POOL_PRELOAD[pool])
             if m.startswith("armfit")]
    loaded = set(fresh_json(f"import sys, json\nimport {', '.join(names)}\n"
                            "print(json.dumps(sorted(sys.modules)))"))
    assert set(names) <= loaded and "pandas" not in loaded


@pytest.mark.parametrize("pool", ["diagnosis", "fit"])
def test_the_fitting_workers_load_no_reader_of_files(pool):
    # the fits' and the diagnosis's tasks take arrays: their workers import neither the
    # spectra file's reader (armfit.spectra) nor pyarrow, which the fork server would
    # otherwise import (about 70 ms of CPU) while the command starts
    from armfit.workers import POOL_PRELOAD
    names = list(POOL_PRELOAD[pool])
    loaded = set(fresh_json(f"import sys, json\nimport {', '.join(names)}\n"
                            "print(json.dumps(sorted(sys.modules)))"))
    assert set(names) <= loaded
    assert not loaded & {"armfit.spectra", "armfit.io.trials", "armfit.io.artifacts",
                         "pyarrow"}


def test_the_global_search_reads_the_papers_rows_without_pandas():
    # every fit's global search starts from the arm parameters of the paper's Tables I
    # and II (armfit.fitting._paper_rows): read in a worker with the csv module, they
    # are the numbers pandas reads from the same files, to the bit
    got = fresh_json("import sys, json\nfrom armfit.fitting import _paper_rows\n"
                     "print(json.dumps({'rows': _paper_rows().tolist(), "
                     "'pandas': 'pandas' in sys.modules}))")
    assert not got["pandas"]
    from armfit.data import paper_table
    cols = ["Ma_kg", "k1_N_per_m", "k2_N_per_m", "b1_Ns_per_m", "b2_Ns_per_m"]
    expected = np.vstack([paper_table(t)[cols].to_numpy(float) for t in ("grip", "nominal")])
    assert np.array(got["rows"]).tobytes() == expected.tobytes()


@pytest.mark.parametrize("name", ["grip", "nominal", "uncertainty", "literature"])
def test_paper_values_are_pandas_numbers_of_the_papers_tables(name):
    # every numeric column (empty cells of Table IV included, NaN) against pandas's reader
    from armfit.data import paper_table, paper_values
    df = paper_table(name)
    cols = [c for c in df.columns if df[c].dtype.kind in "fi"]
    got = paper_values(name, cols)
    assert got.shape == (len(df), len(cols))
    assert got.tobytes() == df[cols].to_numpy(float).tobytes()


def _script_number(script: str, mode: str) -> float:
    """The number ``script`` prints, run with ``mode`` in a fresh interpreter."""
    res = subprocess.run([sys.executable, "-c", script, mode], check=True,
                         capture_output=True, text=True)
    return float(res.stdout.strip())


_PAGE_FAULTS = """
import resource, sys
import numpy as np
import pandas as pd
if sys.argv[1] == "tuned":
    from armfit.workers import tune_allocator
    assert tune_allocator()
before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
for i in range(40):                           # a trial's Welch buffers, about 5 MB each
    a = np.ones((4, 5, 32768 + 100 * i))
    b = np.fft.rfft(a, axis=-1)
    del a, b
print(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
"""


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's mallopt")
def test_tuned_allocator_reuses_the_pages_of_freed_arrays():
    # minor page faults of the same allocations in two fresh processes: with the default
    # settings each 5 MB array is mapped afresh (about 1,250 faults per array of 4 kB
    # pages); tuned, the pages are reused after the first arrays
    plain, tuned = _script_number(_PAGE_FAULTS, "plain"), _script_number(_PAGE_FAULTS, "tuned")
    assert plain > 20 * 1250 and tuned < plain / 5, (plain, tuned)


#: The resident anonymous memory of the script's process, MB (the scripts below).
_ANON_MB = """
def anon_mb():
    with open("/proc/self/status") as fh:
        return next(int(l.split()[1]) for l in fh if l.startswith("RssAnon")) / 1024
"""


_POOL_TRANSFERS = _ANON_MB + """
import ctypes, sys
from concurrent.futures import ProcessPoolExecutor
import numpy as np
from armfit.memory import release_memory
from armfit.workers import MMAP_THRESHOLD_BYTES, TRIM_THRESHOLD_BYTES, tune_allocator

if sys.argv[1] == "tuned":
    assert tune_allocator()
else:    # the same thresholds, each thread in an arena of its own (glibc's default)
    mallopt = ctypes.CDLL(None).mallopt
    assert mallopt(-3, MMAP_THRESHOLD_BYTES) and mallopt(-1, TRIM_THRESHOLD_BYTES)
if __name__ == "__main__":
    before = anon_mb()
    with ProcessPoolExecutor(2) as ex:     # 30 tasks of 4 MB out and 4 MB back
        sums = [float(r.sum()) for r in ex.map(np.negative, [np.ones(500_000)] * 30)]
    assert sums == [-500_000.0] * 30
    release_memory()
    print(anon_mb() - before)
"""


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's mallopt")
def test_tuned_allocator_gives_back_what_a_pools_threads_freed():
    # the memory a process holds, after a pool's 30 round trips of 4 MB and
    # release_memory, in two fresh processes: the threads that pickle the tasks and
    # unpickle the results kept the freed memory in arenas of their own (about 30 MB);
    # in the one arena tune_allocator leaves, release_memory gives it back
    threads = _script_number(_POOL_TRANSFERS, "threads")
    tuned = _script_number(_POOL_TRANSFERS, "tuned")
    assert threads > 10 and tuned < 5, (threads, tuned)


_RECEIVED_HEAP = """
import ctypes, os, sys
from multiprocessing.connection import Connection
from armfit._pool import whole_reads
from armfit.workers import tune_allocator

class MallInfo2(ctypes.Structure):
    _fields_ = [(n, ctypes.c_size_t) for n in ("arena ordblks smblks hblks hblkhd usmblks "
                                               "fsmblks uordblks fordblks keepcost").split()]
mallinfo2 = ctypes.CDLL(None).mallinfo2
mallinfo2.restype = MallInfo2
assert tune_allocator()
size = 8 << 20
rfd, wfd = os.pipe()
pid = os.fork()
if pid == 0:       # the sender: three pickled messages of 8 MiB
    os.close(rfd)
    out = Connection(wfd, readable=False)
    for _ in range(3):
        out.send(bytes(size))
    os._exit(0)
os.close(wfd)
reader = Connection(rfd, writable=False)
if sys.argv[1] == "whole":
    whole_reads(reader)
before, grown = mallinfo2().arena, 0
for _ in range(3):
    got = reader.recv()
    assert len(got) == size
    del got
    grown = max(grown, mallinfo2().arena - before)
os.waitpid(pid, 0)
print(grown / size)
"""


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's mallinfo2")
def test_a_message_read_whole_grows_the_heap_by_no_more_than_it_and_its_object():
    # the C library's heap of a process that keeps what it frees (tune_allocator) after
    # receiving three pickled 8 MiB messages, in sizes of the message: read whole, the
    # message's buffer and the bytes unpickled from it (2, measured 1.996); read as
    # multiprocessing reads it, in a buffer grown and moved a pipe's worth at a time,
    # 2.8 (measured 2.82 every time)
    whole = _script_number(_RECEIVED_HEAP, "whole")
    plain = _script_number(_RECEIVED_HEAP, "plain")
    assert whole <= 2.05 and plain > whole + 0.5, (whole, plain)


_INGEST_HELD = _ANON_MB + """
import os, sys
os.environ["ARROW_DEFAULT_MEMORY_POOL"] = sys.argv[1]    # before pyarrow loads
from armfit.io import trials as io_trials
from armfit.memory import release_memory
from armfit.workers import tune_allocator

assert tune_allocator()
sources, _ = io_trials.discover([sys.argv[2]])
def ingest(srcs, name):   # as run's ingest: each trial read, trials.parquet written
    io_trials.write_dataset((io_trials.read_trial(s) for s in srcs),
                            os.path.join(sys.argv[3], sys.argv[1] + "-" + name))
ingest(sources[:2], "warm.parquet")     # Arrow's and the writer's first-use costs
release_memory()
before = anon_mb()
ingest(sources, "trials.parquet")
release_memory()
print(anon_mb() - before)
"""


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's malloc_trim")
def test_the_c_librarys_arrow_pool_gives_back_what_an_ingest_freed(tmp_path):
    # the memory a fresh process holds after reading the 18 trials of 50-100 s at 1 kHz of
    # a simulated study of 2 subjects (all axes and grips) and writing them to a dataset
    # (both in Arrow's buffers, the writing in a thread of its own), and release_memory:
    # from pyarrow's mimalloc 6-12 MB stayed (6 runs);
    # from the C library's pool (armfit.workers.ARROW_SYSTEM_POOL, as the command line
    # and its workers use it) all but 0.2-0.25 MB went back
    from click.testing import CliRunner

    from armfit.cli.main import cli
    trials = tmp_path / "trials"
    res = CliRunner().invoke(cli, ["-q", "simulate", "-o", str(trials), "--subjects", "2",
                                   "--seed", "1"])
    assert res.exit_code == 0, res.output
    assert len(list(trials.iterdir())) == 18

    def held_mb(pool: str) -> float:
        res = subprocess.run([sys.executable, "-c", _INGEST_HELD, pool, str(trials),
                              str(tmp_path)], check=True, capture_output=True, text=True)
        return float(res.stdout.strip())

    from armfit.workers import ARROW_SYSTEM_POOL
    assert ARROW_SYSTEM_POOL == {"ARROW_DEFAULT_MEMORY_POOL": "system"}
    mimalloc, system = held_mb("mimalloc"), held_mb("system")
    assert mimalloc > 3 and system < 1, (mimalloc, system)


def test_arrows_freed_buffers_are_returned_once_enough_columns_were_read(
        tmp_path, write_trial, make_columns, monkeypatch):
    # Arrow's pool is emptied once RELEASE_ARROW_BYTES of float64 values were read since
    # it last was, not after every trial: 13 raw trials of 7 columns (time, three forces,
    # three positions) x 100,000 samples are 5.6 MB each, so the count since the last
    # release first reaches 32 MiB (33,554,432 B) at the 6th trial (33.6 MB) and again
    # at the 12th: two releases. Each trial read comes back whole all the same.
    from armfit.io import trials as io_trials
    released = []

    class Pool:
        def release_unused(self):
            released.append(len(read) + 1)   # the trial being read

    monkeypatch.setattr(pa, "default_memory_pool", Pool)
    monkeypatch.setattr(io_trials, "_read_since_release", 0)
    cols = make_columns("x", fs=1000.0, duration_s=100.0, seed=4, grip=False)
    for a in "xyz":   # the random walk kept well inside the workspace
        cols[f"pos_{a}_m"] = cols[f"pos_{a}_m"] / 10
    assert len(cols) == 7 and cols["time_s"].size == 100_000
    read = []
    for k in range(13):
        path = write_trial(tmp_path / f"sub-{k:02d}_axis-x_grip-1N.parquet", cols)
        (src,), _ = io_trials.discover([path])
        read.append(io_trials.read_trial(src))
        np.testing.assert_array_equal(read[-1].f, cols["force_x_N"])
    assert io_trials.RELEASE_ARROW_BYTES == 32 << 20
    assert released == [6, 12]


# ---------------------------------------------------------------------------
# The serial estimate reads the next trial while it estimates this one
# ---------------------------------------------------------------------------


@pytest.fixture(scope="module")
def csv_study(tmp_path_factory):
    """4 trials (2 subjects, axis x, grips 1 and 2 N, 26 s; armfit.simulate, seed 5), as
    CSV files: a cell of one can be spoilt."""
    import armfit
    root = tmp_path_factory.mktemp("ahead") / "study"
    armfit.simulate(subjects=2, axes=("x",), grips_N=(1.0, 2.0), duration_s=(26.0, 26.0),
                    seed=5).write(root, fmt="csv")
    return root


def test_serial_estimate_reads_ahead_and_gives_each_trials_own_estimate(csv_study,
                                                                     monkeypatch):
    # the reference: each trial read and estimated by the task the worker processes run
    # (_estimate_source), one after the other
    import threading

    from armfit import spectra as sp
    from armfit.io import trials as io_trials
    config = sp.EstimateConfig()
    sources = list(io_trials.open_trials([csv_study]).sources)
    expected = [sp._estimate_source(s, config)[1] for s in sources]
    readers = []
    real = sp.read_trial

    def spy(*args, **kwargs):
        readers.append(threading.current_thread().name)
        return real(*args, **kwargs)

    monkeypatch.setattr(sp, "read_trial", spy)
    got = sp.estimate_study([csv_study], config, jobs=1)
    assert len(readers) == len(sources) == 4
    assert all(n.startswith("armfit-read") for n in readers)
    for a, b in zip(got.trials, expected, strict=True):
        assert a.source == b.source
        for ra, rb in zip(a.responses, b.responses, strict=True):
            assert ra.kind == rb.kind and ra.flags == rb.flags
            assert np.array_equal(ra.h, rb.h, equal_nan=True)
            assert np.array_equal(ra.se_db, rb.se_db, equal_nan=True)


def test_the_reading_half_makes_the_derived_window(csv_study, monkeypatch):
    # the Hamming window of the derived spectra (its length follows the record's) is
    # made while the trial is read, in the reading thread of a serial estimate; the
    # estimate is the one of a cold cache (the reference: _estimate_source per trial)
    import threading

    from armfit import spectra as sp
    from armfit.io import trials as io_trials
    config = sp.EstimateConfig()
    sources = list(io_trials.open_trials([csv_study]).sources)
    _cached_window.cache_clear()
    expected = [sp._estimate_source(s, config)[1] for s in sources]
    _cached_window.cache_clear()
    made = []
    real = sp._cosine_window

    def spy(coefficients, n, periodic):
        made.append((threading.current_thread().name, n, periodic))
        return real(coefficients, n, periodic)

    monkeypatch.setattr(sp, "_cosine_window", spy)
    got = sp.estimate_study([csv_study], config, jobs=1)
    n_samples = 26 * 1000                   # 26 s at 1 kHz, first and last dropped
    nperseg = sp.tfestimate_segment(n_samples - 2, config.derived_segments)[0]
    derived = [m for m in made if m[1:] == (nperseg, False)]
    assert len(derived) == 1 and derived[0][0].startswith("armfit-read")
    for a, b in zip(got.trials, expected, strict=True):
        for ra, rb in zip(a.responses, b.responses, strict=True):
            assert np.array_equal(ra.h, rb.h, equal_nan=True)


def test_serial_estimate_stops_at_a_bad_trial_or_skips_it(csv_study, tmp_path):
    # the third trial (in file order) has a word in a force cell: without skip_bad its
    # error is raised, naming the file, column and row, and no reading thread is left;
    # with skip_bad it is listed and the other three are estimated
    import shutil
    import threading

    from armfit.errors import BadInputError
    from armfit.spectra import EstimateConfig, estimate_study
    study = tmp_path / "study"
    shutil.copytree(csv_study, study)
    bad = sorted(study.glob("*.csv"))[2]
    lines = bad.read_text().splitlines()
    header = lines[0].split(",")
    col = next(i for i, name in enumerate(header) if name.startswith("force_x"))
    cells = lines[11].split(",")
    cells[col] = "oops"
    lines[11] = ",".join(cells)
    bad.write_text("\n".join(lines) + "\n")
    why = f"column '{header[col]}', row 11: non-numeric value 'oops'; expected a number"
    with pytest.raises(BadInputError) as err:
        estimate_study([study], EstimateConfig(), jobs=1)
    assert str(err.value) == f"{bad}, {why}"
    assert not [t for t in threading.enumerate() if t.name.startswith("armfit-read")]
    got = estimate_study([study], EstimateConfig(), jobs=1, skip_bad=True)
    assert got.skipped == ((str(bad), why),)
    assert [t.source for t in got.trials] == [str(p) for p in sorted(study.glob("*.csv"))
                                              if p != bad]


def _spoilt_study(csv_study, tmp_path):
    """csv_study with its third trial spoilt (a word in a force cell) and its first also
    as a gzipped copy (a duplicate trial): (folder, the spoilt file)."""
    import gzip
    import shutil
    study = tmp_path / "study"
    shutil.copytree(csv_study, study)
    files = sorted(study.glob("*.csv"))
    lines = files[2].read_text().splitlines()
    col = next(i for i, n in enumerate(lines[0].split(",")) if n.startswith("force_x"))
    cells = lines[11].split(",")
    cells[col] = "oops"
    lines[11] = ",".join(cells)
    files[2].write_text("\n".join(lines) + "\n")
    with gzip.open(study / (files[0].name + ".gz"), "wb") as fh:
        fh.write(files[0].read_bytes())
    return study, files[2]


class _SlowPool:
    """A pool of two threads whose tasks first wait 0.2 s, and that records how many of
    its tasks were unfinished at each submission."""

    def __init__(self):
        from concurrent.futures import ThreadPoolExecutor
        self.pool = ThreadPoolExecutor(2)
        self.futures: list = []
        self.in_flight: list[int] = []

    def submit(self, fn, /, *args, **kwargs):
        import time
        self.in_flight.append(sum(not f.done() for f in self.futures) + 1)
        fut = self.pool.submit(lambda: (time.sleep(0.2), fn(*args, **kwargs))[1])
        self.futures.append(fut)
        return fut


@pytest.mark.parametrize("where", ["here", "processes", "threads"])
def test_estimate_alongside_ingest_is_the_estimate_of_the_same_files(csv_study, tmp_path,
                                                                      where):
    # the reference: estimate_study of the same inputs, each trial read by the estimate
    # itself. ingest reads each trial once and hands it to the estimate; a spoilt trial
    # and a duplicate are skipped with the same reasons in the same places, and the
    # spectra file written is the same, byte for byte. At most 2 x jobs trials are in
    # flight on a pool (the reader waits), whose samples the reader holds until sent:
    # on the slow pool, with jobs 1, the third trial waits for the first
    from armfit.spectra import EstimateConfig, estimate_study
    from armfit.workers import process_pool
    study, bad = _spoilt_study(csv_study, tmp_path)
    config = EstimateConfig()
    ref = estimate_study([study], config, jobs=1, skip_bad=True)
    assert {f for f, _ in ref.skipped} == {str(bad), str(study / (sorted(
        study.glob("*.csv"))[0].name + ".gz"))}
    pool = {"here": None, "processes": process_pool(2), "threads": _SlowPool()}[where]
    try:
        got = _alongside_ingest(study, tmp_path, config, skip_bad=True, executor=pool,
                                jobs=1 if where == "threads" else 2)
    finally:
        if where == "processes":
            pool.shutdown()
    assert got.skipped == ref.skipped and got.ignored == ref.ignored
    assert [t.source for t in got.trials] == [t.source for t in ref.trials]
    assert got.fs == ref.fs and got.meta == ref.meta
    got.write(tmp_path / "got.parquet")
    ref.write(tmp_path / "ref.parquet")
    assert (tmp_path / "got.parquet").read_bytes() == (tmp_path / "ref.parquet").read_bytes()
    if where == "threads":
        assert len(ref.trials) == 3 and pool.in_flight == [1, 2, 2]


@pytest.mark.skipif(not Path(_shared.SHM_FOLDER).is_dir(), reason="Linux's shared memory")
@pytest.mark.parametrize("case", ["shared", "spoilt", "full"])
def test_trials_reach_the_pools_workers_through_shared_blocks_removed_after(
        tmp_path, make_columns, write_trial, monkeypatch, case):
    # trials with a reference column (three arrays a trial) estimated alongside ingest on
    # a process pool: each trial's samples go through a shared-memory block (recorded
    # here) and the spectra file is, byte for byte, estimate_study's of the same files
    # read by itself (the reference). Every block is gone once the result is taken, and
    # also when a bad trial ends the ingest (spoilt, without skip_bad). With no room in
    # the shared memory (full: no block can be reserved) the trials go through the pipe,
    # with the same result
    import errno

    from armfit.spectra import EstimateConfig, estimate_study
    from armfit.workers import process_pool
    study = tmp_path / "study"
    study.mkdir()
    for i, grip in enumerate((1, 2, 3)):
        cols = make_columns("x", fs=200.0, duration_s=25.0, seed=i)
        cols["ref_x_N"] = cols["force_x_N"] + 0.25            # the commanded force, N
        if case == "spoilt" and i == 1:
            cols["force_x_N"][40] = np.nan                     # a gap: a bad trial
        write_trial(study / f"sub-01_axis-x_grip-{grip}N.parquet", cols)
    names: list[str] = []
    put = _shared.Blocks.put

    def recorded(self, arrays):
        got = put(self, arrays)
        if got is not None:
            names.append(got[0].name)
            assert len(got[0].layout) == 3                      # force, pos, reference
        return got

    def full(fd, offset, size):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(_shared.Blocks, "put", recorded)
    if case == "full":
        monkeypatch.setattr(os, "posix_fallocate", full)
    config = EstimateConfig(fmin=0.5)
    pool = process_pool(2)
    pool.start()    # its workers up: no trial is held or estimated here while they start
    try:
        if case == "spoilt":
            with pytest.raises(BadInputError):
                _alongside_ingest(study, tmp_path, config, skip_bad=False, executor=pool)
        else:
            got = _alongside_ingest(study, tmp_path, config, skip_bad=False, executor=pool)
    finally:
        pool.shutdown()
    assert bool(names) == (case != "full")
    assert not any((Path(_shared.SHM_FOLDER) / n.lstrip("/")).exists() for n in names)
    if case == "spoilt":
        return
    assert len(names) == (0 if case == "full" else 3)
    ref = estimate_study([study], config, jobs=1)
    got.write(tmp_path / "got.parquet")
    ref.write(tmp_path / "ref.parquet")
    assert (tmp_path / "got.parquet").read_bytes() == (tmp_path / "ref.parquet").read_bytes()


def _alongside_ingest(study, tmp_path, config, *, skip_bad, executor=None, jobs=2,
                      on_add=None):
    """ingest of ``study`` with each trial handed to an EstimateAlongside: its result.
    ``on_add(n)``: called after the n-th trial is handed over."""
    from armfit.io.trials import ingest
    from armfit.spectra import EstimateAlongside
    along = {}
    added = []

    def opened(stream):
        along["estimate"] = EstimateAlongside(stream, config, skip_bad=skip_bad, jobs=jobs,
                                              executor=executor)

    def add(source, trial):
        along["estimate"].add(source, trial)
        added.append(source)
        if on_add is not None:
            on_add(len(added))

    try:
        ingest([study], tmp_path / "trials.parquet", skip_bad=skip_bad, f_min_hz=config.fmin,
               force_limit_N=config.force_limit_N, on_open=opened, on_trial=add)
    except BaseException:
        if "estimate" in along:     # as armfit run's ingest stage does
            along["estimate"].close()
        raise
    return along["estimate"].result()


@pytest.mark.parametrize("read_ahead", ["none", "all"])
def test_the_reader_goes_on_while_the_pools_workers_start(csv_study, tmp_path, monkeypatch,
                                                          read_ahead):
    # the pool's workers start in a thread (armfit.workers.start_workers), held here until
    # the reader has handed over two of the three good trials. Meanwhile nothing goes to
    # the pool: the reader holds the trials, up to READ_AHEAD_BYTES of samples ("all":
    # room for every trial; "none": one byte), and beyond that the oldest is estimated
    # here, in this thread. Once the workers are up the rest go to the pool. Where a
    # trial is estimated does not change it: the spectra file is, byte for byte,
    # estimate_study's of the same files (the reference, each trial read by the
    # estimate itself), the spoilt trial and the duplicate skipped in their places
    import threading
    from concurrent.futures import ThreadPoolExecutor

    import armfit.spectra as spectra_mod
    from armfit.spectra import EstimateConfig, estimate_study
    study, _ = _spoilt_study(csv_study, tmp_path)
    config = EstimateConfig()
    ref = estimate_study([study], config, jobs=1, skip_bad=True)
    assert len(ref.trials) == 3
    up = threading.Event()
    starter = threading.Thread(target=up.wait, daemon=True)

    def start_workers(executor):
        starter.start()
        return starter

    def on_add(n):
        if n == 2:          # the workers are up once the reader has handed over two
            up.set()
            starter.join()

    where: list[str] = []
    estimate_given = spectra_mod._estimate_given

    def recorded(task, cfg):
        where.append("here" if threading.current_thread() is threading.main_thread()
                     else "pool")
        return estimate_given(task, cfg)

    pool = ThreadPoolExecutor(2)
    submitted_up: list[bool] = []
    submit = pool.submit

    def checked(fn, *args, **kwargs):
        submitted_up.append(up.is_set())
        return submit(fn, *args, **kwargs)

    monkeypatch.setattr(pool, "submit", checked)
    monkeypatch.setattr(spectra_mod, "start_workers", start_workers)
    monkeypatch.setattr(spectra_mod, "_estimate_given", recorded)
    monkeypatch.setattr(spectra_mod, "READ_AHEAD_BYTES", 1 if read_ahead == "none" else 1 << 30)
    try:
        got = _alongside_ingest(study, tmp_path, config, skip_bad=True, executor=pool,
                                on_add=on_add)
    finally:
        pool.shutdown()
    assert all(submitted_up)
    assert sorted(where) == (["here", "here", "pool"] if read_ahead == "none"
                             else ["pool"] * 3)
    assert got.skipped == ref.skipped
    got.write(tmp_path / "got.parquet")
    ref.write(tmp_path / "ref.parquet")
    assert (tmp_path / "got.parquet").read_bytes() == (tmp_path / "ref.parquet").read_bytes()


@pytest.mark.parametrize("where", ["here", "threads"])
@pytest.mark.parametrize("skip_bad", [False, True])
def test_estimate_alongside_refuses_another_rate_as_the_estimate_does(csv_study, tmp_path,
                                                                        skip_bad, where):
    # the second trial sampled at 1000.51 Hz, the others at 1000.5 Hz: within ingest's
    # rate tolerance (1e-4), outside the estimate's (1e-6). The reference is
    # estimate_study of the same files: its error, raised once ingest has read every
    # trial (trials.parquet is then complete), or the trial skipped with its reason
    import shutil
    from concurrent.futures import ThreadPoolExecutor

    from armfit.errors import BadInputError
    from armfit.spectra import EstimateConfig, estimate_study
    pool = ThreadPoolExecutor(2) if where == "threads" else None
    study = tmp_path / "study"
    shutil.copytree(csv_study, study)
    files = sorted(study.glob("*.csv"))
    shifted = files[1]
    for path in files:
        fs = 1000.51 if path == shifted else 1000.5
        lines = path.read_text().splitlines()
        lines[1:] = [f"{i / fs:.9f}," + line.split(",", 1)[1]
                     for i, line in enumerate(lines[1:])]
        path.write_text("\n".join(lines) + "\n")
    config = EstimateConfig()
    if not skip_bad:
        with pytest.raises(BadInputError) as ref:
            estimate_study([study], config, jobs=1)
        assert "sampling rate 1000.51 Hz differs from 1000.5 Hz" in str(ref.value)
        with pytest.raises(BadInputError) as got:
            _alongside_ingest(study, tmp_path, config, skip_bad=False, executor=pool)
        assert str(got.value) == str(ref.value)
        assert len(dataset_sources(tmp_path / "trials.parquet")) == 4
        return
    ref = estimate_study([study], config, jobs=1, skip_bad=True)
    got = _alongside_ingest(study, tmp_path, config, skip_bad=True, executor=pool)
    assert got.skipped == ref.skipped and [s for s, _ in ref.skipped] == [str(shifted)]
    got.write(tmp_path / "got.parquet")
    ref.write(tmp_path / "ref.parquet")
    assert (tmp_path / "got.parquet").read_bytes() == (tmp_path / "ref.parquet").read_bytes()
