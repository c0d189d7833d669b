"""Reading by row group gives what a whole read gives (a group laid out as armfit writes
it made straight from Arrow, any other by ``Spectra.from_frame``), and the canonical
dataset's encoding keeps every value.

The references are computed independently of the code under test: a spectra file read
whole by pyarrow and turned into a Spectra by ``Spectra.from_frame`` (the reader's former
route), and the rows a selection keeps picked with numpy from that reference's keys; the
trials read straight from the raw files of the sample study.
"""

from __future__ import annotations

import base64
import gc
import json
import weakref
import zlib
from dataclasses import replace
from pathlib import Path

import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

import armfit
from armfit import spectra as S
from armfit.diagnosis import diagnose_axes
from armfit.diagnosis.joint import JointProblem
from armfit.diagnosis.responses import axis_data
from armfit.errors import BadInputError
from armfit.fitting import trial_groups
from armfit.io.schema import (
    SPECTRA_ESTIMATORS_JSON_KEY,
    SPECTRA_ESTIMATORS_KEY,
    SPECTRA_META_KEY,
    SPECTRA_VALUES,
)
from armfit.io.trials import dataset_sources, discover, read_trial, write_dataset
from armfit.models.arm import ClosedLoopModel

STUDY = Path(__file__).resolve().parents[1] / "sample_data" / "study"


@pytest.fixture(scope="module")
def sample(tmp_path_factory) -> dict[str, Path]:
    """The sample study's spectra (36 trials, 192 responses) written three ways: one row
    group (as armfit writes a study this size), groups of 7 responses, and groups of 50."""
    root = tmp_path_factory.mktemp("spectra")
    sp = armfit.estimate(STUDY)
    out = {"one group": root / "one.parquet"}
    sp.write(out["one group"])
    for rows in (7, 50):
        out[f"{rows} a group"] = root / f"by{rows}.parquet"
        S.write_parts(sp.parts(rows), sp.meta, out[f"{rows} a group"])
    return out


def whole(path: Path) -> S.Spectra:
    """The file read in one piece by pyarrow, made a Spectra from its long table."""
    table = pq.read_table(path)
    kv = table.schema.metadata
    meta = json.loads(kv[SPECTRA_META_KEY])
    if SPECTRA_ESTIMATORS_KEY in kv:     # the per-trial records: JSON, zlib, base64
        meta["estimators"] = json.loads(zlib.decompress(base64.b64decode(
            kv[SPECTRA_ESTIMATORS_KEY])))
    return S.Spectra.from_frame(table.to_pandas(), meta=meta, source=str(path))


def assert_same(a: S.Spectra, b: S.Spectra) -> None:
    """Equal responses: keys, grid, every value (NaN where NaN), flags, presence, meta."""
    assert np.array_equal(a.freq_hz, b.freq_hz)
    assert list(a.keys) == list(b.keys)
    for k in a.keys:
        x, y = list(a.keys[k]), list(b.keys[k])
        assert len(x) == len(y), k
        assert all(u == v or (u != u and v != v) for u, v in zip(x, y, strict=True)), k
    assert np.array_equal(a.h, b.h, equal_nan=True)
    for c in SPECTRA_VALUES:
        assert np.array_equal(a.values[c], b.values[c], equal_nan=True), c
    assert np.array_equal(a.flags, b.flags)
    assert np.array_equal(a.present, b.present)
    assert a.meta == b.meta and a.source == b.source


@pytest.mark.parametrize("layout", ["one group", "7 a group", "50 a group"])
def test_reading_by_row_group_gives_the_whole_table(sample, layout):
    path = sample[layout]
    # 228 responses: 36 trials × 5 (measured, derived, 2 cross, the alternative H2) and
    # 48 aggregates (12 kinds and axes × 3 grip means and a median)
    assert pq.ParquetFile(path).num_row_groups == {"one group": 1, "7 a group": 33,
                                                   "50 a group": 5}[layout]
    assert_same(S.Spectra.read(path), whole(path))


def test_the_file_holds_its_metadata_once_and_reads_as_one_with_arrows_schema(sample,
                                                                             tmp_path):
    """The footer keeps armfit's JSON under its own key only: no ``ARROW:schema``, whose
    base64 copy of the schema repeated it. A file written with that copy (as pyarrow
    writes by default, and armfit wrote before) reads to the same responses."""
    path = sample["7 a group"]
    kv = pq.read_metadata(path).metadata
    assert set(kv) == {SPECTRA_META_KEY, SPECTRA_ESTIMATORS_KEY, b"pandas"}
    assert json.loads(kv[SPECTRA_META_KEY])["method"] == "h1"
    # the same table written with Arrow's schema copy: its metadata there is twice in
    # the footer, and Arrow reads the text columns back as large_string
    table = pq.read_table(path)
    schema = table.schema.with_metadata(kv).set(
        0, pa.field("level", pa.large_string()))
    old = tmp_path / "with_arrow_schema.parquet"
    pq.write_table(table.cast(schema), old, row_group_size=7 * 100)
    old_kv = pq.read_metadata(old).metadata
    assert b"ARROW:schema" in old_kv and len(old_kv[b"ARROW:schema"]) > len(
        kv[SPECTRA_META_KEY])
    assert pq.read_schema(old).field("level").type == pa.large_string()
    got = S.Spectra.read(old)
    assert_same(got, replace(S.Spectra.read(path), source=str(old)))
    # pandas reads the two files to the same frame
    pd.testing.assert_frame_equal(pd.read_parquet(old), pd.read_parquet(path))


