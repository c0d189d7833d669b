"""The shortcuts of the diagnosis, the adopted model and the stability test give the same
results as the full computations they stand for.

Each test computes the same thing twice, once the short way armfit now takes and once
the long way (written out here as armfit did it before: every step of the search over all
axes at once, every start refined, every crossing solved), and asserts equality, bit for
bit where armfit promises the same bytes.

The study: armfit's own simulator, 2 subjects on X and Z, grips 1 and 2 N, 26 s trials,
with a 12 ms delay and a 20 Hz lag (the search takes two or three steps per axis, Z ends
at its step limit and tries the axes' common values).
"""

from __future__ import annotations

import contextlib
import heapq
import operator
import os
import textwrap
import threading
from concurrent.futures import ThreadPoolExecutor
from dataclasses import replace

import numpy as np
import pytest
from scipy import linalg

from armfit import api, workers
from armfit.adopt import adopt
from armfit.constants import PARAM_NAMES
from armfit.diagnosis import joint, schedule, search
from armfit.diagnosis.bands import band_columns, band_error
from armfit.diagnosis.evidence import adequacy
from armfit.diagnosis.fit import start_array
from armfit.diagnosis.responses import axis_data, cross_coupling, param_row
from armfit.diagnosis.schedule import TaskQueue
from armfit.diagnosis.screen import keep_screened, rank_screened, screen_candidate
from armfit.diagnosis.tuning import FTOL_VARIANCE, SHARED_EFFECTS
from armfit.errors import EffectDefinitionError
from armfit.fitting import fit_response
from armfit.loop import (
    WallSettings,
    _by_intervals,
    _crossing_gains_batch,
    _crossings,
    _first_unstable,
    _g_of,
    _interval_gains,
    _loops,
    _pencils,
    _spectral_radius,
    plant_from_model,
    wall_stability,
)
from armfit.models.arm import ClosedLoopModel
from armfit.models.effects import EFFECTS
from armfit.simulation import EffectSetting


@pytest.fixture(scope="module")
def study():
    effects = (EffectSetting.from_parsed("delay", {"delay_s": 0.012}),
               EffectSetting.from_parsed("lowpass", {"cutoff_hz": 20.0}))
    sim = api.simulate(subjects=2, axes=("x", "z"), grips_N=(1.0, 2.0),
                       duration_s=(26.0, 26.0), seed=7, effects=effects)
    spectra = api.estimate(list(sim.trials()))
    return spectra, api.fit_grip(spectra).table


# ---------------------------------------------------------------------------
# The search: each axis's next step as soon as its own fits are done
# ---------------------------------------------------------------------------

def _screen(s, e):
    """The screening fit of ``e`` by its definition (:func:`screen_candidate` on the
    axis's trials), a candidate whose own code breaks its fit as the search records it."""
    try:
        return screen_candidate(s.data, s.band, s.fits[-1], e, s.by_subject_now(e))
    except EffectDefinitionError as exc:
        return search.FailedCandidate(e.name, str(exc))


def _step_by_step(spectra, params, max_steps: int = 3) -> list:
    """The stepwise search as it ran before the task queue: every step of every axis at
    once, each waiting for the slowest axis (the reference of the pipelined search)."""
    effects = list(EFFECTS.values())
    searches = []
    for axis in ("x", "y", "z"):
        data = axis_data(spectra, params, axis)
        if data is not None:
            band = (float(data.f_hz[0]), float(data.f_hz[-1]))
            searches.append(search._Search(data, band, effects, max_steps, 0.5, 3.0))
    for s in searches:
        s.start(search._base_task((s.data, s.band)))
    while any(not s.done for s in searches):
        live = [s for s in searches if not s.done]
        stasks = [(s, e) for s in live for e in s.remaining()]
        sfits = [_screen(s, e) for s, e in stasks]
        for (s, _), sc in zip(stasks, sfits, strict=True):
            if isinstance(sc, search.FailedCandidate):
                s.fail(sc)
        screened = {id(s): rank_screened([(e, sc) for (t, e), sc in zip(stasks, sfits,
                                                                         strict=True)
                                          if t is s
                                          and not isinstance(sc, search.FailedCandidate)])
                    for s in live}
        tasks = [(s, e, sc) for s in live for e, sc in keep_screened(screened[id(s)])]
        fits = [search._extend_task((s.data, s.band, s.fits[-1], e, sc,
                                     *(((s.min_db, s.min_deg),) if s.by_subject_now(e)
                                       else ())))
                for s, e, sc in tasks]
        for (s, _, _), fit in zip(tasks, fits, strict=True):
            if isinstance(fit, search.FailedCandidate):
                s.fail(fit)
        for s in live:
            full = {e.name: (fit if isinstance(fit, tuple) else (fit,))
                    for (t, e, _), fit in zip(tasks, fits, strict=True)
                    if t is s and not isinstance(fit, search.FailedCandidate)}
            s.take([(e, *full[e.name]) for e, _ in screened[id(s)] if e.name in full],
                   screened=[(e, sc) for e, sc in screened[id(s)]
                             if e.name not in full and e.name not in s.failed])
            if s.untested is not None:     # an apparatus effect added: tested per subject
                rivals = s.tested(search._subject_task(
                    (s.data, s.band, s.fits[-1], s.untested, s.min_db, s.min_deg)))
                if rivals:
                    s.settle(rivals, [search._subject_task(
                        (s.data, s.band, c.fit, c.effect, s.min_db, s.min_deg))
                        for c in rivals])
    search._borrow_step(searches, lambda fn, items: [fn(a) for a in items], SHARED_EFFECTS)
    out = [replace(s.result(), coupling=cross_coupling(spectra, s.data, s.band))
           for s in searches]
    agreement = search.cross_axis_agreement(out, SHARED_EFFECTS)
    return [replace(d, shared=agreement) for d in out] if agreement else out


@pytest.fixture(scope="module")
def pipelined(study):
    """The pipelined search of the study in this process (made once, compared twice)."""
    spectra, params = study
    return search.diagnose_axes(spectra, params)


def test_pipelined_search_is_the_step_by_step_search(study, pipelined):
    spectra, params = study
    here = pipelined
    assert repr(here) == repr(_step_by_step(spectra, params))
    # the study exercises several steps: the simulator's delay and lowpass on each axis
    assert [[s.effect for s in d.steps] for d in here] == [[None, "delay", "lowpass"]] * 2
    assert [d.stop for d in here] == ["adequate", "adequate"]


def test_pipelined_search_at_its_step_limit_is_the_step_by_step_search(study, monkeypatch):
    # one step: both axes stop at the limit, inadequate, and refit from the axes' common
    # delay (one borrowed fit each)
    spectra, params = study
    borrowed = []
    real = search._borrow_task
    monkeypatch.setattr(search, "_borrow_task", lambda a: borrowed.append(a) or real(a))
    here = search.diagnose_axes(spectra, params, max_steps=1)
    assert len(borrowed) == 2
    assert repr(here) == repr(_step_by_step(spectra, params, max_steps=1))
    assert [d.stop for d in here] == ["max-steps", "max-steps"]


def test_pipelined_search_in_worker_processes_is_the_same(study, pipelined):
    spectra, params = study
    assert repr(search.diagnose_axes(spectra, params, jobs=2)) == repr(pipelined)


def test_task_queue_runs_by_priority_and_continuations_add_tasks():
    # here (no pool) the ready task of lowest priority runs first, ties in the order
    # added; a continuation's new tasks join the queue
    ran = []
    tasks = TaskQueue()

    def then(result):
        ran.append(result)
        if result == "b":
            tasks.add(0, str.upper, "d", ran.append)

    for pri, name in [(2, "a"), (1, "b"), (2, "c")]:
        tasks.add(pri, str, name, then)
    tasks.run()
    assert ran == ["b", "D", "a", "c"]


def test_task_queue_on_a_pool_returns_every_result_and_raises_the_first_error():
    with ThreadPoolExecutor(max_workers=2) as pool:
        tasks = TaskQueue(pool, capacity=2)
        assert tasks.map(lambda x: x * x, range(7)) == [0, 1, 4, 9, 16, 25, 36]
        started = threading.Event()

        def fail(_):
            started.set()
            raise ValueError("broken")

        tasks.add(0, fail, None, lambda r: None)
        for i in range(5):
            tasks.add(1, lambda x: started.wait() and x, i, lambda r: None)
        with pytest.raises(ValueError, match="broken"):
            tasks.run()
    assert not tasks._ready and not tasks._running


