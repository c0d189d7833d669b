"""Library tests of armfit.io.trials: names, manifest, reading, validation, dataset."""

from __future__ import annotations

import numpy as np
import pytest

from armfit.errors import BadInputError, NoInputError, OutputError, UsageError
from armfit.io.trials import (
    check_grip,
    dataset_metadata,
    dataset_sources,
    discover,
    is_dataset,
    open_trials,
    parse_name,
    read_manifest,
    read_trial,
    resample_trial,
    sampling_rate,
    write_dataset,
)

# ---------------------------------------------------------------------------
# File names (expected identities follow the naming rule of docs/formats.md, "Raw trial files")
# ---------------------------------------------------------------------------


@pytest.mark.parametrize("name, expected", [
    ("sub-07_axis-y_grip-2N.parquet", ("07", "y", 2.0, None)),
    ("sub-A1_axis-z_grip-1.5N_run-3.csv.gz", ("A1", "z", 1.5, 3)),
    ("sub-3_axis-x_grip-1N.csv", ("3", "x", 1.0, None)),
    ("notes.txt", None),
    ("trial_01.csv", None),
    ("sub-07_axis-y_grip-2N.txt", None),
])
def test_parse_name(name, expected):
    assert parse_name(name) == expected


@pytest.mark.parametrize("name, match", [
    ("sub-07_axis-w_grip-2N.csv", r"axis 'w' in the file name is not x, y or z"),
    ("sub-0-7_axis-x_grip-2N.csv", r"subject label '0-7'"),
    ("sub-07_axis-x_grip-twoN.csv", r"grip 'twoN'"),
    ("sub-07_axis-x_grip-2N_run-a.csv", r"run 'a'"),
])
def test_parse_name_rejects_bad_parts(name, match):
    with pytest.raises(BadInputError, match=match):
        parse_name(name)


def test_discover_sorted_recursive_and_ignored(tmp_path, write_trial):
    # Folders are walked recursively in sorted order; non-trial files are ignored.
    write_trial(tmp_path / "b" / "sub-02_axis-x_grip-1N.csv")
    write_trial(tmp_path / "a" / "sub-01_axis-y_grip-1N.parquet")
    write_trial(tmp_path / "a" / "sub-01_axis-x_grip-1N.csv")
    (tmp_path / "a" / "notes.txt").write_text("hello")
    sources, ignored = discover([tmp_path])
    assert [s.path for s in sources] == [
        str(tmp_path / "a" / "sub-01_axis-x_grip-1N.csv"),
        str(tmp_path / "a" / "sub-01_axis-y_grip-1N.parquet"),
        str(tmp_path / "b" / "sub-02_axis-x_grip-1N.csv")]
    assert ignored == [tmp_path / "a" / "notes.txt"]


def test_manifest_wins_over_name(tmp_path, write_trial):
    # The manifest names identity for a file of any name, and overrides a BIDS name.
    write_trial(tmp_path / "raw" / "odd name.csv", axis="z")
    write_trial(tmp_path / "raw" / "sub-01_axis-x_grip-1N.csv", axis="y")
    (tmp_path / "m.csv").write_text(
        "file,subject,axis,grip_N,run\n"
        "raw/odd name.csv,S9,z,3,2\n"
        "raw/sub-01_axis-x_grip-1N.csv,01,y,1.5,\n")
    entries = read_manifest(tmp_path / "m.csv")
    assert entries[(tmp_path / "raw" / "odd name.csv").resolve()] == ("S9", "z", 3.0, 2)
    sources, ignored = discover([tmp_path / "raw"], manifest=tmp_path / "m.csv")
    assert [(s.subject, s.axis, s.grip_N, s.run) for s in sources] == [
        ("S9", "z", 3.0, 2), ("01", "y", 1.5, None)]
    assert ignored == []
    # With no inputs the manifest lists the trials itself.
    sources, _ = discover([], manifest=tmp_path / "m.csv")
    assert len(sources) == 2


@pytest.mark.parametrize("text, match", [
    ("file,subject,grip_N\nx.csv,1,2\n", r"m\.csv, column 'axis': missing required"),
    ("file,subject,axis,grip_N\nx.csv,1,x,2\ny.csv,1,q,2\n",
     r"m\.csv, column 'axis', row 2: axis 'q' is not x, y or z"),
    ("file,subject,axis,grip_N\nx.csv,1,x,heavy\n", r"column 'grip_N', row 1: grip 'heavy'"),
])
def test_manifest_errors_name_column_and_row(tmp_path, text, match):
    (tmp_path / "m.csv").write_text(text)
    with pytest.raises(BadInputError, match=match):
        read_manifest(tmp_path / "m.csv")


def test_missing_input_is_no_input(tmp_path):
    with pytest.raises(NoInputError, match="no such file or folder"):
        discover([tmp_path / "absent"])
    with pytest.raises(NoInputError, match="no trial files found"):
        open_trials([tmp_path])