def test_the_per_trial_records_are_apart_compressed_and_a_read_without_them_never_parses_them(
        sample, tmp_path, monkeypatch):
    """The metadata's per-trial records (``estimators``: one per trial of the sample
    study's 36) are under a key of their own, their JSON compressed by zlib in base64
    (Python's own zlib and base64 unpack it), so a read that leaves them out
    (``estimators=False``) never unpacks or parses them; everything else it reads is the
    same. Files of the two former layouts — the JSON as it is under
    ``armfit.estimators``, or inside armfit's JSON — read to the same metadata either
    way."""
    path = sample["7 a group"]
    kv = pq.read_metadata(path).metadata
    assert "estimators" not in json.loads(kv[SPECTRA_META_KEY])
    text = zlib.decompress(base64.b64decode(kv[SPECTRA_ESTIMATORS_KEY]))
    records = json.loads(text)
    assert len(records) == 36 and {"subject", "axis", "grip_N", "run"} <= set(records[0])
    assert len(kv[SPECTRA_ESTIMATORS_KEY]) < len(text) / 4
    full = S.Spectra.read(path)
    assert full.meta["estimators"] == records
    table = pq.read_table(path)
    old_meta = {**json.loads(kv[SPECTRA_META_KEY]), "estimators": records}
    plain = json.dumps(records).encode()
    former = {
        # the records inside armfit's JSON
        "inside": {SPECTRA_META_KEY: json.dumps(old_meta).encode()},
        # the records' JSON as it is, under a key of its own
        "plain": {SPECTRA_META_KEY: kv[SPECTRA_META_KEY], SPECTRA_ESTIMATORS_JSON_KEY: plain},
    }
    olds = []
    for name, meta_kv in former.items():
        old = tmp_path / f"records_{name}.parquet"
        pq.write_table(table.replace_schema_metadata({**meta_kv, b"pandas": kv[b"pandas"]}),
                       old, row_group_size=7 * 100)
        assert_same(S.Spectra.read(old), replace(full, source=str(old)))
        olds.append(old)
    parsed, unpacked = [], []
    real_loads, real_decompress = json.loads, zlib.decompress

    def loads(text, *args, **kwargs):
        parsed.append(bytes(text))
        return real_loads(text, *args, **kwargs)

    def decompress(data, *args, **kwargs):
        unpacked.append(data)
        return real_decompress(data, *args, **kwargs)

    monkeypatch.setattr(json, "loads", loads)
    monkeypatch.setattr(zlib, "decompress", decompress)
    for p in (path, *olds):
        lean = S.Spectra.read(p, level="trial", kind="measured", estimators=False)
        assert "estimators" not in lean.meta
        kept = {k: v for k, v in full.meta.items() if k != "estimators"}
        assert lean.meta == kept
        assert_same(lean, replace(full.select(level="trial", kind="measured"),
                                  meta=kept, source=str(p)))
    assert not unpacked and plain not in parsed
    assert kv[SPECTRA_META_KEY] in parsed


@pytest.mark.parametrize("wanted", [
    {"level": "trial"},
    {"level": ("mean", "median")},
    {"kind": "derived", "axis": "y"},
    {"level": "trial", "kind": ("measured", "cross"), "axis": "z"},
    {"level": "nothing of the kind"},
])
def test_a_selection_read_by_row_group_keeps_what_select_keeps(sample, wanted):
    path = sample["7 a group"]
    ref = whole(path)
    keep = np.ones(len(ref), bool)
    for k, v in wanted.items():
        keep &= np.isin(np.array([str(x) for x in ref.keys[k]]),
                        [v] if isinstance(v, str) else list(v))
    got = S.Spectra.read(path, **wanted)
    # the rows the numpy mask keeps, in file order, on the frequencies they have
    assert_same(got, ref.take(np.flatnonzero(keep)))
    assert len(got) == int(keep.sum())