def test_task_queue_start_ready_starts_tasks_before_run():
    # start_ready hands the ready tasks to the pool at once (up to its capacity): the
    # first is running before run() is called; without a pool, or while the thread that
    # starts the pool runs, it hands nothing over (run() or that thread does)
    began, release = threading.Event(), threading.Event()
    out = []
    with ThreadPoolExecutor(max_workers=2) as pool:
        tasks = TaskQueue(pool, capacity=1)
        tasks.add(0, lambda x: (began.set(), release.wait(5), x)[2], "a", out.append)
        tasks.add(1, lambda x: x, "b", out.append)
        tasks.start_ready()
        assert began.wait(5)                     # running in the pool, run() not called
        release.set()
        tasks.run()
    assert out == ["a", "b"]
    ran = []
    here = TaskQueue(None)
    here.add(0, ran.append, "c", lambda r: None)
    here.start_ready()
    assert ran == []
    here.run()
    assert ran == ["c"]
    go = threading.Event()
    starting = threading.Thread(target=go.wait)
    starting.start()
    with ThreadPoolExecutor(max_workers=1) as pool:
        waiting = TaskQueue(pool, capacity=1, starting=starting)
        waiting.add(0, ran.append, "d", lambda r: None)
        waiting.start_ready()
        assert ran == ["c"] and len(waiting._ready) == 1
        go.set()
        starting.join()
        waiting.run()
    assert ran == ["c", "d"]


def test_diagnosis_starts_an_axis_while_the_next_is_read(study, pipelined, monkeypatch):
    # with an executor, the first axis's base fit is handed over as soon as its measured
    # rows are read: before its cross rows (the coupling's) and the next axis's rows are
    # read (the result is the same)
    spectra, params = study
    events = []
    from armfit.diagnosis import driver
    reader = driver._trial_rows

    def recorded(sp):
        read = reader(sp)

        def rows(axis, kind):
            events.append(("read", axis, kind))
            return read(axis, kind)
        return rows

    class Recording(ThreadPoolExecutor):
        def submit(self, fn, *args, **kwargs):
            events.append(("submit", fn.__name__))
            return super().submit(fn, *args, **kwargs)

    monkeypatch.setattr(driver, "_trial_rows", recorded)
    with Recording(max_workers=2) as ex:
        got = search.diagnose_axes(spectra, params, executor=ex)
    assert repr(got) == repr(pipelined)
    assert events[:4] == [("read", "x", "measured"), ("submit", "_base_task"),
                          ("read", "x", "cross"), ("read", "z", "measured")]


def test_the_first_base_fit_is_handed_over_before_the_search_is_loaded(study, tmp_path):
    # in a fresh process: the search's own modules (the evidence, the results, the
    # joint fits and the fitting they use) are imported only after the first base fit
    # is handed to the executor, while it runs; the diagnosis is the one made here
    import pickle
    import subprocess
    import sys
    spectra, params = study
    (tmp_path / "study.pkl").write_bytes(pickle.dumps((spectra, params)))
    code = textwrap.dedent("""
        import pickle, sys
        from concurrent.futures import ThreadPoolExecutor
        from armfit.diagnosis import diagnose_axes
        spectra, params = pickle.loads(open(sys.argv[1], "rb").read())
        seen = []
        class Recording(ThreadPoolExecutor):
            def submit(self, fn, *args, **kwargs):
                seen.append((fn.__name__, "armfit.diagnosis.search" in sys.modules,
                             "armfit.fitting" in sys.modules))
                return super().submit(fn, *args, **kwargs)
        with Recording(max_workers=2) as ex:
            out = diagnose_axes(spectra, params, executor=ex)
        print(repr(seen[0]), "armfit.diagnosis.search" in sys.modules)
        sys.stdout.flush()
        open(sys.argv[2], "w").write(repr(out))
    """)
    res = subprocess.run([sys.executable, "-c", code, str(tmp_path / "study.pkl"),
                          str(tmp_path / "out.txt")], capture_output=True, text=True,
                         timeout=300, check=True)
    assert res.stdout.split("\n")[0] == "('_base_task', False, False) True"
    assert (tmp_path / "out.txt").read_text() == repr(search.diagnose_axes(spectra, params))


def test_task_queue_lets_go_of_a_large_task_it_handed_over_last(monkeypatch):
    # after each handing-over whose last task was added as large (an axis's trials),
    # the pool is asked to let go of that task's pickled bytes (workers.let_go_sent);
    # not after one that ended on a small task (sending that one let the large go)
    asked = []
    monkeypatch.setattr(schedule, "let_go_sent", asked.append)
    with ThreadPoolExecutor(max_workers=1) as pool:
        tasks = TaskQueue(pool)
        tasks.add(0, str, "base", lambda r: None, large=True)
        tasks.start_ready()
        assert asked == [pool]
        tasks.add(1, str, "large", lambda r: None, large=True)
        tasks.add(2, str, "small", lambda r: None)
        tasks.start_ready()
        assert asked == [pool]
        assert tasks.map(str, ["a", "b"], large=True) == ["a", "b"]
        assert asked == [pool, pool]
    here = TaskQueue(None)       # no pool: nothing sent, nothing to let go
    here.add(0, str, "x", lambda r: None, large=True)
    here.run()
    assert asked == [pool, pool]


def test_task_queue_gives_memory_back_after_large_tasks_only(monkeypatch):
    # once a large task's result is in (an axis's trials sent, its fit received) the
    # process gives the memory it freed back (release_memory); after small tasks alone
    # (a screening fit's three trials) it does not ask: there is little to give back
    released = []
    monkeypatch.setattr(schedule, "release_memory", lambda: released.append(True))
    with ThreadPoolExecutor(max_workers=1) as pool:
        tasks = TaskQueue(pool, capacity=1)
        assert tasks.map(str, ["a", "b", "c"]) == ["a", "b", "c"]
        assert released == []
        assert tasks.map(str, ["d"], large=True) == ["d"]
        assert released == [True]


def test_an_axis_of_large_data_gives_memory_back_before_its_evidence(monkeypatch):
    # an axis whose trials take 1 MiB or more (search.LARGE_TASK_BYTES: 400 trials of
    # 100 frequencies take 400 * 100 * 32 bytes, 1.28 MB) gives the memory freed so far
    # back before the evidence of a result is made; a small axis (40 trials) does not
    from types import SimpleNamespace

    from armfit.diagnosis.responses import AxisData
    calls = []
    monkeypatch.setattr(search, "release_memory", lambda: calls.append("release"))
    n = 100
    for T, expected in ((400, ["release", "start"]), (40, ["start"])):
        data = AxisData("x", np.geomspace(0.1, 30.0, n), np.ones((T, n), complex),
                        np.ones((T, n)), np.ones((T, n)), ({},) * T)
        assert (data.nbytes >= search.LARGE_TASK_BYTES) == (T == 400)
        axis = SimpleNamespace(data=data, done=True,
                               start=lambda base: calls.append("start"))
        calls.clear()
        search._AxisSteps(axis, TaskQueue(), iter(range(3)))._based(None)
        assert calls == expected


@pytest.mark.parametrize("workers", [1, 2])
def test_the_last_axes_as_many_as_the_workers_screen_their_candidates_in_turn(study,
                                                                             workers):
    # the order the ready screening fits are handed out in: axis by axis (x's, then
    # z's) while the axes outnumber the workers; the last axes as many as the workers
    # alternately (x, z, x, z, ...), each axis's candidates of most parameters first
    spectra, params = study
    effects = list(EFFECTS.values())
    tasks, turns = TaskQueue(), search._Turns()
    turns.share_last(2, workers)
    for axis in ("x", "z"):
        data = axis_data(spectra, params, axis)
        s = search._Search(data, (float(data.f_hz[0]), float(data.f_hz[-1])), effects,
                           3, 0.5, 3.0)
        base = search._base_task((s.data, s.band))
        search._AxisSteps(s, tasks, turns)._based(base)
    order = []
    while tasks._ready:
        item = heapq.heappop(tasks._ready)
        order.append((item[3][0].axis, item[3][4].name))
    by_params = [e.name for e in sorted(effects, key=lambda e: -len(e.params))]
    if workers == 1:
        assert order == [("x", n) for n in by_params] + [("z", n) for n in by_params]
    else:
        assert order == [(a, n) for n in by_params for a in ("x", "z")]