# ---------------------------------------------------------------------------
# Reading: round trips (expected values are what the test wrote)
# ---------------------------------------------------------------------------


@pytest.mark.parametrize("ext", ["csv", "csv.gz", "parquet"])
def test_round_trip_exact(tmp_path, write_trial, make_columns, ext):
    cols = make_columns("y", fs=100.0, duration_s=25.0, seed=3, t0_s=12.5)
    path = write_trial(tmp_path / f"sub-01_axis-y_grip-2N_run-1.{ext}", cols)
    (src,), _ = discover([path])
    trial = read_trial(src)
    m = trial.meta
    assert (m.subject, m.axis, m.grip_N, m.run) == ("01", "y", 2.0, 1)
    # fs = (n-1)/(t_last - t_first) of t = t0 + k/100, rounded to whole Hz: 100 Hz.
    assert m.fs == 100.0 and m.n_samples == 2500 and m.t0_s == 12.5
    for j, a in enumerate("xyz"):
        # pyarrow writes shortest round-trip decimals, so CSV values come back bit-exact.
        np.testing.assert_array_equal(trial.force[:, j], cols[f"force_{a}_N"])
        np.testing.assert_array_equal(trial.pos[:, j], cols[f"pos_{a}_m"])
    np.testing.assert_array_equal(trial.grip, cols["grip_N"])
    np.testing.assert_array_equal(trial.f, cols["force_y_N"])


def test_mm_converted_exactly_and_absent_axes_nan(tmp_path, write_trial, make_columns):
    cols = make_columns("x", pos_unit="mm", all_axes=False, grip=False, seed=4)
    cols["comment"] = ["free text"] * cols["time_s"].size  # extra columns are ignored
    path = write_trial(tmp_path / "sub-01_axis-x_grip-1N.csv", cols)
    trial = read_trial(discover([path])[0][0])
    # mm → m is a division by 1000 (the same IEEE operation, so exact equality holds).
    np.testing.assert_array_equal(trial.x, cols["pos_x_mm"] / 1000.0)
    assert np.isnan(trial.force[:, 1:]).all() and np.isnan(trial.pos[:, 1:]).all()
    assert trial.grip is None


def test_sampling_rate_rules():
    t = np.arange(1000) / 250.0
    assert sampling_rate(t) == 250.0  # analytic: uniform 4 ms spacing
    jitter = t.copy()
    jitter[100] += 0.004 * 0.004  # 0.4 % of a period moves two intervals by 0.4 %: tolerated
    assert sampling_rate(jitter) == 250.0
    gap = t.copy()
    gap[100:] += 0.004 * 0.5  # half a period missing before row 101
    with pytest.raises(BadInputError, match=r"column 'time_s', row 101: non-uniform time"):
        sampling_rate(gap, file="f.csv")
    back = t.copy()
    back[[10, 11]] = back[[11, 10]]  # row 12 (1-based) now earlier than row 11
    with pytest.raises(BadInputError, match=r"row 12: non-monotonic time"):
        sampling_rate(back, file="f.csv")


@pytest.mark.parametrize("shift, row", [
    (0.0049, None),   # intervals 0.49 % long and short: spread 0.98 %, each within 1 %
    (0.008, None),    # 0.8 % long and short: spread 1.6 %, each still within 1 %
    (0.012, 101),     # 1.2 % long: beyond 1 % of the median interval, at row 101
])
def test_uniform_time_is_judged_against_the_median_interval(shift, row):
    # the rule: every interval within 1 % of the median interval (a sample moved by a
    # fraction s of a period lengthens the interval before it and shortens the one
    # after by s); judged the same whether the intervals spread over less than 1 % of
    # the shortest or more
    t = np.arange(1000) / 250.0
    t[100] += shift * 0.004
    if row is None:
        assert sampling_rate(t) == 250.0
    else:
        with pytest.raises(BadInputError, match=rf"row {row}: non-uniform time: interval "
                                                r"0\.004048 s vs period 0\.004 s"):
            sampling_rate(t, file="f.csv")


@pytest.mark.parametrize("value, row", [
    (None, None),          # NaN samples (missing) among ordinary ones: kept
    (np.inf, 7),
    (-np.inf, 7),
    (-2e100, 7),           # beyond any physical force (MAX_ABS_VALUE)
])
def test_grip_values_refused_only_when_infinite_or_absurd(value, row):
    g = np.full(20, 2.0)
    g[[2, 11]] = np.nan
    if value is not None:
        g[6] = value
    if row is None:
        np.testing.assert_array_equal(check_grip(g, "f.csv"), g)
    else:
        with pytest.raises(BadInputError, match=rf"column 'grip_N', row {row}: grip value"):
            check_grip(g, "f.csv")
    np.testing.assert_array_equal(check_grip(np.full(5, np.nan), "f.csv"),
                                  np.full(5, np.nan))      # no grip recorded at all
    assert check_grip(np.empty(0), "f.csv").size == 0