def test_a_spectra_file_is_never_read_whole(sample, monkeypatch):
    """The reader takes the file a row group at a time: pyarrow's whole-file reader is
    not called, and no long table bigger than a group is turned into responses."""
    path = sample["7 a group"]
    ref = whole(path)

    def no_whole_read(*args, **kwargs):
        raise AssertionError("the whole spectra file was read")

    sizes = []
    real = S._group_spectra

    def counted(table, *args):
        sizes.append(table.num_rows)
        return real(table, *args)

    monkeypatch.setattr(pq, "read_table", no_whole_read)
    monkeypatch.setattr(S, "_group_spectra", counted)
    assert_same(S.Spectra.read(path), ref)
    assert len(sizes) == 33 and max(sizes) == 7 * ref.freq_hz.size
    sizes.clear()
    assert len(S.Spectra.read(path, level="mean")) == int(np.sum(ref.keys["level"] == "mean"))
    assert max(sizes) == 7 * ref.freq_hz.size


def test_the_run_reads_its_spectra_by_row_group(tmp_path, monkeypatch):
    """`armfit run` never holds spectra.parquet as one table: every Spectra it makes from
    the file comes from at most one row group's rows (groups of 16 responses here)."""
    monkeypatch.setattr(S, "WRITE_ROWS", 16)
    real_read, real_from = pq.read_table, S.Spectra.from_frame.__func__
    real_group = S._group_spectra
    sizes = []

    def read_table(source, *args, **kwargs):
        assert Path(str(source)).name != "spectra.parquet", "spectra.parquet read whole"
        return real_read(source, *args, **kwargs)

    def counted(cls, df, **kwargs):
        sizes.append(len(df))
        return real_from(cls, df, **kwargs)

    def counted_group(table, *args):
        sizes.append(table.num_rows)
        return real_group(table, *args)

    monkeypatch.setattr(pq, "read_table", read_table)
    monkeypatch.setattr(S.Spectra, "from_frame", classmethod(counted))
    monkeypatch.setattr(S, "_group_spectra", counted_group)
    result = armfit.run(STUDY, tmp_path / "out", figures=False)
    nf = len(S.EstimateConfig().grid())
    assert result.trials == 36
    # 228 responses (see above) in groups of 16
    assert pq.ParquetFile(tmp_path / "out" / "spectra.parquet").num_row_groups == 15
    assert sizes and max(sizes) <= 16 * nf


def test_the_run_lets_the_derived_rows_go_before_the_trial_fits_read_theirs(tmp_path,
                                                                            monkeypatch):
    """fit-uncertainty makes W_max of the derived trial rows and lets them go before the
    per-trial fits read the measured trial rows and while the Wu fits run: no derived
    rows read from the file are alive when the trial fits' read starts."""
    real = S.Spectra.read.__func__
    derived: list[weakref.ref] = []
    alive_at_trial_read: list[int] = []

    def read(cls, path, **kwargs):
        if kwargs.get("level") == "trial" and kwargs.get("kind") == "measured" \
                and kwargs.get("axis") is None:     # the trial fits' read
            gc.collect()
            alive_at_trial_read.append(sum(r() is not None for r in derived))
        out = real(cls, path, **kwargs)
        if kwargs.get("level") == "trial" and kwargs.get("kind") == "derived":
            derived.append(weakref.ref(out))
        return out

    monkeypatch.setattr(S.Spectra, "read", classmethod(read))
    result = armfit.run(STUDY, tmp_path / "out", figures=False, jobs=2)
    assert result.trials == 36
    assert len(derived) == 1 and alive_at_trial_read == [0]


def test_a_response_split_over_row_groups_is_read_as_one(sample, tmp_path):
    """A file another program wrote may continue a response in the next row group: the
    reader then gives the responses of the whole table."""
    table = pq.read_table(sample["one group"])
    path = tmp_path / "split.parquet"
    with pq.ParquetWriter(path, table.schema) as w:
        w.write_table(table.slice(0, 150))   # 1.5 responses of 100 frequencies
        w.write_table(table.slice(150))
    assert pq.ParquetFile(path).num_row_groups == 2
    assert_same(S.Spectra.read(path), whole(path))


def test_a_bad_row_in_a_later_group_is_named_by_its_row_in_the_file(sample, tmp_path):
    table = pq.read_table(sample["7 a group"])
    df = table.to_pandas()
    bad = 2000            # a data row in the third group of 700 rows
    df.loc[bad, "out_axis"] = "w"
    path = tmp_path / "bad.parquet"
    bad_table = pa.Table.from_pandas(df, preserve_index=False).replace_schema_metadata(
        table.schema.metadata)
    pq.write_table(bad_table, path, row_group_size=700)
    with pytest.raises(BadInputError) as exc:
        S.Spectra.read(path, level="mean")
    assert exc.value.row == bad + 1 and exc.value.column == "out_axis"
    assert "axis 'w' is not x, y or z" in str(exc.value)