def test_task_queue_runs_tasks_here_while_the_pool_starts():
    # while the thread starting the pool runs, ready tasks run in this thread; once it
    # has ended, on the pool
    go = threading.Event()
    starting = threading.Thread(target=go.wait)
    starting.start()
    where = []

    def started(_):
        go.set()
        starting.join()

    with ThreadPoolExecutor(max_workers=1) as pool:
        tasks = TaskQueue(pool, capacity=1, starting=starting)
        tasks.add(0, lambda _: where.append(threading.current_thread()), None, started)
        tasks.add(1, lambda _: where.append(threading.current_thread()), None, lambda r: None)
        tasks.run()
    assert where[0] is threading.current_thread()
    assert where[1] is not threading.current_thread()


def test_task_queue_hands_ready_tasks_to_the_pool_while_a_task_runs_here():
    # the task running here (started while the pool starts) waits for the next task to
    # have started in the pool: it can only if the starting thread hands the ready tasks
    # over as soon as the pool is up, not once the task here has ended
    up, other_started = threading.Event(), threading.Event()
    where = {}
    with ThreadPoolExecutor(max_workers=1) as pool:
        tasks = TaskQueue(pool, capacity=1)

        def start():
            up.wait(10.0)
            tasks.hand_over()

        tasks.starting = threading.Thread(target=start)
        tasks.starting.start()

        def here(_):
            where["here"] = threading.current_thread()
            up.set()
            return other_started.wait(10.0)

        def other(_):
            where["other"] = threading.current_thread()
            other_started.set()
            return "other"

        results = []
        tasks.add(0, here, None, results.append)
        tasks.add(1, other, None, results.append)
        tasks.run()
        tasks.starting.join()
    assert where["here"] is threading.current_thread()
    assert where["other"] is not threading.current_thread()
    assert sorted(map(str, results)) == ["True", "other"]


def test_task_queue_context_uses_a_given_executor_as_is():
    with ThreadPoolExecutor(max_workers=1) as given:
        with schedule.task_queue(jobs=4, executor=given) as tasks:
            assert tasks.pool is given and tasks.capacity is None
        assert given.submit(int, "3").result() == 3    # not shut down
    with schedule.task_queue(jobs=1) as tasks:
        assert tasks.pool is None


def test_task_queue_starts_its_pool_early_in_the_main_thread_only(monkeypatch):
    # in the main thread, while no fork server runs, its own pool starts in a thread
    # while tasks run here; in another thread (armfit run's diagnosis, which
    # cancel_pools may stop) it starts at its first task, in the pool
    monkeypatch.setattr(schedule, "fork_server_running", lambda: False)
    with schedule.task_queue(jobs=2) as tasks:
        assert tasks.starting is not None
        assert tasks.map(abs, [-1, -2, -3]) == [1, 2, 3]
    seen = []

    def elsewhere():
        with schedule.task_queue(jobs=2) as tasks:
            seen.append(tasks.starting)
            seen.append(tasks.map(abs, [-4]))

    t = threading.Thread(target=elsewhere)
    t.start()
    t.join()
    assert seen == [None, [4]]


@pytest.mark.skipif(workers.start_method() != "forkserver", reason="no fork server here")
def test_task_queue_hands_every_task_to_the_workers_once_the_fork_server_runs():
    # with the server up (the command line starts it before it loads its own modules)
    # the workers are forked in milliseconds: no task runs in this process, where a
    # long one would hold back the continuations, and so the other axes' next tasks
    workers.start_fork_server(workers.POOL_PRELOAD["diagnosis"])
    assert workers.fork_server_running()
    with schedule.task_queue(jobs=2) as tasks:
        assert tasks.starting is None
        pids = tasks.map(operator.call, [os.getpid] * 4)
    assert len(pids) == 4 and os.getpid() not in pids


def test_task_queue_keeps_one_task_waiting_beyond_its_own_workers(monkeypatch):
    # a pool of the queue's own (2 workers here) is handed one task more than it has
    # workers, so that a worker ending a task finds the next one waiting: at most 3 of
    # the tasks handed over are unfinished at once, and every result comes back
    unfinished, most = [], []

    class Counting(ThreadPoolExecutor):
        def submit(self, fn, *args, **kwargs):
            fut = super().submit(fn, *args, **kwargs)
            unfinished.append(fut)
            most.append(sum(not f.done() for f in unfinished))
            return fut

    @contextlib.contextmanager
    def own_pool(executor, jobs, preload=()):
        with Counting(max_workers=jobs) as pool:
            yield pool

    monkeypatch.setattr(schedule, "executor_for", own_pool)
    monkeypatch.setattr(schedule, "fork_server_running", lambda: True)
    release = threading.Event()
    with schedule.task_queue(jobs=2) as tasks:
        threading.Timer(0.2, release.set).start()
        out = tasks.map(lambda i: release.wait(10) and i, range(6))
    assert out == list(range(6))
    assert max(most) == 2 + schedule.AHEAD == 3


# ---------------------------------------------------------------------------
# Joint fits: repeated starts, single-trial fits
# ---------------------------------------------------------------------------

def _z_data(study):
    spectra, params = study
    data = axis_data(spectra, params, "z")
    return data, (float(data.f_hz[0]), float(data.f_hz[-1]))


def test_joint_jacobian_is_that_of_the_residuals(study):
    # the arm parameters' columns are analytic, the effect's forward differences: both
    # against central differences of the residuals (step 1e-6 in the fitter's
    # coordinate; an independent computation), per-trial and shared blocks, with the
    # delay per subject (grouped shared columns) as well as shared
    data, band = _z_data(study)
    model = ClosedLoopModel.for_axis("z", [EFFECTS["delay"]])
    sel = (data.f_hz >= band[0]) & (data.f_hz <= band[1])
    for varying in ((), ("delay.delay_s",)):
        prob = joint.JointProblem(model, data, sel, varying)
        x = prob.pack(start_array(data) * 1.1, {"delay.delay_s": 0.01})
        jb, js = prob.jac(x)
        T, nb = prob.T, prob.nb
        r0 = prob.fun(x)
        want = np.empty((r0.size, x.size))
        for j in range(x.size):
            e = np.zeros(x.size)
            e[j] = 1e-6
            want[:, j] = (prob.fun(x + e) - prob.fun(x - e)) / 2e-6
        want = want.reshape(T, -1, x.size)
        scale = np.abs(want).max()
        for i in range(T):
            np.testing.assert_allclose(jb[i], want[i][:, i * nb:(i + 1) * nb], rtol=1e-5,
                                       atol=1e-7 * scale)
            cols = (np.arange(prob.k) if prob.cols is None else prob.cols[i]) + T * nb
            np.testing.assert_allclose(js[i], want[i][:, cols], rtol=1e-4, atol=1e-6 * scale)


def _levy_one_by_one(model, data, band, effect_values, fallback):
    """levy_starts written out as armfit did it before: trial by trial, each band cut's
    Levy fit on its own frequencies, each candidate's response on its own."""
    from armfit.diagnosis.bands import residuals
    from armfit.diagnosis.tuning import UNIT_DEG
    from armfit.fitting import analytic_guess
    sel = (data.f_hz >= band[0]) & (data.f_hz <= band[1])
    f = data.f_hz[sel]
    out = np.array(fallback, float, copy=True)
    base_model = ClosedLoopModel(mp=model.mp)
    bounds = [(p.lower, p.upper) for p in base_model.params]
    for i in range(data.h.shape[0]):
        with np.errstate(all="ignore"):
            hb = model.remove_effects(f, data.h[i, sel], effect_values) if effect_values \
                else data.h[i, sel]
            if not np.all(np.isfinite(hb)):
                continue
            best = None
            cands = [c for lo_f in (0.0, 0.3, 1.0) if np.sum(f >= lo_f) > 10
                     for c in analytic_guess(f[f >= lo_f], hb[f >= lo_f], model.mp)]
            for cand in cands:
                row = np.array([np.clip(cand[n], lo, hi)
                                for n, (lo, hi) in zip(PARAM_NAMES, bounds, strict=True)])
                r_db, r_deg = residuals(hb, base_model.response(f, row))
                err = float(np.nanmean(r_db ** 2 + (r_deg / UNIT_DEG) ** 2))
                if np.isfinite(err) and (best is None or err < best[0]):
                    best = (err, row)
        if best is not None:
            out[i] = best[1]
    return out


