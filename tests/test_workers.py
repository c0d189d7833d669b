"""Executors passed in and pools of armfit's own (armfit.workers).

An executor given is used as it is and never shut down by armfit; a pool armfit makes is
shut down by armfit; the results are the same whatever runs the tasks (compared with the
same call run in this process, jobs=1).
"""

from __future__ import annotations

import multiprocessing as mp
import sys
import threading
import time
from concurrent.futures import ProcessPoolExecutor, ThreadPoolExecutor
from pathlib import Path

import click
import numpy as np
import pandas as pd
import pytest
from click.testing import CliRunner

import armfit
from armfit import workers


def _square(x: int) -> int:
    return x * x


def test_start_method_is_the_fork_server_where_python_offers_it():
    # the rule of armfit.workers: forkserver except on macOS, else spawn
    expected = ("forkserver" if sys.platform != "darwin"
                and "forkserver" in mp.get_all_start_methods() else "spawn")
    assert workers.start_method() == expected


def test_an_executor_given_is_used_and_not_shut_down():
    with ThreadPoolExecutor(max_workers=2) as given:
        with workers.executor_for(given, jobs=8) as ex:
            assert ex is given
        # still open after the block: armfit never shuts down the caller's executor
        assert workers.map_tasks(_square, [1, 2, 3], executor=given) == [1, 4, 9]
        assert given.submit(_square, 4).result() == 16


def test_a_pool_of_its_own_is_shut_down_at_the_end_of_the_block():
    with workers.executor_for(jobs=2) as pool:
        assert isinstance(pool, ProcessPoolExecutor)
        assert list(pool.map(_square, range(4))) == [0, 1, 4, 9]
    with pytest.raises(RuntimeError, match="after shutdown"):
        pool.submit(_square, 2)


def test_one_worker_or_one_task_runs_here():
    with workers.executor_for(jobs=1) as ex:
        assert ex is None
    with workers.executor_for(jobs=4, tasks=1) as ex:
        assert ex is None
    assert workers.map_tasks(_square, [3], jobs=4) == [9]


def test_a_pool_starts_all_its_workers_at_its_first_task():
    before = set(mp.active_children())
    pool = workers.process_pool(2)
    try:
        assert set(mp.active_children()) == before   # nothing started yet
        assert pool.submit(_square, 5).result() == 25
        started = set(mp.active_children()) - before
        assert len(started) == 2                     # both workers, not one per task
    finally:
        pool.shutdown()
    assert set(mp.active_children()) - before == set()


def test_start_workers_starts_a_pools_workers_in_a_thread_once():
    # a pool of armfit's own whose workers have not started: a thread starts them all
    # while the caller goes on; once it ends they are up (no task run). A started pool,
    # another executor, or None: no thread
    before = set(mp.active_children())
    pool = workers.process_pool(2)
    other = ThreadPoolExecutor(1)
    try:
        thread = workers.start_workers(pool)
        assert isinstance(thread, threading.Thread)
        thread.join(timeout=60)
        assert not thread.is_alive() and pool.started
        assert len(set(mp.active_children()) - before) == 2
        assert workers.start_workers(pool) is None
        assert workers.start_workers(other) is None and workers.start_workers(None) is None
        assert pool.submit(_square, 7).result() == 49
        assert len(set(mp.active_children()) - before) == 2     # the same two workers
    finally:
        pool.shutdown()
        other.shutdown()
    assert set(mp.active_children()) - before == set()


@pytest.mark.parametrize("idle_after", ["first", "every"])
def test_a_pool_starts_all_its_workers_when_the_first_is_idle_before_the_next_task(
        monkeypatch, idle_after):
    # seen on a loaded machine: the first worker had done its start task before the next
    # was sent, took that one too, and the pool started with one worker. Here the first
    # start task ("first"), or every one ("every": the one worker wins every race, also
    # seen once on a loaded machine), is done and its worker idle before the next is sent
    from concurrent.futures import ProcessPoolExecutor
    submit = ProcessPoolExecutor.submit
    sent = []

    def first_done(self, fn, *args, **kwargs):
        fut = submit(self, fn, *args, **kwargs)
        sent.append(fn)
        if sent == [workers._ready] or (idle_after == "every" and fn is workers._ready):
            fut.result()
            deadline = time.monotonic() + 10
            while not self._idle_worker_semaphore._value and time.monotonic() < deadline:
                time.sleep(0.005)       # the pool's thread marks the worker idle
        return fut

    monkeypatch.setattr(ProcessPoolExecutor, "submit", first_done)
    before = set(mp.active_children())
    pool = workers.process_pool(2)
    try:
        assert pool.submit(_square, 6).result() == 36
        assert len(set(mp.active_children()) - before) == 2
    finally:
        pool.shutdown()


def test_cancel_pools_stops_the_pools_a_thread_made():
    made = {}

    def in_thread():
        made["pool"] = workers.process_pool(2)
        made["ident"] = threading.get_ident()

    t = threading.Thread(target=in_thread)
    t.start()
    t.join()
    other = workers.process_pool(2)          # made here: not touched
    try:
        workers.cancel_pools(made["ident"])
        with pytest.raises(RuntimeError, match="after shutdown"):
            made["pool"].submit(_square, 2)
        assert other.submit(_square, 3).result() == 9
    finally:
        other.shutdown()