@pytest.mark.parametrize("layout", ["one group", "7 a group"])
@pytest.mark.parametrize("values", [("se_db", "se_deg"), ("coherence",), ()])
def test_a_read_keeping_some_values_is_the_whole_read_without_the_others(sample, layout,
                                                                         values):
    # the same responses, grid, flags and presence as the whole table read, and of its
    # values exactly those asked for (33 row groups and 192 trial rows in the second
    # layout: the read gives memory back every few groups and parts as it goes)
    path = sample[layout]
    ref = whole(path)
    ref = ref.take(np.flatnonzero(np.array([str(v) for v in ref.keys["level"]]) == "trial"))
    got = S.Spectra.read(path, level="trial", values=values)
    assert list(got.values) == list(values)
    for c in values:
        assert np.array_equal(got.values[c], ref.values[c], equal_nan=True), c
    assert_same(S.Spectra(got.freq_hz, got.keys, got.h, dict(ref.values), got.flags,
                          got.present, got.meta, got.source), ref)


def test_a_read_of_values_a_spectra_file_has_not_is_refused(sample):
    from armfit.errors import UsageError
    with pytest.raises(UsageError, match="'se_dB'"):
        S.Spectra.read(sample["one group"], values=("se_db", "se_dB"))


def test_the_diagnosis_of_a_file_read_axis_by_axis_is_that_of_the_whole(sample):
    path = sample["7 a group"]
    grip = armfit.fit_grip(S.Spectra.read(path, level="mean"))
    by_file = diagnose_axes(path, grip.table)
    in_memory = diagnose_axes(whole(path), grip.table)
    assert [d.axis for d in by_file] == ["x", "y", "z"]
    doc = armfit.Diagnosis(tuple(by_file)).to_dict()
    assert doc == armfit.Diagnosis(tuple(in_memory)).to_dict()
    assert all(doc["axes"][a]["cross_coupling_db"] for a in "xyz")


def test_trial_groups_of_a_file_are_those_of_its_spectra(sample):
    path = sample["50 a group"]
    by_file, in_memory = trial_groups(path), trial_groups(whole(path))
    assert len(by_file) == 36
    for (k1, rows1), (k2, rows2) in zip(by_file, in_memory, strict=True):
        assert k1 == k2
        assert all(np.array_equal(a, b, equal_nan=True)
                   for a, b in zip(rows1, rows2, strict=True))


def test_trial_groups_hold_whole_grid_responses_as_views_of_one_read(sample):
    # a response on every frequency is a view of the read's arrays (one copy of the
    # study's responses, not two), a response lacking a frequency its own copy at the
    # frequencies it has; the values are those of Spectra.row either way
    sp = S.Spectra.read(sample["one group"], level="trial", kind="measured",
                        values=("se_db", "se_deg"))
    present = sp.present.copy()
    present[3, 5] = False       # one trial's response without its sixth frequency
    sp = S.Spectra(sp.freq_hz, sp.keys, sp.h, sp.values, sp.flags, present, sp.meta,
                   sp.source)
    index = {(str(a), str(s), float(g), r): i for i, (a, s, g, r) in enumerate(zip(
        sp.key("axis"), sp.key("subject"), sp.key("grip_N"), sp.key("run"), strict=True))}
    groups = trial_groups(sp)
    assert len(groups) == len(sp) == 36
    for key, rows in groups:
        i = index[key]
        assert all(np.array_equal(a, b, equal_nan=True)
                   for a, b in zip(rows, sp.row(i), strict=True))
        assert np.shares_memory(rows[1], sp.h) == (i != 3)
        assert rows[0].size == sp.freq_hz.size - (i == 3)


def test_take_of_every_row_is_the_spectra_itself(sample):
    sp = S.Spectra.read(sample["one group"])
    assert sp.take(np.arange(len(sp))) is sp
    assert sp.select() is sp
    part = sp.take(np.arange(1, len(sp)))
    assert part is not sp and len(part) == len(sp) - 1
    assert np.array_equal(part.h, sp.h[1:])


def test_the_joint_problem_in_blocks_of_trials_is_the_joint_problem(sample, monkeypatch):
    """Each trial's residuals and Jacobian rows depend on that trial only: evaluated a few
    trials at a time they agree with one evaluation of all (to round-off, which the
    forward difference magnifies to ~1e-8 relative)."""
    from armfit.diagnosis import joint

    sp = S.Spectra.read(sample["one group"], level=("trial", "mean"), kind="measured")
    grip = armfit.fit_grip(sp)
    data = axis_data(sp, grip.table, "y")
    prob = JointProblem(ClosedLoopModel.for_axis("y"), data, np.ones(data.f_hz.size, bool))
    x = prob.pack(np.array([[s[n] for n in ("Ma", "k1", "k2", "b1", "b2")]
                            for s in data.starts]), {})
    jb, js = prob.jac(x)
    r = prob.fun(x)
    monkeypatch.setattr(joint, "CHUNK_TRIALS", 5)
    jb5, js5 = prob.jac(x)
    assert jb.shape == jb5.shape == (12, 2 * data.f_hz.size, 5) and js5.shape[2] == 0
    np.testing.assert_allclose(jb5, jb, rtol=1e-6, atol=1e-9 * np.abs(jb).max())
    # the residuals themselves, a few trials at a time, to round-off
    np.testing.assert_allclose(prob.fun(x), r, rtol=1e-12, atol=1e-12 * np.abs(r).max())