def test_levy_starts_of_many_trials_at_once_are_those_trial_by_trial(study, monkeypatch):
    # bit for bit: the base model, and the delay and the lowpass removed at several
    # values (one so large that some trials' responses without it are not finite, and
    # another where no candidate is physical and the fallback row stays); the trials
    # taken 3 at a time (several chunks, the last one short) and all at once
    from armfit.diagnosis import starts
    data, band = _z_data(study)
    assert data.h.shape[0] > 3 and data.h.shape[0] % 3
    fallback = start_array(data)
    cases = [(ClosedLoopModel.for_axis("z"), {})]
    for name, values in (("delay", (0.0, 0.012, 0.05)), ("lowpass", (20.0, 2.0, 0.2))):
        model = ClosedLoopModel.for_axis("z", [EFFECTS[name]])
        param = f"{name}.{EFFECTS[name].params[0].name}"
        cases += [(model, {param: v}) for v in values]
    kept = 0
    for chunk in (3, 10_000):
        monkeypatch.setattr(starts, "CHUNK_TRIALS", chunk)
        for model, values in cases:
            got = starts.levy_starts(model, data, band, values, fallback)
            want = _levy_one_by_one(model, data, band, values, fallback)
            assert np.array_equal(got, want), (chunk, values)
            kept += int(np.sum(np.all(got == fallback, axis=1)))
    assert kept        # some trial kept its fallback row: that branch was taken too


def test_joint_normal_blocks_a_few_trials_at_a_time_are_those_of_the_whole_jacobian(
        study, monkeypatch):
    # independent computation: the blocks of JᵀJ and Jᵀr from the whole Jacobian
    # (JointProblem.jac, every trial at once), with the delay shared and per subject;
    # the problem's own blocks are made CHUNK_TRIALS trials at a time (3 here, so that
    # the study's trials fall in several chunks, the last one short)
    from armfit import blocklsq
    data, band = _z_data(study)
    model = ClosedLoopModel.for_axis("z", [EFFECTS["delay"]])
    sel = (data.f_hz >= band[0]) & (data.f_hz <= band[1])
    monkeypatch.setattr(joint, "CHUNK_TRIALS", 3)
    for varying in ((), ("delay.delay_s",)):
        prob = joint.JointProblem(model, data, sel, varying)
        assert prob.T > 3 and prob.T % 3
        x = prob.pack(start_array(data) * 1.1, {"delay.delay_s": 0.01})
        r = prob.fun(x).reshape(prob.T, -1)
        groups = None if prob.cols is None else blocklsq.Groups(prob.cols, prob.K)
        want = blocklsq._normal(*prob.jac(x), r, groups)
        got = prob.normal(x, r)
        for g, w in zip(got, want, strict=True):
            assert g.shape == w.shape
            np.testing.assert_allclose(g, w, rtol=1e-12, atol=1e-12 * np.abs(w).max())


def test_start_rows_and_residuals_a_few_trials_at_a_time_are_those_of_all_at_once(
        study, monkeypatch):
    # independent computation: the same functions with every trial in one chunk; made
    # 3 trials at a time (the study's trials in several chunks, the last one short),
    # the best candidate rows, the weighted residuals and the fit's summary are the same
    # to the bit
    from armfit.diagnosis import starts
    data, band = _z_data(study)
    model = ClosedLoopModel.for_axis("z", [EFFECTS["delay"]])
    sel = (data.f_hz >= band[0]) & (data.f_hz <= band[1])
    base = start_array(data)
    effect = {"delay.delay_s": 0.01}

    def made(chunk: int):
        monkeypatch.setattr(joint, "CHUNK_TRIALS", chunk)
        monkeypatch.setattr(starts, "CHUNK_TRIALS", chunk)
        rows = starts.best_rows(model, data, band, effect, [base, base * 1.3, base[0]])
        prob = joint.JointProblem(model, data, sel)
        x = prob.pack(base * 1.1, effect)
        fit = joint.joint_fit(model, data, band, base, [effect], max_nfev=5)
        return rows, prob.fun(x), fit
    assert data.h.shape[0] > 3 and data.h.shape[0] % 3
    (rows3, r3, fit3), (rows_all, r_all, fit_all) = made(3), made(10_000)
    assert rows3.tobytes() == rows_all.tobytes()
    assert r3.tobytes() == r_all.tobytes()
    assert (fit3.rss, fit3.rho, fit3.n_res) == (fit_all.rss, fit_all.rho, fit_all.n_res)
    assert fit3.r_db.tobytes() == fit_all.r_db.tobytes()


def test_a_joint_fit_never_holds_its_whole_jacobian(study, monkeypatch):
    # the memory of a joint fit's solve (tracemalloc's peak, numpy's arrays included):
    # its blocks of JᵀJ are made a chunk of trials at a time, so it takes less than the
    # same solve given the whole Jacobian (blocklsq.solve with JointProblem.jac, the
    # reference) by at least half that Jacobian's size, (T, m, 5 + k) float64; both
    # take the same steps
    import tracemalloc

    from armfit import blocklsq
    data, band = _z_data(study)
    many = data.subset(np.tile(np.arange(data.h.shape[0]), 16))     # 16 x the trials
    model = ClosedLoopModel.for_axis("z", [EFFECTS["delay"]])
    sel = (many.f_hz >= band[0]) & (many.f_hz <= band[1])
    monkeypatch.setattr(joint, "CHUNK_TRIALS", 4)
    prob = joint.JointProblem(model, many, sel)
    x0 = prob.pack(start_array(many), {"delay.delay_s": 0.01})
    lo, hi = prob.bounds()

    def peak(solve):
        tracemalloc.start()
        try:
            base = tracemalloc.get_traced_memory()[0]
            res = solve()
            return res, tracemalloc.get_traced_memory()[1] - base
        finally:
            tracemalloc.stop()

    res, blocks = peak(lambda: prob.solve(x0, 20))
    ref, whole = peak(lambda: blocklsq.solve(prob.fun, prob.jac, x0, lo, hi,
                                             n_trials=prob.T, n_block=prob.nb,
                                             max_nfev=20))
    assert res.nfev == ref.nfev > 1
    np.testing.assert_allclose(res.x, ref.x, rtol=1e-6, atol=1e-9)
    jacobian = prob.T * 2 * int(sel.sum()) * (prob.nb + prob.k) * 8
    assert blocks < whole - 0.5 * jacobian, (blocks, whole, jacobian)


def test_a_joint_problem_on_the_whole_grid_holds_the_datas_own_responses(study):
    # on the whole grid (the default band) the problem's responses are the data's array
    # itself, not a copy (an axis's 1,350 trials: 2.2 MB); on a narrower band they are
    # the band's columns, and the residuals are those of the band alone either way
    data, band = _z_data(study)
    model = ClosedLoopModel.for_axis("z")
    whole = joint.JointProblem(model, data, np.ones(data.f_hz.size, bool))
    assert whole.h is not data.h and np.shares_memory(whole.h, data.h)
    assert whole.h.tobytes() == data.h.tobytes()
    sel = data.f_hz <= 10.0
    part = joint.JointProblem(model, data, sel)
    assert not np.shares_memory(part.h, data.h)
    assert part.h.tobytes() == data.h[:, sel].tobytes()
    x0 = whole.pack(start_array(data), {})
    n = int(sel.sum())
    r_whole, r_part = whole.fun(x0).reshape(whole.T, -1), part.fun(x0).reshape(part.T, -1)
    nf = data.f_hz.size
    assert r_part[:, :n].tobytes() == r_whole[:, :nf][:, sel].tobytes()
    assert r_part[:, n:].tobytes() == r_whole[:, nf:][:, sel].tobytes()