def test_estimate_on_a_process_pool_of_the_callers_is_the_same(small_study, serial_spectra):
    with ProcessPoolExecutor(max_workers=2) as pool:
        spectra = armfit.estimate(small_study, executor=pool)
        assert pool.submit(_square, 6).result() == 36   # still usable: not shut down
    pd.testing.assert_frame_equal(spectra.to_frame(), serial_spectra.to_frame())


def test_fits_on_a_thread_pool_are_the_same(serial_spectra):
    """fit_grip, fit_trials and fit_uncertainty with an executor given give the frames
    of the same calls run here (jobs=1)."""
    with ThreadPoolExecutor(max_workers=2) as pool:
        grip = armfit.fit_grip(serial_spectra, executor=pool)
        trials = armfit.fit_trials(serial_spectra, executor=pool)
        nominal = armfit.fit_nominal(serial_spectra, executor=pool)
        unc = armfit.fit_uncertainty(serial_spectra, nominal, executor=pool)
    pd.testing.assert_frame_equal(grip.to_frame(), armfit.fit_grip(serial_spectra).to_frame())
    pd.testing.assert_frame_equal(trials.to_frame(),
                                  armfit.fit_trials(serial_spectra).to_frame())
    ref = armfit.fit_uncertainty(serial_spectra, armfit.fit_nominal(serial_spectra))
    pd.testing.assert_frame_equal(unc.to_frame(), ref.to_frame())
    for a, b in zip(unc.axes, ref.axes, strict=True):
        assert np.array_equal(a.wmax_raw, b.wmax_raw, equal_nan=True)


def test_scheduler_without_dask_is_one_line_and_exit_2(small_study, tmp_path, monkeypatch):
    """`--scheduler` needs the optional extra; without it: the documented usage exit (2)
    and one line saying what to install, no traceback."""
    from click.testing import CliRunner

    from armfit.cli.main import cli
    monkeypatch.setitem(sys.modules, "distributed", None)   # `import distributed` fails
    res = CliRunner().invoke(cli, ["estimate", str(small_study), "-o",
                                   str(tmp_path / "s.parquet"), "--scheduler",
                                   "tcp://127.0.0.1:8786"])
    assert res.exit_code == 2
    assert res.stderr == ("armfit: error: --scheduler needs dask.distributed: "
                          "pip install armfit[dask]\n")
    assert not (tmp_path / "s.parquet").exists()


def test_every_preloaded_module_exists():
    """The fork server imports its preload list and silently skips a name it cannot
    import (multiprocessing.forkserver), so a stale name would only cost each pool's
    workers an import: every name of workers.PRELOAD, and of every ``preload=`` tuple
    the package passes to a pool, must be an importable module."""
    import ast
    import importlib.util
    names = set(workers.PRELOAD).union(workers.RUN_FIGURES_PRELOAD,
                                        *workers.POOL_PRELOAD.values())

    def literal(value) -> set[str]:
        if isinstance(value, ast.Name | ast.Subscript):  # a name, POOL_PRELOAD[k]
            return set()
        if isinstance(value, ast.IfExp):                 # A if figures else B
            return literal(value.body) | literal(value.orelse)
        return set(ast.literal_eval(value))

    for path in Path(workers.__file__).parent.rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.keyword) and node.arg == "preload":
                names |= literal(node.value)
            if (isinstance(node, ast.Assign) and len(node.targets) == 1
                    and isinstance(node.targets[0], ast.Name)
                    and node.targets[0].id == "preload"):
                names |= literal(node.value)
    assert {"armfit.spectra", "armfit.fitting", "armfit.uncertainty"} <= names
    assert sorted(m for m in names if importlib.util.find_spec(m) is None) == []


def test_each_pool_preloads_the_module_of_its_tasks():
    """A worker unpickles its task's function by importing the function's module; the
    pool's preload must name that module, not a package whose ``__init__`` imports none
    of it (``armfit.diagnosis`` loads its modules on first use): else each worker of the
    diagnosis imported its search, about half a second, at its first task. The modules
    of the engine's task functions are in :data:`workers.PRELOAD` (``run``'s pool, and
    the fork server of an API script), and each pool's own preload names its own."""
    import inspect

    from armfit import fitting, spectra, uncertainty
    from armfit.diagnosis import driver, schedule, search
    assert inspect.signature(schedule.task_queue).parameters["preload"].default == \
        workers.POOL_PRELOAD["diagnosis"]
    tasks = {"diagnosis": (driver._base_task, search._screen_task, search._extend_task,
                           search._subject_task),
             "estimate": (spectra._estimate_source,),
             "fit": (fitting._fit_group, fitting._fit_trial_task),
             "uncertainty": (uncertainty._order_task,)}
    assert set(tasks) == set(workers.POOL_PRELOAD)
    for kind, fns in tasks.items():
        for fn in fns:
            assert fn.__module__ in workers.POOL_PRELOAD[kind], (kind, fn)
            assert fn.__module__ in workers.PRELOAD, fn


#: The start of the scripts below, each run in a fresh process (:func:`_script_json`):
#: ``loaded(names)`` is run in a worker, to see what it holds at its first task.
_SCRIPT_HEAD = """
import json, sys
from armfit import workers

def loaded(names):
    return [n for n in names if n in sys.modules]
"""