@pytest.fixture(scope="module")
def sample_trials():
    """The sample study's trials as read from their raw files."""
    sources, _ = discover([STUDY])
    return [read_trial(s) for s in sources]


def test_the_dataset_reads_back_every_value_bit_for_bit(sample_trials, tmp_path):
    path = tmp_path / "trials.parquet"
    write_dataset(sample_trials, path)
    back = [read_trial(s) for s in dataset_sources(path)]
    assert len(back) == len(sample_trials) == 36
    for t, b in zip(sample_trials, back, strict=True):
        assert b.meta == t.meta
        for x, y in ((t.force, b.force), (t.pos, b.pos), (t.grip, b.grip)):
            # the same bits, NaN (absent axis, missing grip sample) included
            assert np.array_equal(x.view(np.uint64), y.view(np.uint64))


def test_the_dataset_is_plain_parquet_no_larger_than_the_raw_files(sample_trials, tmp_path):
    path = tmp_path / "trials.parquet"
    write_dataset(sample_trials, path)
    df = pd.read_parquet(path)                    # any Parquet reader: pandas here
    assert len(df) == sum(t.meta.n_samples for t in sample_trials)
    first = df[df["trial"] == 0]
    t = sample_trials[0]
    assert np.array_equal(first["force_x_N"].to_numpy(), t.force[:, 0], equal_nan=True)
    assert np.array_equal(first["pos_z_m"].to_numpy(), t.pos[:, 2], equal_nan=True)
    column = pq.ParquetFile(path).metadata.row_group(0)
    enc = {column.column(i).path_in_schema: column.column(i) for i in range(column.num_columns)}
    assert {c.compression for c in enc.values()} == {"ZSTD"}
    assert "BYTE_STREAM_SPLIT" in enc["force_x_N"].encodings
    assert "RLE_DICTIONARY" in enc["pos_x_m"].encodings
    # the sample study's raw files are zstd Parquet (level 9) with time stored: the
    # dataset, without time, measured 0.96 x their size
    raw = sum(p.stat().st_size for p in STUDY.iterdir())
    assert path.stat().st_size <= raw


# ---------------------------------------------------------------------------
# A row group laid out as armfit writes it becomes responses straight from Arrow
# ---------------------------------------------------------------------------


def _edited(sample, tmp_path, edit) -> Path:
    """The sample's one-group file with its long table changed by ``edit(df)``."""
    table = pq.read_table(sample["one group"])
    df = edit(table.to_pandas())
    path = tmp_path / "edited.parquet"
    pq.write_table(pa.Table.from_pandas(df, preserve_index=False).replace_schema_metadata(
        table.schema.metadata), path)
    return path


def test_arrow_responses_are_from_frames(sample):
    # the reference: Spectra.from_frame of the group's long table (the pandas route);
    # the sample holds trial rows, grip means and medians (grip NaN), flags of several
    # kinds and the alternative estimate
    table = pq.read_table(sample["one group"])
    meta = json.loads(table.schema.metadata[SPECTRA_META_KEY])
    got = S._arrow_spectra(table.select(list(S.SPECTRA_COLUMNS)), meta, "f")
    assert got is not None
    assert_same(got, S.Spectra.from_frame(table.to_pandas(), meta=meta, source="f"))
    assert len({f for f in got.flags.ravel()}) > 2


def test_runs_and_missing_keys_read_as_from_frame_reads_them(sample, tmp_path):
    # repeated trials (run 1, 2) beside trials without a run, and a response without a
    # subject or method: the keys are None, ints and NaN as from_frame gives them
    def edit(df):
        trial = df["level"] == "trial"
        first = df.loc[trial, "subject"].iloc[0]
        mine = trial & (df["subject"] == first)
        df["run"] = pd.array([None] * len(df), dtype="Int64")
        df.loc[mine & (df["grip_N"] == 1.0), "run"] = 1
        df.loc[mine & (df["grip_N"] == 2.0), "run"] = 2
        df.loc[mine & (df["grip_N"] == 3.0), "method"] = None
        return df

    path = _edited(sample, tmp_path, edit)
    got = S.Spectra.read(path)
    assert_same(got, whole(path))
    assert {1, 2, None} <= set(got.keys["run"]) and None in set(got.keys["method"])