def test_a_joint_fit_keeps_no_residuals_of_its_best_start_while_it_refines_the_next(
        study, monkeypatch):
    # the memory traced as each refined start begins (tracemalloc, numpy's arrays
    # included): the best fit so far is kept without its weighted residuals, (T, 2n)
    # float64, so the second start begins with less than half their size more than the
    # first held (the kept parameters and blocks of JᵀJ: 31 kB here, the residuals
    # 102 kB; kept with its residuals, 134 kB); the fit's residuals are those of its
    # parameters (made anew from them)
    import tracemalloc
    data, band = _z_data(study)
    many = data.subset(np.tile(np.arange(data.h.shape[0]), 16))     # 16 x the trials
    model = ClosedLoopModel.for_axis("z", [EFFECTS["delay"]])
    real, real_rescue, at_start, rescuing = joint.refine, joint.rescue_trials, [], []

    def refine(prob, x0, max_nfev, brief=None):     # a start's refinement, not a rescue's
        if not rescuing:
            at_start.append(tracemalloc.get_traced_memory()[0])
        return real(prob, x0, max_nfev, brief)

    def rescue(*args, **kwargs):
        rescuing.append(1)
        try:
            return real_rescue(*args, **kwargs)
        finally:
            rescuing.pop()

    monkeypatch.setattr(joint, "refine", refine)
    monkeypatch.setattr(joint, "rescue_trials", rescue)
    starts = ({"delay.delay_s": 0.0}, {"delay.delay_s": 0.03})
    tracemalloc.start()
    try:
        fit = joint.joint_fit(model, many, band, start_array(many), starts, refine_best=2)
    finally:
        tracemalloc.stop()
    residuals = many.h.shape[0] * 2 * many.f_hz.size * 8
    assert len(at_start) == 2
    assert at_start[1] - at_start[0] < residuals / 2, (at_start, residuals)
    prob = joint.JointProblem(model, many, np.ones(many.f_hz.size, bool))
    r_db, _ = prob.split_res(prob.pack(fit.base, fit.shared))
    np.testing.assert_allclose(r_db, fit.r_db, rtol=1e-9, atol=1e-9)


def test_refine_stops_where_the_values_are_those_of_a_tight_fit(study):
    # refine stops when a step lowers the cost by less than FTOL_VARIANCE (1 %) of the
    # residual variance s² = 2 cost/(m − p). The reference: the same fit from the same
    # start run to 1e-14 (or 1,000 evaluations). Along the flat valley a delay and a
    # lowpass make together the fit creeps; refine ends within a tenth of s² of the
    # reference's cost and within a tenth of the 95 % half-width of its values (0.09 s²
    # and 0.05 measured here), in a fraction of its evaluations
    data, band = _z_data(study)
    model = ClosedLoopModel.for_axis("z", [EFFECTS["delay"], EFFECTS["lowpass"]])
    sel = (data.f_hz >= band[0]) & (data.f_hz <= band[1])
    prob = joint.JointProblem(model, data, sel)
    for start in ({"delay.delay_s": 0.01, "lowpass.cutoff_hz": 30.0},
                  {"delay.delay_s": 0.0, "lowpass.cutoff_hz": 15.0}):
        x0 = prob.pack(start_array(data), start)
        got = joint.refine(prob, x0, 200)
        tight = prob.solve(x0, 1000, ftol=1e-14, xtol=1e-14, gtol=1e-14)
        assert got.status > 0 and got.nfev < tight.nfev / 2
        s2 = 2 * tight.cost / (tight.fun.size - tight.x.size)
        assert 0 <= got.cost - tight.cost <= 10 * FTOL_VARIANCE * s2
        fit = joint._result(prob, got)
        ref = joint._result(prob, tight)
        for n in ("delay.delay_s", "lowpass.cutoff_hz"):
            half = (ref.shared_hi[n] - ref.shared_lo[n]) / 2
            assert abs(fit.shared[n] - ref.shared[n]) < 0.1 * half, n


def test_axis_data_starts_are_the_param_row_of_each_trials_grip(study):
    # the reference: param_row of each trial, one by one (axis_data finds each grip's row
    # once); a grip without a row of its own takes the nearest grip's row, as param_row
    spectra, params = study
    shifted = params.assign(grip_N=params["grip_N"] + np.where(params["grip_N"] > 1.5,
                                                               0.25, 0.0))
    for table in (params, shifted):
        for axis in ("x", "z"):
            data = axis_data(spectra, table, axis)
            grips = [float(n.split("_grip-")[1].split("N")[0]) for n in data.labels]
            assert sorted(set(grips)) == [1.0, 2.0]
            for grip, start in zip(grips, data.starts, strict=True):
                ref = param_row(table, axis, grip)
                assert start == {n: float(ref[n]) for n in PARAM_NAMES}


def test_screen_starts_with_repeated_combinations_is_each_tried(study):
    data, band = _z_data(study)
    model = ClosedLoopModel.for_axis("z", [EFFECTS["delay"]])
    sel = (data.f_hz >= band[0]) & (data.f_hz <= band[1])
    prob = joint.JointProblem(model, data, sel)
    start = start_array(data)
    combos = [(start, {"delay.delay_s": 0.0}), (start.copy(), {"delay.delay_s": 0.0}),
              (start, {"delay.delay_s": 0.015}), (start * 1.5, {"delay.delay_s": 0.0})]
    got = joint.screen_starts(model, data, sel, combos, prob, keep=3, nfev=12)
    # the long way: every combination's short fit made on its own
    T = data.h.shape[0]
    idx = np.unique(np.linspace(0, T - 1, min(T, 9)).round().astype(int))
    sub = joint.AxisData(data.axis, data.f_hz, data.h[idx], data.se_db[idx],
                         data.se_deg[idx], tuple(data.starts[i] for i in idx))
    sprob = joint.JointProblem(model, sub, sel)
    scored = sorted([(sprob.solve(sprob.pack(b[idx], st), 12), b, st) for b, st in combos],
                    key=lambda t: t[0].cost)
    want = []
    for r, b, st in scored[:3]:
        x0 = prob.pack(b, st)
        x0[-1:] = r.x[-1:]
        want.append(x0)
    assert len(got) == 3
    for g, w in zip(got, want, strict=True):
        np.testing.assert_array_equal(g, w)


@pytest.mark.parametrize(("nfev", "way"), [(4, "resumed"), (60, "watched")])
def test_a_refinement_that_goes_on_from_its_brief_try_is_the_refinement_made_anew(study,
                                                                                 nfev, way):
    # the base model on the z axis's 4 trials: the brief tries are on every trial and
    # their starts are the refinements' own (no effect value moves), so each refinement
    # goes on from its brief try (resumed) or is the fit the brief try saw stop
    # (watched); the reference is the refinement made from the start in one run
    data, band = _z_data(study)
    model = ClosedLoopModel.for_axis("z")
    sel = (data.f_hz >= band[0]) & (data.f_hz <= band[1])
    prob = joint.JointProblem(model, data, sel)
    start = start_array(data)
    combos = [(start, {}), (start * 1.3, {}), (start * 0.6, {})]
    briefs: dict = {}
    x0s = joint.screen_starts(model, data, sel, combos, prob, keep=3, nfev=nfev,
                              briefs=briefs)
    assert len(x0s) == 3 and set(briefs) == {x.tobytes() for x in x0s}
    ways = set()
    for x0 in x0s:
        brief = briefs[x0.tobytes()]
        ways.add("watched" if brief.watched is not None else "resumed")
        got, want = joint.refine(prob, x0, 200, brief), joint.refine(prob, x0, 200)
        np.testing.assert_array_equal(got.x, want.x)
        np.testing.assert_array_equal(got.fun, want.fun)
        assert (got.cost, got.status, got.nfev) == (want.cost, want.status, want.nfev)
        for p, q in zip(got.normal, want.normal, strict=True):
            np.testing.assert_array_equal(p, q)
    assert ways == {way}