def _script_json(tmp_path: Path, text: str, *args: str):
    """Run the script ``text`` in a fresh Python process: what it printed, as JSON (its
    stderr must be empty)."""
    import json
    import subprocess
    script = tmp_path / "script.py"
    script.write_text(_SCRIPT_HEAD + text)
    res = subprocess.run([sys.executable, str(script), *args], capture_output=True,
                         text=True, check=True, timeout=120)
    assert res.stderr == ""
    return json.loads(res.stdout)


_FIRST_TASK = """
if __name__ == "__main__":
    if sys.argv[1] == "own":
        workers.preload_own_only()
    names = ["armfit.spectra", "armfit.fitting", "armfit.diagnosis.search", "scipy.special",
             "scipy.optimize", "armfit._server_exit"]
    pool = workers.process_pool(2, ("armfit.spectra",))
    try:
        print(json.dumps(pool.submit(loaded, names).result()))
    finally:
        pool.shutdown()
"""


@pytest.mark.skipif(workers.start_method() != "forkserver", reason="the fork server's")
def test_a_command_process_preloads_only_what_its_pool_runs(tmp_path):
    # the modules a worker holds at its first task, in a fresh process whose first pool
    # preloads armfit.spectra: by default every engine module too (any later pool of a
    # script starts loaded); after preload_own_only(), as the command line sets it, only
    # what that pool named (estimate's workers then start about 1 s sooner). No pool
    # needs scipy.optimize (the Wu fits' solvers are armfit._trf and armfit._slsqp) or
    # scipy.special (the intervals' t quantiles are armfit._student's)
    def worker_modules(mode: str) -> list[str]:
        return _script_json(tmp_path, _FIRST_TASK, mode)

    assert worker_modules("all") == ["armfit.spectra", "armfit.fitting",
                                     "armfit.diagnosis.search", "armfit._server_exit"]
    assert worker_modules("own") == ["armfit.spectra", "armfit._server_exit"]


def _here_and_in_a_worker(tmp_path: Path, probe: str, mode: str, setter: str):
    """``probe()`` (the source of a module-level function of that name) in a fresh
    Python process and in a worker of its first pool, as JSON {"here": ..., "worker":
    ...}; with ``mode`` "entry" the process first calls ``workers.<setter>()``, as the
    console entry point does before numpy and pyarrow load."""
    text = probe + f"""
if __name__ == "__main__":
    if sys.argv[1] == "entry":
        workers.{setter}()
    here = probe()
    pool = workers.process_pool(2, ())
    try:
        print(json.dumps({{"here": here, "worker": pool.submit(probe).result()}}))
    finally:
        pool.shutdown()
"""
    return _script_json(tmp_path, text, mode)


def _plain_process(probe: str):
    """``probe()`` in a plain Python process (no armfit), as JSON."""
    import json
    import subprocess
    res = subprocess.run([sys.executable, "-c", f"import json\n{probe}\n"
                          "print(json.dumps(probe()))"],
                         capture_output=True, text=True, check=True)
    return json.loads(res.stdout)


_BLAS_THREADS = """
def probe():
    import numpy  # noqa: F401  (its BLAS loaded)
    from threadpoolctl import threadpool_info
    return sorted({i["num_threads"] for i in threadpool_info() if i["user_api"] == "blas"})
"""


@pytest.mark.parametrize("environment, mode, here, worker", [
    ({}, "script", None, [1]),           # a script's own BLAS as BLAS sets it
    ({}, "entry", [1], [1]),             # the command line's process
    ({"OPENBLAS_NUM_THREADS": "2"}, "entry", [2], [2]),   # the user's setting stands
])
def test_blas_runs_on_one_thread_in_workers_and_the_command_line(tmp_path, monkeypatch,
                                                                 environment, mode, here,
                                                                 worker):
    # threadpoolctl's report of the BLAS libraries loaded (numpy's and scipy's OpenBLAS)
    # in the process and in a worker of its pool: one thread each (their threads cost
    # more than they save on armfit's small problems), unless the environment says
    for name in workers.BLAS_ONE_THREAD:
        monkeypatch.delenv(name, raising=False)
    for name, value in environment.items():
        monkeypatch.setenv(name, value)
    got = _here_and_in_a_worker(tmp_path, _BLAS_THREADS, mode, "one_blas_thread")
    assert got["worker"] == worker
    # None: as in a plain Python process (BLAS's own default)
    assert got["here"] == (_plain_process(_BLAS_THREADS) if here is None else here)


_ARROW_POOL = """
def probe():
    import pyarrow
    return pyarrow.default_memory_pool().backend_name
"""


@pytest.mark.parametrize("environment, mode, here, worker", [
    ({}, "script", None, "system"),      # a script's own pool as pyarrow chooses it
    ({}, "entry", "system", "system"),   # the command line's process
    ({"ARROW_DEFAULT_MEMORY_POOL": "mimalloc"}, "entry", "mimalloc", "mimalloc"),
])
def test_arrow_allocates_from_the_c_library_in_workers_and_the_command_line(
        tmp_path, monkeypatch, environment, mode, here, worker):
    # pyarrow's own report of the pool its buffers come from: the C library's ("system",
    # whose freed memory armfit.memory.release_memory gives back), in the command line's
    # process and in a worker of any pool, unless the environment names one
    monkeypatch.delenv("ARROW_DEFAULT_MEMORY_POOL", raising=False)
    for name, value in environment.items():
        monkeypatch.setenv(name, value)
    got = _here_and_in_a_worker(tmp_path, _ARROW_POOL, mode, "system_arrow_pool")
    assert got["worker"] == worker
    # None: as in a plain Python process (pyarrow's own default)
    assert got["here"] == (_plain_process(_ARROW_POOL) if here is None else here)