def test_force_limit_warns_not_raises(tmp_path, write_trial, make_columns):
    cols = make_columns("z", seed=5, grip_N=1.0)
    cols["force_z_N"][41] = 9.0  # beyond the 8.5 N default limit at 1-based row 42
    path = write_trial(tmp_path / "sub-01_axis-z_grip-1N.parquet", cols)
    warnings = []
    read_trial(discover([path])[0][0], warn=warnings.append)
    assert len(warnings) == 1
    assert "column 'force_z_N', row 42: |force| reaches the device limit 8.5 N" in warnings[0]
    warnings.clear()
    read_trial(discover([path])[0][0], force_limit_N=10.0, warn=warnings.append)
    assert warnings == []


# ---------------------------------------------------------------------------
# Cross-trial checks
# ---------------------------------------------------------------------------


def test_duplicates_named_and_skippable(tmp_path, write_trial):
    a = write_trial(tmp_path / "sub-01_axis-y_grip-2N.csv")
    b = write_trial(tmp_path / "sub-01_axis-y_grip-2N.parquet")
    with pytest.raises(BadInputError, match=rf"{b}: duplicate trial .* also in {a}"):
        open_trials([tmp_path])
    stream = open_trials([tmp_path], skip_bad=True)
    assert [t.meta.source for t in stream] == [str(a)]
    assert [s.file for s in stream.skipped] == [str(b)]


def test_rate_mismatch_and_resample_to_most_common(tmp_path, write_trial):
    # Trials at 200, 100, 100 Hz (in sorted order): the most common rate is 100 Hz.
    write_trial(tmp_path / "sub-01_axis-y_grip-1N.csv", axis="y", fs=200.0)
    write_trial(tmp_path / "sub-02_axis-y_grip-1N.csv", axis="y", fs=100.0)
    write_trial(tmp_path / "sub-03_axis-y_grip-1N.csv", axis="y", fs=100.0)
    with pytest.raises(BadInputError, match=r"sub-02.*column 'time_s': sampling rate 100 Hz "
                       r"differs from 200 Hz of .*sub-01.*pass resample"):
        list(open_trials([tmp_path]))
    notes = []
    trials = list(open_trials([tmp_path], resample=True, warn=notes.append))
    assert [t.meta.fs for t in trials] == [100.0, 100.0, 100.0]
    assert trials[0].meta.n_samples == 2500  # 25 s at 100 Hz
    assert any("resampled from 200 Hz to 100 Hz" in n for n in notes)