def test_a_start_far_behind_after_its_brief_try_is_not_refined(study, monkeypatch):
    # START_GAP: of the best REFINE_BEST brief tries, one whose cost exceeds START_GAP
    # times the best one's is left out; the reference is the short fits made the long
    # way (as above), the premise that this start is that far behind checked first
    data, band = _z_data(study)
    model = ClosedLoopModel.for_axis("z", [EFFECTS["delay"]])
    sel = (data.f_hz >= band[0]) & (data.f_hz <= band[1])
    prob = joint.JointProblem(model, data, sel)
    start = start_array(data)
    combos = [(start, {"delay.delay_s": 0.012}), (start * 30.0, {"delay.delay_s": 0.09})]
    T = data.h.shape[0]
    idx = np.unique(np.linspace(0, T - 1, min(T, 9)).round().astype(int))
    sprob = joint.JointProblem(model, data.subset(idx), sel)
    near, far = (sprob.solve(sprob.pack(b[idx], st), 12).cost for b, st in combos)
    assert far > joint.START_GAP * near
    got = joint.screen_starts(model, data, sel, combos, prob, keep=2, nfev=12)
    monkeypatch.setattr(joint, "START_GAP", np.inf)
    every = joint.screen_starts(model, data, sel, combos, prob, keep=2, nfev=12)
    assert len(got) == 1 and len(every) == 2
    np.testing.assert_array_equal(got[0], every[0])


def test_joint_fit_refines_a_repeated_start_once_with_the_same_result(study, monkeypatch):
    data, band = _z_data(study)
    model = ClosedLoopModel.for_axis("z", [EFFECTS["delay"]])
    start = start_array(data)
    # two identical combinations: both are among the best two, the same start twice
    starts = [{"delay.delay_s": 0.012}, {"delay.delay_s": 0.012}]
    rescued = []
    real = joint.rescue_trials
    monkeypatch.setattr(joint, "rescue_trials",
                        lambda *a, **k: rescued.append(a[4]) or real(*a, **k))
    got = joint.joint_fit(model, data, band, start, starts, max_nfev=60)
    assert len(rescued) == 1
    # the long way: every start of the screening refined and rescued, the first of the
    # lowest cost kept
    sel = (data.f_hz >= band[0]) & (data.f_hz <= band[1])
    prob = joint.JointProblem(model, data, sel)
    x0s = joint.screen_starts(model, data, sel, [(start, st) for st in starts], prob)
    assert len(x0s) == 2 and np.array_equal(x0s[0], x0s[1])
    results = [real(prob, model, data, sel, joint.refine(prob, x0, 60), 60) for x0 in x0s]
    best = min(results, key=lambda r: r.cost)
    theta = prob.space.to_theta(prob.unpack(best.x))
    np.testing.assert_array_equal(got.base, theta[:, :5])
    assert got.shared == {"delay.delay_s": float(theta[0, 5])}


def test_a_stuck_trial_takes_its_arm_parameters_from_the_best_start_first(study,
                                                                          monkeypatch):
    # a start whose fit leaves a trial stuck, while another start's fit has none: the
    # trial takes its arm parameters from that fit and the joint fit is refined, with no
    # single-trial fit; without such a fit the single-trial fits are made, as before
    data, band = _z_data(study)
    model = ClosedLoopModel.for_axis("z", [EFFECTS["delay"]])
    sel = (data.f_hz >= band[0]) & (data.f_hz <= band[1])
    prob = joint.JointProblem(model, data, sel)
    prior = joint.refine(prob, prob.pack(start_array(data), {"delay.delay_s": 0.05}), 200)
    assert joint._stuck(prob, prior).size == 0
    lo, hi = prob.bounds()
    x = prior.x.copy()
    x[5:10] = np.clip(x[5:10] + 3.0, lo[5:10], hi[5:10])   # trial 1's arm far off
    r = prob.fun(x)
    res = replace(prior, x=x, fun=r, cost=0.5 * float(r @ r))
    assert joint._stuck(prob, res).tolist() == [1]
    real = joint.trial_fit
    calls = []
    monkeypatch.setattr(joint, "trial_fit", lambda *a, **k: calls.append(a[2]) or real(*a, **k))
    got = joint.rescue_trials(prob, model, data, sel, res, 200, prior=prior.x)
    assert calls == []
    assert joint._stuck(prob, got).size == 0 and got.cost <= prior.cost
    joint.rescue_trials(prob, model, data, sel, res, 200)
    assert calls and set(calls) == {1}


def test_trial_fit_is_the_single_trial_fit_and_made_once(study):
    data, band = _z_data(study)
    model = ClosedLoopModel.for_axis("z", [EFFECTS["delay"]])
    joint._TRIAL_FITS.clear()
    start = {"Ma": 1.0, "k1": 2000.0, "k2": 300.0, "b1": 30.0, "b2": 20.0,
             "delay.delay_s": 0.01}
    for x0 in (start, None):
        first = joint.trial_fit(model, data, 1, band, x0)
        assert joint.trial_fit(model, data, 1, band, x0) is first       # made once
        direct = fit_response(model, data.f_hz, data.h[1], se_db=data.se_db[1],
                              se_deg=data.se_deg[1], band=band, x0=x0,
                              global_search=x0 is None, strict=False, intervals=False)
        assert first.params == direct.params
    # another trial, another start or another model is another fit
    assert joint.trial_fit(model, data, 2, band) is not joint.trial_fit(model, data, 1, band)
    base = ClosedLoopModel.for_axis("z")
    assert joint.trial_fit(base, data, 1, band).params.keys() != first.params.keys()


# ---------------------------------------------------------------------------
# K_max: the first unstable gain, each crossing angle once
# ---------------------------------------------------------------------------

def _plants():
    """Arms of X and Z with delays of 0 to 14 ms and a lag: loops of a few to 40
    states at the settings below, with many crossings."""
    out = []
    arms = {"x": (0.5, 120.0, 400.0, 8.0, 6.0), "z": (2.0, 2500.0, 150.0, 40.0, 30.0)}
    for axis, arm in arms.items():
        base = dict(zip(("Ma", "k1", "k2", "b1", "b2"), arm, strict=True))
        out.append(plant_from_model(ClosedLoopModel.for_axis(axis), base))
        for tau in (0.002, 0.009, 0.014):
            model = ClosedLoopModel.for_axis(axis, [EFFECTS["delay"], EFFECTS["lowpass"]])
            out.append(plant_from_model(model, {**base, "delay.delay_s": tau,
                                                "lowpass.cutoff_hz": 40.0}))
    return out


SETTINGS = [WallSettings(), WallSettings(1 / 2828.4, 0.0, 2), WallSettings(5e-4, 2.0, 0)]


@pytest.mark.parametrize("settings", SETTINGS)
def test_crossing_gains_solve_each_angle_once_with_the_same_gains(settings):
    repeated = 0
    for g in _loops(_plants(), settings):
        got = _crossing_gains_batch(g.M0, g.b, g.c)
        # the long way: g(e^jθ) solved for every candidate angle, repeated ones too
        A, E = _pencils(g.M0, g.b, g.c)
        ggev, = linalg.get_lapack_funcs(("ggev",), (A[0],))
        for r in range(g.M0.shape[0]):
            with np.errstate(all="ignore"):
                ar, ai, beta, *_ = ggev(A[r], E[r], compute_vl=0, compute_vr=0)
                ev = (ar + 1j * ai) / beta
            ev = ev[np.isfinite(ev)]
            on = ev[np.abs(np.abs(ev) - 1.0) < 1e-6]
            th = np.concatenate([np.abs(np.angle(on)), [0.0, np.pi]])
            gz = _g_of(np.repeat(g.M0[r:r + 1], th.size, 0),
                       np.repeat(g.b[r:r + 1], th.size, 0),
                       np.repeat(g.c[r:r + 1], th.size, 0), np.exp(1j * th))
            with np.errstate(all="ignore"):
                K = 1.0 / gz.real
            ok = np.isfinite(K) & (K > 0) & (np.abs(gz.imag) <= 1e-6 * np.abs(gz) + 1e-300)
            repeated += th.size - np.unique(th).size
            np.testing.assert_array_equal(got[r][0], K[ok])
            np.testing.assert_array_equal(got[r][1], th[ok])
    assert repeated > 0       # complex pairs of eigenvalues: angles solved once, not twice