def test_the_server_exit_module_acts_only_in_the_fork_servers_preload(tmp_path):
    # imported anywhere else it registers nothing: the process's own exit status stands
    import subprocess
    res = subprocess.run([sys.executable, "-c", "import sys, armfit._server_exit; "
                          "sys.stdout.write('kept'); sys.exit(3)"],
                         capture_output=True, text=True, timeout=60)
    assert (res.returncode, res.stdout) == (3, "kept")
    # imported from a function ``main`` of multiprocessing/forkserver.py (as the server's
    # preload imports it), the process then ends at its exit at once, with the status 0
    # the server's own exit (SystemExit) has, after its buffered output is written
    fake = tmp_path / "multiprocessing"
    fake.mkdir()
    (fake / "forkserver.py").write_text("def main():\n    import armfit._server_exit\n")
    path = str(fake / "forkserver.py")
    script = ("import importlib.util, sys\n"
              f"spec = importlib.util.spec_from_file_location('fake_fs', {path!r})\n"
              "mod = importlib.util.module_from_spec(spec)\n"
              "spec.loader.exec_module(mod)\n"
              "mod.main()\n"
              "sys.stdout.write('flushed')\n"
              "sys.exit(3)\n")
    res = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                         timeout=60)
    assert (res.returncode, res.stdout) == (0, "flushed")


@pytest.mark.parametrize("args, jobs", [
    # click's spellings of a valued option (its own parsing is the reference)
    (["in.parquet", "-o", "out.parquet", "-j", "2"], 2),
    (["in.parquet", "-j2"], 2),
    (["--jobs", "3", "in.parquet"], 3),
    (["--jobs=4", "in.parquet"], 4),
    (["-j", "2", "in.parquet", "--jobs", "1"], 1),      # the last one wins, as in click
    (["in.parquet"], None),
    (["in.parquet", "-j"], None),                       # the command reports the error
    (["in.parquet", "-j", "two"], None),
    (["--", "-j", "2"], None),                          # after "--": an argument
])
def test_requested_jobs_reads_the_option_as_click_does(args, jobs):
    from armfit.cli.main import requested_jobs, wants_workers
    assert requested_jobs(args) == jobs
    assert wants_workers(args) == (jobs is not None and jobs > 1)
    # a dask cluster's workers, or only the help: no worker process here
    assert not wants_workers([*args, "--scheduler", "tcp://127.0.0.1:8786"])
    assert not wants_workers([*args, "--scheduler=tcp://127.0.0.1:8786"])
    assert not wants_workers(["--help", *args])


def test_the_commands_with_jobs_start_their_fork_server_first(monkeypatch, tmp_path):
    # every command with --jobs is listed with its pool's preload, and none other; asked
    # for two workers it starts the fork server before its own modules are loaded (here
    # on a missing input: the command then fails, the server just ends with it)
    from armfit.cli import main
    for name in main.COMMANDS:
        cmd = main.cli.get_command(click.Context(main.cli), name)
        has_jobs = any(p.name == "jobs" for p in getattr(cmd, "params", ()))
        assert has_jobs == (name in main.POOLS), name
    started = []
    monkeypatch.setattr(main, "start_fork_server", started.append)
    missing = str(tmp_path / "missing.parquet")
    cases = [(["diagnose", missing, "--model", missing, "-j", "2"],
              [workers.POOL_PRELOAD["diagnosis"]]),
             (["estimate", missing, "-o", str(tmp_path / "s.parquet"), "--jobs=2"],
              [workers.POOL_PRELOAD["estimate"]]),
             (["run", missing, "-o", str(tmp_path / "out"), "-j", "2"],
              [workers.RUN_FIGURES_PRELOAD]),
             (["run", missing, "-o", str(tmp_path / "out"), "-j", "2", "--no-figures"],
              [()]),
             (["estimate", missing, "-o", str(tmp_path / "s.parquet")], []),
             (["estimate", missing, "-o", str(tmp_path / "s.parquet"), "-j", "1"], []),
             (["estimate", "-j", "2", "--help"], []),
             (["compare", missing, "--model", missing, "-j", "2"], [])]
    for args, expected in cases:
        started.clear()
        CliRunner().invoke(main.cli, ["-q", *args])
        assert started == expected, args


@pytest.mark.parametrize("name, args, figures", [
    ("run", ["study", "-o", "out", "-j", "2"], True),
    ("run", ["study", "--no-figures", "-o", "out", "-j", "2"], False),
    ("run", ["study", "-o", "out", "--", "--no-figures"], True),  # an argument after "--"
    ("estimate", ["study", "-o", "s.parquet", "-j", "2", "--no-figures"], False),
])
def test_a_run_that_draws_figures_preloads_the_figures_module(name, args, figures):
    # run's workers draw the figures: its fork server imports armfit.figures (matplotlib)
    # once, beside every engine module; any other pool keeps its own preload
    from armfit.cli.main import pool_preload
    own = ("armfit.spectra",)
    assert pool_preload(name, args, own) == (workers.RUN_FIGURES_PRELOAD if figures
                                             else own)
    assert workers.RUN_FIGURES_PRELOAD == (*workers.PRELOAD, "armfit.figures")