@pytest.mark.parametrize("what", ["split", "twice", "text", "negative run", "zero freq"])
def test_a_group_not_laid_out_as_armfit_writes_it_is_read_by_from_frame(sample, tmp_path,
                                                                        what):
    # each is left to from_frame (the Arrow route gives None), which reads it as it
    # always did, or refuses it naming the column and row
    def edit(df):
        if what == "split":      # the first response's last 10 rows after the second's
            n = int(df["freq_hz"].iloc[1:].eq(df["freq_hz"].iloc[0]).idxmax())  # rows
            assert n == 100          # of the first response: its 100 frequencies
            order = [*range(n - 10), *range(n, 2 * n), *range(n - 10, n),
                     *range(2 * n, len(df))]
            return df.iloc[order].reset_index(drop=True)
        if what == "twice":      # row 5 repeats row 4's frequency
            df.loc[4, "freq_hz"] = df.loc[3, "freq_hz"]    # rows 4 and 5 of the file
        if what == "text":       # numbers written as text (another program's file)
            df["re"] = df["re"].map(repr)
        if what == "negative run":   # from_frame takes a whole-number column as it is
            df["run"] = pd.array([None] * len(df), dtype="Int64")
            df.loc[7, "run"] = -1
        if what == "zero freq":
            df.loc[9, "freq_hz"] = 0.0
        return df

    path = _edited(sample, tmp_path, edit)
    table = pq.read_table(path)
    meta = json.loads(table.schema.metadata[SPECTRA_META_KEY])
    assert S._arrow_spectra(table.select(list(S.SPECTRA_COLUMNS)), meta, str(path)) is None
    try:
        expected = whole(path)
    except BadInputError as exc:
        with pytest.raises(BadInputError) as got:
            S.Spectra.read(path)
        assert (str(got.value), got.value.row, got.value.column) == (
            str(exc), exc.row, exc.column)
        # the first of the two rows of one frequency; the zero frequency's own row
        assert (exc.column, exc.row) == {"twice": ("freq_hz", 4),
                                         "zero freq": ("freq_hz", 10)}[what]
    else:
        assert what in ("split", "text", "negative run")
        assert_same(S.Spectra.read(path), expected)


@pytest.mark.parametrize("study", ["study", "hidden"])
def test_a_studys_aggregates_are_the_rows_its_file_reads_back(study, tmp_path):
    # `armfit run` starts the grip fits from StudySpectra.aggregates(kinds=("measured",))
    # and makes the other kinds' while the file is written: they must be the rows
    # Spectra.read gives of the levels mean and median (of that kind), whichever were
    # made first
    def same(made, read):
        assert len(made) == len(read) > 0
        pd.testing.assert_frame_equal(made.to_frame(), read.to_frame(), check_exact=True)
        assert made.meta == read.meta
        assert np.array_equal(made.present, read.present)

    est = S.estimate_study([STUDY.parent / study], S.EstimateConfig())
    measured = est.aggregates(kinds=("measured",))
    path = est.write(tmp_path / "spectra.parquet")
    same(measured, S.Spectra.read(path, level=("mean", "median"), kind="measured"))
    read = S.Spectra.read(path, level=("mean", "median"))
    made = est.aggregates()
    assert set(made.keys["level"]) == {"mean", "median"}
    assert set(made.keys["kind"]) > {"measured"}
    same(made, read)
    # and the file is the one written when every kind is made at once
    other = S.estimate_study([STUDY.parent / study], S.EstimateConfig())
    assert other.write(tmp_path / "whole.parquet").read_bytes() == path.read_bytes()


# ---------------------------------------------------------------------------
# A study's trials wait in a temporary file (SpooledTrials), read back one at a time
# ---------------------------------------------------------------------------

@pytest.fixture(scope="module")
def spooled(small_study) -> S.StudySpectra:
    """The small study estimated from its files in this process."""
    return S.estimate_study([small_study], S.EstimateConfig())


def _held(sp: S.StudySpectra) -> S.StudySpectra:
    """The same study with its trials all in memory (a tuple): the reference."""
    from dataclasses import replace
    return replace(sp, trials=tuple(sp.trials))


def test_an_estimated_studys_trials_read_back_bit_for_bit(spooled):
    # the reference: the same trials held in memory, compared array by array
    trials = spooled.trials
    assert isinstance(trials, S.SpooledTrials)
    held = tuple(trials)
    assert len(trials) == len(held) == 4          # 2 subjects x 2 grips, axis x
    for a, b in zip(trials, held, strict=True):
        assert (a.source, a.axis, a.grip_N, a.subject) == (b.source, b.axis, b.grip_N,
                                                           b.subject)
        for ra, rb in zip(a.responses, b.responses, strict=True):
            assert ra.flags == rb.flags
            for name in ("h", "coherence", "se_db", "se_deg"):
                assert np.array_equal(getattr(ra, name), getattr(rb, name), equal_nan=True)
    assert [t.source for t in trials[1:3]] == [held[1].source, held[2].source]
    assert trials[-1].source == held[-1].source
    import pickle
    back = pickle.loads(pickle.dumps(trials))            # pickled, a tuple
    assert type(back) is tuple and [t.source for t in back] == [t.source for t in held]