@pytest.mark.parametrize("settings", SETTINGS)
def test_open_loop_from_the_plant_alone_is_that_of_the_whole_loop(settings):
    # g(z) = cᵀ(zI − M0)⁻¹b solved with the loop's N states (the independent
    # computation, _g_of) against the plant's n states and the controller's closed form
    # (_Group.g), on and off the unit circle; the crossing gains wall_stability takes
    # from the latter are those of the former
    z = np.concatenate([np.exp(1j * np.linspace(0.0, np.pi, 41)),
                        0.7 * np.exp(0.4j) * np.ones(1), 1.3 * np.exp(2.0j) * np.ones(1)])
    n_shift = 0
    for g in _loops(_plants(), settings):
        R, N = g.M0.shape[:2]
        n_shift += N - g.Pd.shape[1]
        idx = np.repeat(np.arange(R), z.size)
        zz = np.tile(z, R)
        whole = _g_of(g.M0[idx], g.b[idx], g.c[idx], zz)
        np.testing.assert_allclose(g.g(idx, zz), whole, rtol=1e-9, atol=0)
        for (k1, t1), (k2, t2) in zip(_crossing_gains_batch(g.M0, g.b, g.c),
                                      _crossing_gains_batch(g.M0, g.b, g.c, g_of=g.g),
                                      strict=True):
            np.testing.assert_array_equal(t1, t2)
            np.testing.assert_allclose(k1, k2, rtol=1e-9)
    assert n_shift > 0      # loops whose shift register the plant-only solve skips


@pytest.mark.parametrize("settings", SETTINGS)
def test_first_unstable_gain_is_that_of_testing_every_gain(settings):
    tested = 0
    for g in _loops(_plants(), settings):
        mids = []
        for K, _ in _crossing_gains_batch(g.M0, g.b, g.c):
            K = np.sort(K)
            mids.append(_interval_gains(K[np.concatenate([[True], np.diff(K) > 1e-9 * K[1:]])]
                                        if K.size else K))
        first, top = _first_unstable(g, mids)
        # the long way: every gain of every loop tested in one batch
        idx = np.concatenate([np.full(m.size, r) for r, m in enumerate(mids)])
        rho, tops = _spectral_radius(g, idx, np.concatenate(mids))
        for r in range(len(mids)):
            sel = np.flatnonzero(idx == r)
            unstable = rho[sel] >= 1.0
            assert first[r] == (int(np.argmax(unstable)) if unstable.any() else -1)
            assert top[r] == tops[sel[0]]
            tested += mids[r].size
    assert tested > 3 * len(_plants())      # loops with many crossings among them


def _against_interval_test(settings) -> int:
    """wall_stability of _plants() against the interval test alone (_by_intervals) for
    every loop, asserted equal; the number of loops whose K_max is not their first
    crossing gain (or that have none)."""
    plants = _plants()
    got = wall_stability(plants, settings)
    want: list = [None] * len(plants)
    fallback = 0
    for g in _loops(plants, settings):
        cands, thetas = _crossings(g)
        _by_intervals(g, list(range(g.M0.shape[0])), cands, thetas,
                      settings.sample_time_s, want)
        fallback += sum(1 for r, K in enumerate(cands)
                        if not K.size or want[g.rows[r]].k_max_N_per_m != K[0])
    for a, b in zip(got, want, strict=True):
        assert a.k_max_N_per_m == b.k_max_N_per_m
        assert a.unstable_at_zero == b.unstable_at_zero
        np.testing.assert_array_equal(a.f_unstable_hz, b.f_unstable_hz)
    assert any(np.isfinite(w.k_max_N_per_m) for w in want)
    return fallback


@pytest.mark.parametrize("settings", SETTINGS)
def test_k_max_checked_at_the_first_crossing_is_that_of_the_interval_test(settings):
    # wall_stability first probes every loop just below and above its first crossing
    # gain; the reference is the interval test alone for every loop: the same K_max,
    # frequency and flag, loop by loop
    _against_interval_test(settings)


def test_loops_whose_first_crossing_is_no_loss_of_stability_are_among_those_tested():
    # the premise of the test above: at some setting a loop's K_max is not its first
    # crossing gain (or it has none), so the interval test's own path is compared too
    assert sum(_against_interval_test(s) for s in SETTINGS) > 0


# ---------------------------------------------------------------------------
# The adopted model's tables side by side
# ---------------------------------------------------------------------------

def test_adopted_tables_side_by_side_are_those_fitted_in_turn(study):
    spectra, params = study
    # the diagnosis on two workers (its results are those of one: tested above)
    diagnosis = api.diagnose(spectra, api.fit_grip(spectra, jobs=2), jobs=2)
    ad = adopt(diagnosis)
    assert ad.anything
    grip, nominal = api._adopted_tables(spectra, ad, "complex", 2, None)
    kw = dict(cost="complex", bands=ad.bands, effects=ad.effects)
    assert grip.table.equals(api.fit_grip(spectra, **kw).table)
    assert nominal.table.equals(api.fit_nominal(spectra, **kw).table)


def test_screening_tasks_carry_only_the_screened_trials(study):
    # the trials a step's candidates are screened on are made once (screen_trials): a
    # task holds those SCREEN_SUBSET trials, not the axis's; the screening fit on them is
    # screen_candidate's, to the bit (the reference: screen_candidate on the axis)
    from armfit.diagnosis.screen import screen_on, screen_trials
    from armfit.diagnosis.tuning import SCREEN_SUBSET
    spectra, params = study
    data = axis_data(spectra, params, "x")
    band = (float(data.f_hz[0]), float(data.f_hz[-1]))
    base = search._base_task((data, band))
    sub, cur, quick = screen_trials(data, band, base)
    assert data.h.shape[0] == 4 > SCREEN_SUBSET == sub.h.shape[0] == cur.base.shape[0]
    assert quick
    effect = EFFECTS["delay"]
    got = screen_on(sub, cur, quick, band, effect)
    ref = screen_candidate(data, band, base, effect)
    assert repr(got) == repr(ref)
    assert np.array_equal(got.r_db, ref.r_db) and got.shared == ref.shared


def _band_error_written_out(f, r_db, r_deg, se_db, se_deg, lo, hi):
    """band_error as it was computed with every copy held (the reference)."""
    sel = (f >= lo) & (f <= hi)
    rdb, rdeg = r_db[..., sel], r_deg[..., sel]
    sdb, sdeg = se_db[..., sel], se_deg[..., sel]
    with np.errstate(all="ignore"):
        zdb, zdeg = rdb / sdb, rdeg / sdeg
        z = np.concatenate([zdb.ravel(), zdeg.ravel()])
        z = z[np.isfinite(z)]
        rms_norm = float(np.sqrt(np.mean(z * z)))
        mall = np.concatenate([np.nanmean(zdb, axis=0), np.nanmean(zdeg, axis=0)])
        bias = float(np.sqrt(np.nanmean(mall ** 2)))
    return (float(np.sqrt(np.mean(rdb ** 2))), float(np.sqrt(np.mean(rdeg ** 2))),
            rms_norm, int(sel.sum()), bias)