@pytest.mark.parametrize("figures", [True, False])
def test_the_runs_own_pool_preloads_the_figures_module_when_it_draws(figures, tmp_path,
                                                                    monkeypatch):
    # armfit.run's pool (an API call: no command line started a fork server first) names
    # the figures' module in its preload exactly when the run draws figures
    import contextlib

    from armfit import pipeline
    from armfit.errors import ArmfitError
    asked = []

    @contextlib.contextmanager
    def recorder(executor=None, jobs=1, *, tasks=None, preload=()):
        asked.append((jobs, tuple(preload)))
        yield None                                   # the stages then run here, in turn

    monkeypatch.setattr(pipeline, "executor_for", recorder)
    with pytest.raises(ArmfitError):                 # no such input: the ingest stops it
        armfit.run(tmp_path / "missing", tmp_path / "out", jobs=2, figures=figures)
    assert asked == [(2, workers.RUN_FIGURES_PRELOAD if figures else ())]


_EARLY_SERVER = """
def server_blocks_sigint():
    # the fork server: this process's child running multiprocessing.forkserver's main
    import os
    for pid in filter(str.isdigit, os.listdir("/proc")):
        try:
            status = open(f"/proc/{pid}/status").read()
            cmdline = open(f"/proc/{pid}/cmdline").read()
        except OSError:
            continue
        if f"PPid:\\t{os.getpid()}\\n" in status and "forkserver" in cmdline:
            blocked = [ln for ln in status.splitlines() if ln.startswith("SigBlk:")][0]
            return bool(int(blocked.split()[1], 16) & (1 << 1))   # SIGINT is signal 2

if __name__ == "__main__":
    workers.preload_own_only()
    workers.start_fork_server(("armfit.spectra",))
    blocked = server_blocks_sigint()
    pool = workers.process_pool(2, ("armfit.fitting",))
    try:
        print(json.dumps([blocked,
                          pool.submit(loaded, ["armfit.spectra", "armfit.fitting"]).result()]))
    finally:
        pool.shutdown()
"""


@pytest.mark.skipif(workers.start_method() != "forkserver" or not Path("/proc/self").exists(),
                    reason="the fork server's, seen in /proc")
def test_a_fork_server_started_early_serves_the_first_pool(tmp_path):
    # the server starts with SIGINT blocked, as a pool starts it (Ctrl-C reaches the
    # whole process group; a server stopped in its imports would print a traceback), and
    # the workers of the pool made afterwards are forked from it: they hold what it
    # imported, not what the pool itself would have preloaded
    assert _script_json(tmp_path, _EARLY_SERVER) == [True, ["armfit.spectra"]]


_SHORT_FOLDER = """
if __name__ == "__main__":
    import os, tempfile
    from multiprocessing import process
    first = workers.prepare_pool_folder()
    again = workers.prepare_pool_folder()           # made once
    print(json.dumps([first, again, process.current_process()._config.get("tempdir"),
                      len(os.fsencode(tempfile.gettempdir()))]))
"""


@pytest.mark.parametrize("depth", [0, 6])
def test_the_pools_folder_is_made_short_enough_for_the_servers_socket(depth, tmp_path):
    # with TMPDIR short enough, multiprocessing makes its folder there itself; with one
    # too long for a socket's path (+33 characters), armfit makes it in a short system
    # folder, once
    import os
    import subprocess
    tmpdir = tmp_path.joinpath(*["d" * 20] * depth)
    tmpdir.mkdir(parents=True, exist_ok=True)
    script = tmp_path / "script.py"
    script.write_text(_SCRIPT_HEAD + _SHORT_FOLDER)
    res = subprocess.run([sys.executable, str(script)], capture_output=True, text=True,
                         env={**os.environ, "TMPDIR": str(tmpdir)}, timeout=60, check=True)
    import json
    first, again, folder, base = json.loads(res.stdout)
    assert again is None
    if base + 33 <= workers.SOCKET_PATH_MAX:
        assert first is None and folder is None
    else:
        assert first == folder
        assert Path(folder).parent.as_posix() in workers.SHORT_TEMP_FOLDERS
        assert len(os.fsencode(folder)) + 18 <= workers.SOCKET_PATH_MAX   # /listener-XXXXXXXX
        assert not Path(folder).exists()                  # removed as the process ended
    assert depth == 0 or base + 33 > workers.SOCKET_PATH_MAX


