"""Scale-out on dask: a dask.distributed client's executor serves as any executor.

One local cluster of two worker processes (one thread each) serves the module. Each
result is compared with the same call run in this process (jobs=1): array- and
frame-equal, or byte-equal for the files the command line writes.
"""

from __future__ import annotations

import pandas as pd
import pytest
from click.testing import CliRunner

import armfit
from armfit.cli.main import cli

distributed = pytest.importorskip("distributed")


@pytest.fixture(scope="module")
def cluster(tmp_path_factory):
    """Two worker processes (processes=True: tasks and results are pickled to and from
    other interpreters, as on a cluster of machines); their scratch space in the test's
    own temporary folder, not dask's default in the system's."""
    import dask
    with dask.config.set({"temporary-directory": str(tmp_path_factory.mktemp("dask"))}), \
            distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                                     dashboard_address=":0") as c:
        yield c


@pytest.fixture(scope="module")
def executor(cluster):
    with distributed.Client(cluster) as client:
        yield client.get_executor()


def test_the_cluster_runs_tasks_in_other_processes(cluster, executor):
    import os
    pids = set(executor.map(lambda _: os.getpid(), range(8)))
    assert os.getpid() not in pids and 1 <= len(pids) <= 2   # its 2 worker processes


def test_estimate_on_dask_is_the_same(small_study, serial_spectra, executor):
    spectra = armfit.estimate(small_study, executor=executor)
    pd.testing.assert_frame_equal(spectra.to_frame(), serial_spectra.to_frame())


def test_fit_trials_on_dask_is_the_same(serial_spectra, executor):
    fits = armfit.fit_trials(serial_spectra, executor=executor)
    ref = armfit.fit_trials(serial_spectra)
    pd.testing.assert_frame_equal(fits.to_frame(), ref.to_frame())
    assert [t.fit.params for t in fits.fits] == [t.fit.params for t in ref.fits]


def test_diagnose_on_dask_is_the_same(serial_spectra, executor):
    """The diagnosis's screening and joint fits on the cluster: the same verdicts,
    steps and errors as in this process."""
    grip = armfit.fit_grip(serial_spectra)
    on_dask = armfit.diagnose(serial_spectra, grip, executor=executor).to_dict()
    here = armfit.diagnose(serial_spectra, grip).to_dict()
    assert on_dask == here


def test_wu_fits_on_dask_are_the_same(executor):
    """The axes' Wu fits (fit_weights hands them to the executor, an axis a task) run in
    the workers' threads: each equals fit_wu here, as on armfit's own pools. Table
    III's weights are the targets: fitted with BLAS's threaded kernels, order 4 of the
    X weight reaches another local minimum (armfit.uncertainty._one_blas_thread). A
    dask worker started by its nanny (``dask worker``, a LocalCluster of processes) has
    one BLAS thread from its environment (dask's ``distributed.nanny.pre-spawn-environ``),
    whatever the thread that runs the task sets."""
    from importlib import resources

    import numpy as np

    from armfit import uncertainty as U
    with resources.as_file(resources.files("armfit.data")
                           .joinpath("table3_uncertainty_weights.csv")) as path:
        table3 = U.read_wu(path)
    f = np.logspace(-2, np.log10(30.0), 140)
    targets = [np.abs(table3[a].response(f)) for a in ("x", "y", "z")]
    tasks = [(f, w, {"cost": "envelope", "band": (0.01, 30.0)}) for w in targets]
    got = U._fit_wu_axes(tasks, 2, executor)
    for a, w in zip(got, targets, strict=True):
        b = U.fit_wu(f, w, band=(0.01, 30.0))
        assert (a.order, a.orders_tried, a.gain) == (b.order, b.orders_tried, b.gain)
        assert np.array_equal(a.zeros, b.zeros) and np.array_equal(a.poles, b.poles)


def test_run_on_dask_writes_the_same_files(small_study, executor, tmp_path):
    """Every stage's tasks on the cluster (the diagnosis in this process, jobs=1):
    every file the same bytes as the run in this process (two folders of one name: the
    report's command line names the output folder as given)."""
    local = armfit.run(small_study, tmp_path / "local" / "out", figures=False)
    remote = armfit.run(small_study, tmp_path / "dask" / "out", figures=False,
                        executor=executor)
    assert remote.files == local.files

    def content(where, f):
        return (tmp_path / where / "out" / f).read_bytes().replace(
            str(tmp_path / where).encode(), b"PARENT")
    assert [f for f in local.files if content("local", f) != content("dask", f)] == []


def test_cli_scheduler_option(small_study, cluster, tmp_path):
    out_local, out_dask = tmp_path / "local.parquet", tmp_path / "dask.parquet"
    runner = CliRunner()
    res = runner.invoke(cli, ["estimate", str(small_study), "-o", str(out_local)])
    assert res.exit_code == 0, res.output
    res = runner.invoke(cli, ["estimate", str(small_study), "-o", str(out_dask),
                              "--scheduler", cluster.scheduler_address])
    assert res.exit_code == 0, res.output
    assert out_dask.read_bytes() == out_local.read_bytes()