def test_band_errors_and_adequacy_letting_copies_go_early_are_the_same_to_the_bit():
    """The evidence of a fit of many trials lets each band's copies go once used (at
    1,350 trials its transient memory fell from 15 to 9 MB): every band's errors and the
    adequacy's cost are those of the computation written out, bit for bit, with NaN and
    inf residuals and standard errors among them."""
    rng = np.random.default_rng(3)
    T, n = 60, 100
    f = np.geomspace(0.1, 30.0, n)
    r_db, r_deg = 0.3 * rng.normal(size=(T, n)), 2.0 * rng.normal(size=(T, n))
    se_db, se_deg = 0.05 + 0.2 * rng.random((T, n)), 0.5 + rng.random((T, n))
    r_db[2, 10], se_deg[4, 50], r_deg[7, 80] = np.nan, np.inf, np.nan
    for lo, hi in [(0.1, 30.0), (0.3, 3.0), (1.0, 10.0), (5.0, 30.0)]:
        got = band_error(f, r_db, r_deg, se_db, se_deg, lo, hi)
        ref = _band_error_written_out(f, r_db, r_deg, se_db, se_deg, lo, hi)
        # exact equality, NaN where the reference is NaN (a NaN residual in the band)
        assert np.array_equal([got.rms_db, got.rms_deg, got.rms_norm, got.n_points,
                               got.bias_norm], ref, equal_nan=True)
        assert np.isfinite(got.rms_norm) and got.n_points == ref[3] > 0
    fit = joint.JointFit(ClosedLoopModel.for_axis("x"), np.zeros((T, 5)), {}, {}, {},
                         r_db, r_deg, 0.0, 2 * T * n, 0.0, True)
    ad = adequacy(f, fit, se_db, se_deg, (0.1, 30.0), 5 * T)
    with np.errstate(all="ignore"):
        z = np.concatenate([(r_db / se_db).ravel(), (r_deg / se_deg).ravel()])
    assert ad.cost == float(np.nansum(z * z))
    assert ad.overall.rms_norm == _band_error_written_out(f, r_db, r_deg, se_db, se_deg,
                                                          0.1, 30.0)[2]


def test_adequacy_on_views_of_the_band_is_that_of_copies_written_out_to_the_bit():
    """The search judges a fit against views of the band's noise (a slice of the grid,
    not a copy), and the adequacy makes the normalised residuals once, the NaN set to
    0 in place: the Adequacy is the one of the former steps — copies by the band's
    mask, a copy with NaN as 0 for each statistic — bit for bit, with a failing band
    and NaN among the residuals and errors; and with an infinite residual."""
    rng = np.random.default_rng(8)
    T, n = 40, 100
    f = np.geomspace(0.1, 30.0, n)
    band = (0.2, 12.0)
    sel = (f >= band[0]) & (f <= band[1])
    cols, count = band_columns(f, *band)
    assert isinstance(cols, slice) and np.array_equal(np.arange(n)[cols],
                                                      np.flatnonzero(sel))
    assert count == sel.sum()
    m = int(sel.sum())
    fb = f[sel]
    r_db, r_deg = 0.3 * rng.normal(size=(T, m)), 2.0 * rng.normal(size=(T, m))
    r_db[:, 30:40] += 0.8          # a bias of the model over ten points: a failing band
    r_db[3, 5], r_deg[9, 60] = np.nan, np.nan
    se_db, se_deg = 0.05 + 0.2 * rng.random((T, n)), 0.5 + rng.random((T, n))
    se_db[6, np.flatnonzero(sel)[20]] = np.nan
    got = _former_adequacy_and_adequacy(fb, r_db, r_deg, se_db, se_deg, sel, cols, band)
    assert got[1].failing and not got[1].adequate and np.isfinite(got[1].cost)
    assert repr(got[0]) == repr(got[1])
    r_deg[11, 7] = np.inf          # an infinite residual: the cost is infinite
    got = _former_adequacy_and_adequacy(fb, r_db, r_deg, se_db, se_deg, sel, cols, band)
    assert got[1].cost == np.inf and repr(got[0]) == repr(got[1])


def _former_adequacy_and_adequacy(fb, r_db, r_deg, se_db, se_deg, sel, cols, band):
    """(the adequacy by the former steps, on copies by ``sel``; adequacy on views by
    ``cols``) of residuals on the band ``fb``."""
    from armfit.diagnosis.bands import failing_bands, trial_statistics
    from armfit.diagnosis.evidence import Adequacy
    from armfit.diagnosis.tuning import BANDS, MIN_EFFECT_DB, MIN_EFFECT_DEG, MIN_RUN
    T, m = r_db.shape
    fit = joint.JointFit(ClosedLoopModel.for_axis("x"), np.zeros((T, 5)), {}, {}, {},
                         r_db, r_deg, 0.0, 2 * T * m, 0.0, True)
    got = adequacy(fb, fit, se_db[:, cols], se_deg[:, cols], band, 5 * T)
    sdb, sdeg = se_db[:, sel], se_deg[:, sel]
    zdb, zdeg = r_db / sdb, r_deg / sdeg
    with np.errstate(all="ignore"):
        t_db, t_deg = trial_statistics(np.nan_to_num(zdb), np.nan_to_num(zdeg))
    m_db, m_deg = r_db.mean(axis=0), r_deg.mean(axis=0)
    fails = failing_bands(fb, t_db, t_deg, m_db, m_deg,
                          size_db=np.where(np.abs(m_db) > MIN_EFFECT_DB,
                                           np.nan_to_num(zdb).mean(axis=0), 0.0),
                          size_deg=np.where(np.abs(m_deg) > MIN_EFFECT_DEG,
                                            np.nan_to_num(zdeg).mean(axis=0), 0.0))
    overall = band_error(fb, r_db, r_deg, sdb, sdeg, *band)
    bands = tuple(b for b in (band_error(fb, r_db, r_deg, sdb, sdeg, max(lo, band[0]),
                                         min(hi, band[1]))
                              for lo, hi in BANDS if hi > band[0] and lo < band[1])
                  if b.n_points >= MIN_RUN)
    over = tuple(b for b in bands if b.rms_norm > 1.5 and not b.bias_norm <= 1.0)
    z = np.concatenate([zdb.ravel(), zdeg.ravel()])
    nu = max(int(np.isfinite(z).sum()) - 5 * T, 1)
    ref = Adequacy(not fails and not over, overall, bands, over, tuple(fails),
                   float(np.nansum(z * z)), float(nu), float(np.sqrt(2.0 * nu)))
    return ref, got


def test_the_noise_model_of_an_axis_is_made_once_and_every_caller_gets_its_own_arrays():
    # AxisData.noise_se keeps the noise model's standard errors of the whole grid of a
    # small axis (made once: each joint problem and each choice of start rows asks for
    # them), not those of a large one (held for the search's length): each call
    # is what armfit.noise.standard_errors gives afresh (independent computation), NaN
    # at the excluded points, restricted to the band after; a caller may change what it
    # got; and the kept errors are not pickled with the trials (a task's payload)
    import pickle

    from armfit import noise
    from armfit.diagnosis import responses
    from armfit.diagnosis.responses import AxisData
    rng = np.random.default_rng(5)
    T, n = 4, 60
    se_db = rng.uniform(0.01, 2.0, (T, n))
    se_db[1, 7] = np.nan
    se_deg = rng.uniform(0.1, 20.0, (T, n))
    excluded = np.zeros((T, n), bool)
    excluded[2, 40:45] = True
    data = AxisData("x", np.geomspace(0.1, 30.0, n), np.ones((T, n), complex), se_db,
                    se_deg, ({},) * T, excluded=excluded)
    want_db, want_deg = noise.standard_errors(se_db, se_deg)
    want_db[excluded], want_deg[excluded] = np.nan, np.nan
    sel = (data.f_hz >= 1.0) & (data.f_hz <= 10.0)
    for s in (slice(None), sel, slice(5, 50)):
        got_db, got_deg = data.noise_se(s)
        np.testing.assert_array_equal(got_db, want_db[:, s])
        np.testing.assert_array_equal(got_deg, want_deg[:, s])
        got_db[:] = -1.0
        got_deg[:] = -1.0
    np.testing.assert_array_equal(data.noise_se()[0], want_db)
    assert "_noise_kept" in data.__dict__
    back = pickle.loads(pickle.dumps(data))
    assert "_noise_kept" not in back.__dict__
    assert len(pickle.dumps(data)) == len(pickle.dumps(back))
    np.testing.assert_array_equal(back.noise_se()[1], want_deg)
    # an axis of more than NOISE_KEPT_BYTES of standard errors: made at each call, the
    # same numbers, nothing held
    big_T = responses.NOISE_KEPT_BYTES // (16 * n) + 1
    rows = np.arange(big_T) % T
    big = AxisData("x", data.f_hz, data.h[rows], se_db[rows], se_deg[rows],
                   ({},) * big_T, excluded=excluded[rows])
    np.testing.assert_array_equal(big.noise_se(sel)[0], want_db[rows][:, sel])
    assert "_noise_kept" not in big.__dict__