def test_two_threads_shutting_a_pool_down_together_take_turns(monkeypatch):
    """The thread that made a pool and cancel_pools (a failing run stopping a background
    stage) may shut the pool down at once; ProcessPoolExecutor.shutdown run twice at the
    same time closes its result queue twice (OSError EBADF, seen in a failing run). The
    calls take turns: never two inside ProcessPoolExecutor.shutdown together, no error."""
    inside, most, lock = [0], [0], threading.Lock()
    real = ProcessPoolExecutor.shutdown

    def counted(self, *args, **kwargs):
        with lock:
            inside[0] += 1
            most[0] = max(most[0], inside[0])
        try:
            threading.Event().wait(0.3)   # widen the window in which a second call enters
            return real(self, *args, **kwargs)
        finally:
            with lock:
                inside[0] -= 1

    monkeypatch.setattr(ProcessPoolExecutor, "shutdown", counted)
    pool = workers.process_pool(1)
    assert pool.submit(abs, -3).result() == 3
    errors = []

    def stop():
        try:
            pool.shutdown(wait=True, cancel_futures=True)
        except BaseException as exc:  # noqa: BLE001 - the test reports it
            errors.append(exc)

    threads = [threading.Thread(target=stop) for _ in range(2)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(60)
    assert errors == [] and most[0] == 1


# ---------------------------------------------------------------------------
# read_ahead: the next item computed in a thread while the caller works on this one
# ---------------------------------------------------------------------------


def _read_threads() -> list[str]:
    return [t.name for t in threading.enumerate() if t.name.startswith("armfit-read")]


def test_read_ahead_computes_the_next_item_while_the_caller_holds_this_one():
    started = {i: threading.Event() for i in range(3)}
    names = {}

    def fn(i):
        names[i] = threading.current_thread().name
        started[i].set()
        return i * 10

    it = workers.read_ahead(fn, [0, 1, 2])
    assert next(it) == 0
    # item 1 is computed without the caller asking for it: a plain map would wait
    assert started[1].wait(10.0)
    assert not started[2].is_set()          # never more than one item ahead
    assert list(it) == [10, 20]
    assert all(n.startswith("armfit-read") for n in names.values())
    assert _read_threads() == []


def test_read_ahead_raises_an_items_error_in_its_turn_and_leaves_no_thread():
    def fn(i):
        if i == 2:
            raise ValueError(f"item {i} is bad")
        return i

    got = []
    with pytest.raises(ValueError, match="item 2 is bad"):
        for v in workers.read_ahead(fn, [0, 1, 2, 3]):
            got.append(v)
    assert got == [0, 1]                    # the items before the bad one, in order
    assert _read_threads() == []


def test_read_ahead_closed_early_waits_for_the_call_under_way():
    started, release = threading.Event(), threading.Event()
    finished = []

    def fn(i):
        if i == 1:
            started.set()
            release.wait(10.0)
        finished.append(i)
        return i

    it = workers.read_ahead(fn, [0, 1, 2])
    assert next(it) == 0
    # the call for item 1 is under way (on a busy machine the reading thread may not
    # have begun it when next() returns: closing then starts nothing, rightly)
    assert started.wait(10.0)
    threading.Timer(0.2, release.set).start()
    it.close()                              # returns once the call for item 1 has ended
    assert finished == [0, 1]               # item 2 was never started
    assert _read_threads() == []


def test_read_ahead_of_one_item_runs_here():
    here = threading.current_thread().name
    assert list(workers.read_ahead(lambda i: (i, threading.current_thread().name), [7])) == [
        (7, here)]
    assert list(workers.read_ahead(_square, [])) == []


# ---------------------------------------------------------------------------
# giving_way: tasks that wait while the pool's other tasks run first
# ---------------------------------------------------------------------------


def _logged(args) -> str:
    """Worker: wait until the file ``gate`` exists (if given), then append ``name`` to
    ``log`` (the order the tasks ran in, one worker running them one at a time)."""
    import os
    import time
    log, name, gate = args
    while gate is not None and not os.path.exists(gate):
        time.sleep(0.01)
    with open(log, "a") as f:
        f.write(name + "\n")
    return name


def _ran(log: Path) -> list[str]:
    return log.read_text().split()


def _wait_until(cond, timeout: float = 30.0) -> bool:
    import time
    deadline = time.monotonic() + timeout
    while not cond():
        if time.monotonic() > deadline:
            return False
        time.sleep(0.01)
    return True


@pytest.fixture
def one_busy_worker(tmp_path):
    """A pool of one worker busy with a task that logs "busy" once the file ``gate``
    exists; its tasks that give way; the log. Shut down at the end (again, if the test
    did)."""
    from types import SimpleNamespace
    log, gate = tmp_path / "log", tmp_path / "gate"
    pool = workers.process_pool(1)
    busy = pool.submit(_logged, (log, "busy", gate))
    try:
        yield SimpleNamespace(pool=pool, later=workers.giving_way(pool), busy=busy,
                              log=log, gate=gate)
    finally:
        gate.touch()
        pool.shutdown()


def test_tasks_that_give_way_run_after_those_submitted_to_the_pool_later(one_busy_worker):
    # the rule of workers.giving_way: with the one worker busy, the tasks that give way
    # wait; a task submitted to the pool itself after them runs first, then they run in
    # the order they were submitted
    w = one_busy_worker
    a = w.later.submit(_logged, (w.log, "a", None))
    b = w.later.submit(_logged, (w.log, "b", None))
    now = w.pool.submit(_logged, (w.log, "now", None))
    assert not (a.running() or b.running())      # still in the pool's own queue
    w.gate.touch()
    assert [f.result(timeout=60) for f in (w.busy, a, b, now)] == ["busy", "a", "b", "now"]
    assert _ran(w.log) == ["busy", "now", "a", "b"]


def test_tasks_that_give_way_fill_idle_workers_at_once(tmp_path):
    # nothing else to run: both workers take a task that gives way, without waiting for
    # anything (the second task's gate opens only when the first has started)
    log = tmp_path / "log"
    pool = workers.process_pool(2)
    later = workers.giving_way(pool)
    try:
        first = later.submit(_logged, (log, "first", tmp_path / "second-started"))
        second = later.submit(_logged, (log, "second", None))
        assert second.result(timeout=60) == "second"
        (tmp_path / "second-started").touch()
        assert first.result(timeout=60) == "first"
    finally:
        pool.shutdown()
    assert _ran(log) == ["second", "first"]


@pytest.mark.parametrize("chunksize", [1, 3])
def test_map_of_tasks_that_give_way_is_map(chunksize):
    # the values of the builtin map, in order, whatever the chunks
    pool = workers.process_pool(2)
    try:
        later = workers.giving_way(pool)
        assert list(later.map(_square, range(10), chunksize=chunksize)) == [
            x * x for x in range(10)]
        assert workers.map_tasks(_square, range(7), chunksize=chunksize,
                                 executor=later) == [x * x for x in range(7)]
        with pytest.raises(ValueError, match="chunksize"):
            later.map(_square, range(3), chunksize=0)
    finally:
        pool.shutdown()


def test_a_task_that_gives_way_raises_its_error_in_the_caller():
    pool = workers.process_pool(1)
    try:
        fut = workers.giving_way(pool).submit(int, "not a number")
        with pytest.raises(ValueError, match="not a number"):
            fut.result(timeout=60)
    finally:
        pool.shutdown()


def test_a_pool_shut_down_runs_the_tasks_still_waiting(one_busy_worker):
    # shutdown without cancel_futures hands the waiting task to the workers while the
    # busy one still runs (the waiting task shows as running before the gate opens)
    w = one_busy_worker
    waiting = w.later.submit(_logged, (w.log, "waiting", None))
    stopper = threading.Thread(target=w.pool.shutdown)
    stopper.start()
    assert _wait_until(waiting.running)
    w.gate.touch()
    stopper.join(60)
    assert w.busy.result() == "busy" and waiting.result() == "waiting"
    assert _ran(w.log) == ["busy", "waiting"]
    with pytest.raises(RuntimeError, match="after shutdown"):
        w.later.submit(_square, 2)


def test_a_pool_shut_down_with_cancel_futures_cancels_the_tasks_still_waiting(
        one_busy_worker):
    w = one_busy_worker
    waiting = w.later.submit(_logged, (w.log, "waiting", None))
    assert _wait_until(w.busy.running)  # handed to the worker (else shutdown cancels it)
    threading.Timer(0.5, w.gate.touch).start()
    w.pool.shutdown(wait=True, cancel_futures=True)
    assert w.busy.result() == "busy" and waiting.cancelled()
    assert _ran(w.log) == ["busy"]


def test_a_task_that_gives_way_cancelled_while_waiting_never_runs(one_busy_worker):
    w = one_busy_worker
    dropped = w.later.submit(_logged, (w.log, "dropped", None))
    kept = w.later.submit(_logged, (w.log, "kept", None))
    assert dropped.cancel()
    w.gate.touch()
    assert w.busy.result(timeout=60) == "busy" and kept.result(timeout=60) == "kept"
    assert _ran(w.log) == ["busy", "kept"]


def test_giving_way_leaves_other_executors_as_they_are():
    assert workers.giving_way(None) is None
    with ThreadPoolExecutor(max_workers=1) as given:
        assert workers.giving_way(given) is given


def _nbytes(a: np.ndarray) -> int:
    return a.nbytes


def test_a_pool_lets_go_of_the_last_task_it_sent():
    # the thread that sends a pool's tasks (the feeder of its multiprocessing.Queue)
    # keeps the pickled bytes of the last task it sent until it sends another: here 8 MiB
    # of a task whose result has come back, traced in this process (tracemalloc sees
    # every thread's allocations). workers.let_go_sent sends an empty task; once it has
    # run, the bytes are freed
    import tracemalloc
    payload = np.ones(1 << 20)
    pool = workers.process_pool(1)
    try:
        assert pool.submit(int).result(timeout=60) == 0    # started, before the trace
        tracemalloc.start()
        try:
            assert pool.submit(_nbytes, payload).result(timeout=60) == payload.nbytes
            held = tracemalloc.get_traced_memory()[0]
            empty = workers.let_go_sent(workers.giving_way(pool))  # the pool's own
            assert empty.result(timeout=60) is None
            after = tracemalloc.get_traced_memory()[0]
        finally:
            tracemalloc.stop()
    finally:
        pool.shutdown()
    assert held >= payload.nbytes
    assert after < payload.nbytes / 8
    # nothing to let go of: no pool of armfit's own, or one shut down
    assert workers.let_go_sent(None) is None and workers.let_go_sent(pool) is None
    with ThreadPoolExecutor(max_workers=1) as given:
        assert workers.let_go_sent(given) is None


def _connection_classes(_: int) -> list[str]:
    """In a worker: the classes of the pipe ends it holds (its pool's queues')."""
    import gc
    from multiprocessing.connection import Connection
    return sorted({type(o).__name__ for o in gc.get_objects() if isinstance(o, Connection)})


def _echo(a: np.ndarray) -> np.ndarray:
    return a


def test_a_pools_tasks_and_results_are_read_whole_and_come_through_unchanged():
    # the pool's reading ends are WholeReads: its result queue's here, its call queue's
    # in the workers (pickled to them as WholeReads); what goes through is what was sent,
    # below, at and above WHOLE_READ_BYTES
    from armfit._pool import WHOLE_READ_BYTES, WholeReads
    pool = workers.process_pool(2)
    try:
        assert type(pool._result_queue._reader) is WholeReads
        assert "WholeReads" in pool.submit(_connection_classes, 0).result(timeout=60)
        rng = np.random.default_rng(5)
        arrays = [rng.standard_normal(n) for n in
                  (3, WHOLE_READ_BYTES // 8 - 40, WHOLE_READ_BYTES // 8, 1 << 20)]
        for a, back in zip(arrays, pool.map(_echo, arrays), strict=True):
            assert back.tobytes() == a.tobytes()
    finally:
        pool.shutdown()


def test_a_message_read_whole_is_the_message_for_every_way_of_receiving_it():
    # recv, recv_bytes and recv_bytes_into (at an offset, into an array of 8-byte items)
    # give what was sent, a message of many pipe reads (1 MB through 64 KiB) as a short one
    from multiprocessing.connection import Pipe

    from armfit._pool import WholeReads, whole_reads
    reader, writer = Pipe(duplex=False)
    whole_reads(reader)
    assert type(reader) is WholeReads
    data = bytes(range(256)) * 4000
    obj = {"a": np.arange(200_000.0), "b": "x"}
    sender = threading.Thread(target=lambda: [writer.send_bytes(data), writer.send(obj),
                                              writer.send_bytes(data), writer.send_bytes(b"ab"),
                                              writer.close()])
    sender.start()
    try:
        assert reader.recv_bytes() == data
        got = reader.recv()
        assert got["b"] == "x" and got["a"].tobytes() == obj["a"].tobytes()
        into = np.zeros(len(data) // 8 + 2)
        assert reader.recv_bytes_into(into, 8) == len(data)
        assert into.tobytes()[8:8 + len(data)] == data and not into[0] and not into[-1]
        assert reader.recv_bytes() == b"ab"
        with pytest.raises(EOFError):
            reader.recv_bytes()
    finally:
        sender.join()
        reader.close()



_AFTER_TASK_MODULE = '''
import numpy as np
from armfit.memory import release_memory, release_memory_after_task


def double(args):
    """A task with an argument and a result of 8 MB that gives memory back at its end."""
    a, when = args
    try:
        return a * 2.0
    finally:
        (release_memory_after_task if when == "after" else release_memory)()


def anon_mb(_):
    with open("/proc/self/status") as fh:
        return next(int(l.split()[1]) for l in fh if l.startswith("RssAnon")) / 1024
'''

_AFTER_TASK_SCRIPT = """
import sys
import numpy as np
from armfit import workers
import after_task_tasks as t

if __name__ == "__main__":
    pool = workers.process_pool(1)
    try:
        before = pool.submit(t.anon_mb, 0).result()
        out = pool.submit(t.double, (np.ones(1_000_000), sys.argv[1])).result()
        assert out.shape == (1_000_000,) and out[0] == 2.0
        print(pool.submit(t.anon_mb, 0).result() - before)
    finally:
        pool.shutdown()
"""


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's malloc_trim")
def test_a_worker_gives_back_its_tasks_arguments_and_result_after_the_task(tmp_path):
    # a pool's worker (which keeps what it frees: tune_allocator) after one task of an
    # 8 MB array in and an 8 MB array out, in MB over its memory before: given back in
    # the task's own `finally`, what is freed after the task function returns stays
    # with the worker: the message received and the argument unpickled from it (freed
    # once the result is sent), the result and its pickled message, 4 x 8 MB (measured
    # 31 MB); given back after the task (release_memory_after_task), run before the
    # worker waits for its next task, they are gone (measured 0.0-0.2 MB). (The sizes
    # stay well below the C library's trim threshold, TRIM_THRESHOLD_BYTES, beyond which
    # it gives the top of its heap back by itself.)
    import os
    import subprocess
    (tmp_path / "after_task_tasks.py").write_text(_AFTER_TASK_MODULE)
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(
        [str(tmp_path), *filter(None, [os.environ.get("PYTHONPATH")])])}

    def held(when: str) -> float:
        res = subprocess.run([sys.executable, "-c", _AFTER_TASK_SCRIPT, when], env=env,
                             check=True, capture_output=True, text=True, cwd=tmp_path)
        return float(res.stdout.strip())

    inside, after = held("inside"), held("after")
    assert inside > 20 and after < 3, (inside, after)


def test_after_task_runs_nothing_outside_a_pools_worker():
    # in the calling process (a task run here, --jobs 1) nothing is deferred: the memory
    # is given back at once, and after_task says it did not take the function
    from armfit import _pool
    from armfit.memory import release_memory_after_task
    ran = []
    assert _pool.after_task(lambda: ran.append(1)) is False
    release_memory_after_task()
    assert ran == [] and _pool._AFTER_TASK == []