def test_the_first_trials_are_held_and_the_rest_read_back_from_the_file(spooled,
                                                                        monkeypatch):
    # the reference: the trials appended; the first HELD_TRIALS are those very objects,
    # the others pickled to the file and read back equal, in their order
    import pickle
    monkeypatch.setattr(S.SpooledTrials, "HELD_TRIALS", 2)
    trials = tuple(spooled.trials)
    spool = S.SpooledTrials()
    for t in trials:
        spool.append(t)
    assert len(spool) == 4 and spool._file is not None
    assert spool[0] is trials[0] and spool[1] is trials[1]
    for k in (2, 3):
        assert spool[k] is not trials[k]
        assert pickle.dumps(spool[k]) == pickle.dumps(trials[k])    # bit for bit
    assert [t.source for t in spool[1:4]] == [t.source for t in trials[1:4]]
    assert spool.outlines() == [S._outline(t) for t in trials]
    # none held: every trial in the file, nothing held in memory
    monkeypatch.setattr(S.SpooledTrials, "HELD_TRIALS", 0)
    spool = S.SpooledTrials()
    for t in trials:
        spool.append(t)
    assert all(spool[k] is not trials[k] for k in range(4))
    assert [pickle.dumps(t) for t in spool] == [pickle.dumps(t) for t in trials]


def test_a_spooled_study_writes_the_file_a_held_one_writes(spooled, tmp_path):
    # the same study with its trials in memory (the former route) writes the reference
    spooled.write(tmp_path / "spooled.parquet")
    _held(spooled).write(tmp_path / "held.parquet")
    assert (tmp_path / "spooled.parquet").read_bytes() == \
        (tmp_path / "held.parquet").read_bytes()
    assert S.estimator_summary(spooled.trials) == \
        S.estimator_summary(tuple(spooled.trials))


class _Watched(S.SpooledTrials):
    """A SpooledTrials that records, at each read, how many trials it handed out are
    still alive; it holds none in memory (every trial goes to its file)."""

    HELD_TRIALS = 0

    def __init__(self, trials):
        super().__init__()
        for t in trials:
            self.append(t)
        self.out: list = []
        self.alive_at_read: list[int] = []

    def __getitem__(self, index):
        import weakref
        self.alive_at_read.append(sum(r() is not None for r in self.out))
        got = super().__getitem__(index)
        if not isinstance(index, slice):
            self.out.append(weakref.ref(got))
        return got


def test_the_aggregates_hold_one_trial_at_a_time(spooled):
    # invariant: the aggregates of a spooled study are those of the trials held in
    # memory, and no more than one trial read back is alive when the next is read
    import gc
    watched = _Watched(spooled.trials)
    gc.disable()            # a trial alive is one still referenced, not one not yet freed
    try:
        blocks = S._aggregate_blocks(watched)
    finally:
        gc.enable()
    want = S._aggregate_blocks(tuple(spooled.trials))
    # measured, derived and cross to y and z: a mean per grip (2) and a median each
    assert len(blocks) == len(want) == 4 * 3
    for a, b in zip(blocks, want, strict=True):
        assert a.keys() == b.keys()
        for k in a:
            va, vb = a[k], b[k]
            if isinstance(va, np.ndarray):
                assert np.array_equal(va, vb, equal_nan=True), k
            else:
                assert va == vb or (va != va and vb != vb), k
    assert max(watched.alive_at_read) <= 1
    assert len(watched.alive_at_read) >= len(watched)   # every trial was read back


def test_a_temporary_file_that_cannot_be_written_is_an_output_error(small_study,
                                                                     monkeypatch):
    import errno
    import tempfile

    from armfit.errors import OutputError

    def full(*args, **kwargs):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(tempfile, "TemporaryFile", full)
    monkeypatch.setattr(S.SpooledTrials, "HELD_TRIALS", 0)   # the first trial goes there
    with pytest.raises(OutputError, match=r"cannot keep the trials' responses in a "
                                          r"temporary file in .*No space left on device; "
                                          r"set TMPDIR"):
        armfit.estimate(small_study)


@pytest.mark.parametrize("by", [("subject", "grip_N", "run"), ("axis", "level", "method"),
                                ("grip_N",)])
def test_sorted_orders_responses_as_pandas_sorts_them(spectra, by):
    # the reference: pandas' stable sort_values of the keys, missing values last (the
    # order of groupby(by, sort=True, dropna=False)); the rows shuffled and some keys
    # made missing, with ties left in their order
    from dataclasses import replace
    sp = S.Spectra.read(spectra)
    rng = np.random.default_rng(7)
    sp = sp.take(rng.permutation(len(sp)))
    keys = {k: np.array(v, dtype=object) for k, v in sp.keys.items()}
    gone = rng.random(len(sp)) < 0.2
    keys["subject"][gone] = None
    keys["grip_N"][rng.random(len(sp)) < 0.2] = np.nan
    runs = rng.integers(1, 4, len(sp))
    keys["run"][:] = [None if g else int(r)
                      for g, r in zip(rng.random(len(sp)) < 0.5, runs, strict=True)]
    keys["method"][rng.random(len(sp)) < 0.2] = None
    sp = replace(sp, keys=keys)
    dtypes = {"subject": "string", "grip_N": "float64", "run": "Int64", "level": "string",
              "axis": "string", "method": "string"}
    frame = pd.DataFrame({k: pd.array(list(keys[k]), dtype=dtypes[k]) for k in by})
    order = frame.sort_values(list(by), na_position="last", kind="stable").index.to_numpy()
    got = sp.sorted(by)
    for k in keys:
        assert list(map(str, got.keys[k])) == list(map(str, keys[k][order])), k
    assert np.array_equal(got.h, sp.h[order], equal_nan=True)