def test_resample_matches_analytic_sine():
    # A 1 Hz sine sampled at 200 Hz, resampled to 100 Hz, must equal sin(2π t) at the new
    # times. resample_poly's Kaiser anti-alias filter passes 1 Hz with ripple far below
    # 1e-3; the first and last 0.5 s hold the filter's edge transients and are excluded.
    from armfit.io.trials import Trial, TrialMeta
    fs, n = 200.0, 4000
    t = np.arange(n) / fs
    force = np.column_stack([np.sin(2 * np.pi * t), np.full(n, np.nan), np.full(n, np.nan)])
    grip = np.repeat(np.arange(n // 4, dtype=float), 4)
    trial = Trial(TrialMeta("1", "x", 1.0, None, fs, n, 0.0, "s"), force, force.copy(), grip)
    out = resample_trial(trial, 100.0)
    assert out.meta.n_samples == 2000 and out.meta.fs == 100.0
    t2 = np.arange(2000) / 100.0
    inner = slice(50, -50)
    np.testing.assert_allclose(out.f[inner], np.sin(2 * np.pi * t2)[inner], atol=1e-3)
    assert np.isnan(out.force[:, 1]).all()
    # Grip holds the last sample at or before each new time: new sample k is old 2k.
    np.testing.assert_array_equal(out.grip, grip[::2])


# ---------------------------------------------------------------------------
# Canonical dataset
# ---------------------------------------------------------------------------


@pytest.fixture(scope="module")
def raw_study(tmp_path_factory, write_trial):
    """Three raw trials in three formats: one without grip or cross axes, one in mm."""
    root = tmp_path_factory.mktemp("study")
    write_trial(root / "sub-01_axis-x_grip-1N.csv", seed=10, t0_s=3.0)
    write_trial(root / "sub-01_axis-y_grip-2N_run-2.parquet", seed=11, all_axes=False,
                grip=False)
    write_trial(root / "sub-02_axis-z_grip-1.5N.csv.gz", seed=12, pos_unit="mm")
    return root


def test_dataset_round_trip_bit_for_bit(tmp_path, raw_study):
    originals = list(open_trials([raw_study]))
    out = tmp_path / "trials.parquet"
    metas = write_dataset(originals, out)
    assert metas == [t.meta for t in originals]
    assert is_dataset(out) and not is_dataset(raw_study / "sub-01_axis-y_grip-2N_run-2.parquet")
    records = dataset_metadata(out)
    assert [r["columns"] for r in records][1] == ["force_y_N", "pos_y_m"]
    for src, orig in zip(dataset_sources(out), originals, strict=True):
        back = read_trial(src)
        assert back.meta == orig.meta
        assert np.array_equal(back.force, orig.force, equal_nan=True)
        assert np.array_equal(back.pos, orig.pos, equal_nan=True)
        assert (back.grip is None) == (orig.grip is None)
        if orig.grip is not None:
            assert np.array_equal(back.grip, orig.grip, equal_nan=True)
    # One row group per trial; read_trial of a source reads only that row group.
    import pyarrow.parquet as pq
    assert pq.ParquetFile(out).num_row_groups == 3
    # A dataset is accepted as input and yields the same trials again.
    again = list(open_trials([out]))
    assert [t.meta for t in again] == metas


def test_dataset_with_nullable_columns_reads_the_same(tmp_path, raw_study):
    # armfit writes the dataset's columns as required (no definition levels); a dataset
    # whose columns are nullable (written by an earlier armfit, or by other software
    # from the same table) holds the same values and is read the same, trial by trial
    import pyarrow as pa
    import pyarrow.parquet as pq
    ours = tmp_path / "trials.parquet"
    write_dataset(list(open_trials([raw_study])), ours)
    table = pq.read_table(ours)
    assert not any(f.nullable for f in table.schema)
    nullable = pa.schema([f.with_nullable(True) for f in table.schema])
    other = tmp_path / "nullable.parquet"
    with pq.ParquetWriter(other, nullable) as w:
        for g in range(pq.ParquetFile(ours).num_row_groups):
            w.write_table(pq.ParquetFile(ours).read_row_group(g).cast(nullable))
        w.add_key_value_metadata({k: v for k, v in pq.read_metadata(ours).metadata.items()
                                  if k.startswith(b"armfit.")})
    assert all(f.nullable for f in pq.read_schema(other))
    assert dataset_metadata(other) == dataset_metadata(ours)
    for a, b in zip(dataset_sources(ours), dataset_sources(other), strict=True):
        ta, tb = read_trial(a), read_trial(b)
        assert ta.meta == tb.meta
        assert (ta.grip is None) == (tb.grip is None)
        pairs = [(ta.force, tb.force), (ta.pos, tb.pos)]
        pairs += [] if ta.grip is None else [(ta.grip, tb.grip)]
        for x, y in pairs:
            assert np.array_equal(x, y, equal_nan=True)


def test_write_dataset_stops_at_a_bad_trial_behind_a_row_group_being_written(tmp_path,
                                                                            raw_study):
    # the row groups are written by a thread while the next trial is read: a trial that
    # fails after others (here one with a reference, refused without the column) leaves
    # no file and no thread behind
    import dataclasses
    import threading
    good = list(open_trials([raw_study]))
    bad = dataclasses.replace(good[0], ref=np.zeros(good[0].meta.n_samples))
    before = threading.active_count()
    with pytest.raises(UsageError, match="has a reference"):
        write_dataset([*good, bad], tmp_path / "t.parquet")
    assert list(tmp_path.iterdir()) == []
    assert threading.active_count() == before


def test_write_dataset_raises_the_writers_error_and_leaves_nothing(tmp_path, raw_study,
                                                                  monkeypatch):
    # an error of the thread that writes the row groups (a full disk: OSError at the
    # second row group) is raised by write_dataset itself, as the error naming the file
    # that it is when the caller's own thread writes, and no file is left
    import threading

    import pyarrow.parquet as pq
    real = pq.ParquetWriter.write_table
    calls = []

    def full_disk(self, table, *args, **kwargs):
        calls.append(threading.current_thread().name)
        if len(calls) == 2:
            raise OSError(28, "No space left on device")
        return real(self, table, *args, **kwargs)

    monkeypatch.setattr(pq.ParquetWriter, "write_table", full_disk)
    with pytest.raises(OutputError, match="t.parquet: cannot write: No space left"):
        write_dataset(list(open_trials([raw_study])), tmp_path / "t.parquet")
    assert list(tmp_path.iterdir()) == []
    assert len(calls) == 2 and all(n.startswith("armfit-write") for n in calls)


def test_write_dataset_empty_leaves_nothing(tmp_path):
    with pytest.raises(NoInputError, match="no trials to write"):
        write_dataset([], tmp_path / "t.parquet")
    assert list(tmp_path.iterdir()) == []