def test_dictionary_columns_give_each_text_one_code():
    # a dictionary holding a text twice (Parquet's dictionary of two pages), and rows
    # without a text: equal texts get equal codes, a missing one -1
    dictionary = pa.array(["b", "a", "b", "c"])
    indices = pa.array([0, 1, 2, None, 3, 2, 0], type=pa.int32())
    codes, texts = S._text_codes(pa.DictionaryArray.from_arrays(indices, dictionary))
    got = [None if c < 0 else texts[c] for c in codes]
    assert got == ["b", "a", "b", None, "c", "b", "b"]
    assert codes[0] == codes[2] == codes[5] == codes[6] and codes[3] == -1
    plain = S._text_codes(pa.array(["b", "a", "b", None, "c", "b", "b"]))
    assert [None if c < 0 else plain[1][c] for c in plain[0]] == got


def test_chunks_on_different_dictionaries_become_one_array():
    a = pa.DictionaryArray.from_arrays(pa.array([0, 1, 0], pa.int32()), pa.array(["x", "y"]))
    b = pa.DictionaryArray.from_arrays(pa.array([1, None], pa.int32()), pa.array(["z", "x"]))
    one = S._one_chunk(pa.chunked_array([a, b]))
    codes, texts = S._text_codes(one)
    assert [None if c < 0 else texts[c] for c in codes] == ["x", "y", "x", "x", None]


def test_a_group_read_with_dictionaries_gives_the_responses_of_from_frame(sample):
    # the text columns read dictionary-encoded, as Spectra.read reads a group
    table = pq.ParquetFile(sample["one group"],
                           read_dictionary=list(S.SPECTRA_TEXT)).read_row_group(0)
    assert pa.types.is_dictionary(table.schema.field("subject").type)
    meta = json.loads(table.schema.metadata[SPECTRA_META_KEY])
    got = S._arrow_spectra(table.select(list(S.SPECTRA_COLUMNS)), meta, "f")
    assert got is not None
    plain = pq.read_table(sample["one group"])
    assert_same(got, S.Spectra.from_frame(plain.to_pandas(), meta=meta, source="f"))


@pytest.mark.parametrize("what", ["as written", "value text", "split", "negative run"])
def test_values_left_out_are_not_read_and_the_rest_is_the_whole_reads(sample, tmp_path,
                                                                      what, monkeypatch):
    # the reference: the file read whole, its responses of level trial, their standard
    # errors only. The other value columns are not read from the file when it holds
    # them as floats; when a group is not laid out as armfit writes it, or another
    # program wrote a value column as text, every column is read and from_frame decides
    def edit(df):
        if what == "value text":
            df["mag_db"] = df["mag_db"].map(repr)
        if what == "split":      # the first response's last 10 rows after the second's
            order = [*range(90), *range(100, 200), *range(90, 100), *range(200, len(df))]
            return df.iloc[order].reset_index(drop=True)
        if what == "negative run":
            df["run"] = pd.array([None] * len(df), dtype="Int64")
            df.loc[7, "run"] = -1
        return df

    path = _edited(sample, tmp_path, edit)
    ref = whole(path).select(level="trial")
    read_columns = []
    real = pq.ParquetFile.read_row_group

    def read_row_group(self, i, columns=None, **kwargs):
        read_columns.append(tuple(columns))
        return real(self, i, columns=columns, **kwargs)

    monkeypatch.setattr(pq.ParquetFile, "read_row_group", read_row_group)
    got = S.Spectra.read(path, level="trial", values=("se_db", "se_deg"))
    assert list(got.values) == ["se_db", "se_deg"]
    for c in ("se_db", "se_deg"):
        assert np.array_equal(got.values[c], ref.values[c], equal_nan=True)
    assert np.array_equal(got.h, ref.h, equal_nan=True)
    assert np.array_equal(got.flags, ref.flags) and got.keys.keys() == ref.keys.keys()
    assert all(list(map(str, got.keys[k])) == list(map(str, ref.keys[k])) for k in got.keys)
    fewer = tuple(c for c in S.SPECTRA_COLUMNS if c not in S.SPECTRA_VALUES
                  or c in ("se_db", "se_deg"))
    assert read_columns[0] == (tuple(S.SPECTRA_COLUMNS) if what == "value text" else fewer)
    if what in ("split", "negative run"):      # the group read again, every column
        assert tuple(S.SPECTRA_COLUMNS) in read_columns[1:]
