"""calib_core.parallel.pmap and Ahead: the loop's answers from forked processes, errors and shared objects carried
back, helpers that die with their parent; and a diagnosis in two processes giving the answer of one."""
from __future__ import annotations

import dataclasses
import os
import select
import signal
import subprocess
import sys
import textwrap
import time

import numpy as np
import pytest

from calib_core.datasets import available, motoman_leica
from calib_core.diagnosis import diagnose
from calib_core.diagnosis.masses import _mass_driven
from calib_core.model import parse_model
from calib_core.parallel import MAX_ITEMS, Ahead, one_blas_thread, pmap
from calib_core.robots import arm6, spray7
from calib_world import World, null_world
from calib_world.scenarios import hide
from threadpoolctl import threadpool_info, threadpool_limits


@pytest.mark.parametrize("workers", [1, 2, 3, 5])
@pytest.mark.parametrize("n", [0, 1, 2, 7])
def test_pmap_gives_the_loop_in_order(workers, n):
    items = list(np.random.default_rng(n).normal(size=n))
    assert pmap(lambda v: v * 2.0, items, workers) == [v * 2.0 for v in items]


def _slow(fn, s: float = 0.1):
    """fn after a pause: every process then takes a share of a few items (each takes the next one free)."""
    def part(item):
        time.sleep(s)
        return fn(item)
    return part


def test_more_items_than_the_queue_holds_are_done_in_order():
    n = MAX_ITEMS + 1
    assert pmap(lambda i: (i, os.getpid()), range(n), 2) == [(i, os.getpid()) for i in range(n)]


def test_pmap_runs_parts_in_other_processes():
    pids = pmap(_slow(lambda _: os.getpid()), range(10), 2)
    assert os.getpid() in pids and len(set(pids)) == 2


def _blas_threads(_=None) -> list[int]:
    return [p["num_threads"] for p in threadpool_info() if p["user_api"] == "blas"]


def test_parts_and_a_diagnosis_run_on_one_blas_thread_each():
    """Forked parts on two BLAS threads each oversubscribe the cores (the Motoman's search ran 3x slower); the
    caller's own count is back after."""
    with threadpool_limits(2, user_api="blas"):
        assert set(_blas_threads()) == {2}, threadpool_info()
        inside = pmap(_blas_threads, range(4), workers=2)
        assert all(set(t) == {1} for t in inside), inside
        assert set(one_blas_thread(_blas_threads)()) == {1}
        assert set(_blas_threads()) == {2}


@pytest.mark.parametrize("where", ["parent", "child"])
def test_a_part_that_raises_raises_in_the_caller(where):
    parent = os.getpid()

    def part(i):
        if (os.getpid() == parent) == (where == "parent"):
            raise ValueError(f"part {i} cannot be fitted")
        return i

    with pytest.raises(ValueError, match="part .* cannot be fitted"):
        pmap(_slow(part), range(10), 2)

    class Odd(Exception):
        def __reduce__(self):
            raise TypeError("not picklable")

    def odd(i):
        if os.getpid() != parent:
            raise Odd("odd")
        return i

    with pytest.raises(RuntimeError, match="Odd"):
        pmap(_slow(odd), range(10), 2)


def test_the_parts_of_a_helper_that_died_are_done_again():
    parent = os.getpid()

    def part(i):
        if os.getpid() != parent:
            os.kill(os.getpid(), signal.SIGKILL)  # out of memory, say
        return i * i

    assert pmap(_slow(part), range(10), 2) == [i * i for i in range(10)]


def test_shared_objects_come_back_as_themselves():
    model = parse_model(spray7())
    out = pmap(_slow(lambda i: (model, os.getpid())), range(10), 2, shared=(model,))
    assert all(m is model for m, _ in out) and any(pid != os.getpid() for _, pid in out)
    copies = pmap(_slow(lambda i: (model, os.getpid())), range(10), 2)
    assert {m is model for m, pid in copies} == {True, False}
    assert all(m.joint_names == model.joint_names for m, _ in copies)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="PR_SET_PDEATHSIG is Linux's")
def _mostly_zero(seed: int) -> list[np.ndarray]:
    """Arrays as a screening worker sends back (bases of effects through a few joints): mostly zeros, -0.0 among them,
    a NaN and an infinity, in C and F order and as a strided view."""
    rng = np.random.default_rng(seed)
    a = np.zeros((400, 23, 6))
    a[:, rng.integers(23), :] = rng.standard_normal((400, 6))
    a[::3, rng.integers(23), :] = -0.0
    a[1, 2, 3], a[2, 3, 4] = np.nan, -np.inf
    return [a, np.asfortranarray(a), a.T, a[::2], rng.standard_normal((200, 100))]  # the last one dense


def test_mostly_zero_arrays_come_back_with_the_same_bits_and_layout(seed):
    here = _mostly_zero(seed)
    there = [out for pid, out in pmap(_slow(lambda i: (os.getpid(), _mostly_zero(seed))), range(4), 2)
             if pid != os.getpid()]
    assert there  # made in a helper, pickled back
    for a, b in zip(here, there[0]):
        assert a.shape == b.shape and a.flags.f_contiguous == b.flags.f_contiguous
        assert np.array_equal(np.ascontiguousarray(a).view(np.uint64), np.ascontiguousarray(b).view(np.uint64))


def test_mostly_zero_arrays_travel_as_their_nonzeros(seed):
    import io

    from calib_core.parallel import _Pickler

    a = _mostly_zero(seed)[0]
    buf = io.BytesIO()
    _Pickler(buf, ()).dump(a)
    assert len(buf.getvalue()) < 0.15 * a.nbytes  # a sixth of it nonzero, and a bit per element for the signs


def test_a_helper_dies_with_its_parent(tmp_path):
    pid_file = tmp_path / "child.pid"
    script = textwrap.dedent(f"""
        import os, time
        from calib_core.parallel import MAX_ITEMS, pmap
        def part(i):
            if i == 1:
                open({str(pid_file)!r}, "w").write(str(os.getpid()))
            time.sleep(60)
        pmap(part, range(2), 2)
    """)
    parent = subprocess.Popen([sys.executable, "-c", script])
    try:
        t_end = time.monotonic() + 30
        while not (pid_file.exists() and pid_file.read_text()) and time.monotonic() < t_end:
            time.sleep(0.05)
        child = int(pid_file.read_text())
        os.kill(parent.pid, signal.SIGKILL)
        parent.wait(10)
        t_end = time.monotonic() + 5
        while time.monotonic() < t_end and _alive(child):
            time.sleep(0.05)
        assert not _alive(child)
    finally:
        parent.kill()


def _alive(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().split(")")[-1].split()[0] != "Z"  # a zombie is gone, its parent just has not reaped it
    except FileNotFoundError:
        return False


def test_a_diagnosis_in_two_processes_gives_the_answer_of_one():
    """Drawn: the seed, a play (its search runs per joint apart), a spring (rival fits apart) or a cable pulled by a
    joint (nothing named: the smooth field fitted beside the search for what the residual follows), its size.

    The same findings and prose; the numbers to rounding, not always to the bit: a part done in a forked process
    allocates its arrays at other addresses, and numpy's SIMD sums follow memory alignment (a hard play: x differed by
    7e-13 and 1.3e-12 mm between runs in two processes on 2 of 6 seeds, before this test said so; one process is
    the same to the bit from run to run)."""
    seed = int(np.random.default_rng().integers(2**31))
    rng = np.random.default_rng(seed)
    model = parse_model(spray7())
    world = World(model, seed)
    kind = str(rng.choice(["hard_backlash", "joint_spring", "cable_force"]))
    info = hide(world, kind, float(rng.uniform(2.0, 5.0)), rng)
    meas = world.measure(info["q"], payload_kg=info["payload_kg"], temperature=info["temperature"])
    one, two = diagnose(model, meas, workers=1), diagnose(model, meas, workers=2)
    same = [(f["kind"], f["joints"], f.get("correction"), f["evidence"]) for f in one.findings]
    assert [(f["kind"], f["joints"], f.get("correction"), f["evidence"]) for f in two.findings] == same, (seed, kind)
    assert two.explanation == one.explanation, (seed, kind)
    a, b = one.calibration, two.calibration
    close = dict(rtol=1e-9, atol=1e-9, err_msg=f"seed {seed}, {kind}")
    np.testing.assert_allclose(b.x, a.x, **close)
    np.testing.assert_allclose(b.holdout_residual_mm, a.holdout_residual_mm, **close)
    # what the findings' chained refits and the answer's doubts set, side by side in two processes
    figures = lambda d: [[f.get(k, np.nan) for k in ("holdout_rms_before_mm", "holdout_rms_after_mm")]  # noqa: E731
                         for f in d.findings]
    np.testing.assert_allclose(figures(two), figures(one), **close)
    assert [type(e) for e in b.effects] == [type(e) for e in a.effects], (seed, kind)
    np.testing.assert_allclose([getattr(e, "switch_width", 0.0) for e in b.effects],
                               [getattr(e, "switch_width", 0.0) for e in a.effects], **close)
    assert len(b.mass_doubt) == len(a.mass_doubt), (seed, kind)
    for u, v in zip(a.mass_doubt[1:], b.mass_doubt[1:]):
        np.testing.assert_allclose(v, u, **close)
    if any(_mass_driven(e) for e in a.effects):  # the doubt of the mass data is on the answer
        assert len(a.mass_doubt) == 3, (seed, kind)


def test_ahead_computes_in_another_process_and_carries_back_answers_errors_and_shared_objects():
    model = parse_model(spray7())
    here = os.getpid()
    got, pid = Ahead(lambda: (model, os.getpid()), shared=(model,)).result()
    assert got is model and pid != here
    with pytest.raises(ZeroDivisionError):
        Ahead(lambda: 1 / 0).result()


def test_ahead_done_here_when_its_child_died_and_stopped_when_cancelled():
    parent = os.getpid()

    def killed():
        if os.getpid() != parent:
            os.kill(os.getpid(), signal.SIGKILL)  # out of memory, say
        return 42

    assert Ahead(killed).result() == 42
    slow = Ahead(lambda: time.sleep(60))
    pid = slow.pid
    slow.cancel()
    assert slow.pid is None and not _alive(pid)


class _Eager(Ahead):
    """An Ahead whose child has ended before the search goes on: the search settles it at its next look (late()),
    within its first rounds (a job's attempt 2 on the Motoman did, and began a second one: '_Settled' escaped)."""

    def __init__(self, fn, shared=()):
        super().__init__(fn, shared)
        if self.pid is not None:
            select.select([self.read], [], [])


class _Died(Ahead):
    """An Ahead whose child dies without answering (out of memory, an operator's kill): its answer is computed here
    when asked for, after the search has gone on."""

    def __init__(self, fn, shared=()):
        parent = os.getpid()
        super().__init__(lambda: fn() if os.getpid() == parent else os._exit(1), shared)


@pytest.mark.skipif(not available(), reason="../shared/datasets not present")
@pytest.mark.parametrize("draw, taken", [(2, True), (5, False)])
@pytest.mark.parametrize("child", [Ahead, _Eager, _Died])
def test_a_sparser_search_begun_ahead_gives_the_answer_in_order(monkeypatch, draw, taken, child):
    """On a third of the Motoman's poses (drawn by `draw`, without the measurement order) the search takes the
    compliance of every joint on identified loads, which asks _sparser's search for causes on single joints: two
    processes begin it in a child while the search goes on as if it were not taken (_Search.settle). On draw 2 it is
    taken (the work done meanwhile is dropped and the search goes on from where the child left it), on draw 5 not
    (the search keeps what it did meanwhile). Either way, whether the search begun ahead ends late or at once
    (_Eager), or its child dies and it is done here from the search as it was begun (_Died: it was done from the
    search as it had gone on since, and a job whose helper was killed answered the Motoman with another model), the
    answer is that of one process."""
    from calib_core.diagnosis import search as S
    from calib_core.io import parse_measurements

    begun = []  # where each Ahead was begun (the robust fit and the smooth correction are begun ahead too)
    monkeypatch.setattr(S, "Ahead", lambda fn, shared: begun.append(fn.__qualname__) or child(fn, shared))
    ds = motoman_leica()
    model = parse_model(ds.model)
    meas = parse_measurements(ds.csv_text, model)
    third = np.sort(np.random.default_rng(draw).permutation(meas.n_poses)[:meas.n_poses // 3])
    meas = dataclasses.replace(meas.subset(third), sequence=None)
    one, two = diagnose(model, meas, workers=1), diagnose(model, meas, workers=2)
    assert any("_round" in b for b in begun), f"the sparser search was not begun ahead: {begun}"
    assert [(f["kind"], f["joints"], f["evidence"]) for f in two.findings] == \
        [(f["kind"], f["joints"], f["evidence"]) for f in one.findings]
    assert two.explanation == one.explanation and two.rejected == one.rejected
    np.testing.assert_allclose(two.calibration.x, one.calibration.x, rtol=1e-9, atol=1e-9)
    assert any("on single joints do better" in r["why"] for r in one.rejected) == taken, one.rejected


class _Done:
    """A search begun ahead that has ended with `answer` (Ahead's face: ready, result, cancel)."""

    def __init__(self, answer):
        self.answer, self.cancelled = answer, False

    def ready(self):
        return True

    def result(self):
        return self.answer

    def cancel(self):
        self.cancelled = True


def _bare_search(**kw):
    from calib_core.diagnosis.fitter import _Fitter
    from calib_core.diagnosis.search import _Search

    fit = _Fitter(model=None, meas=None, loss=None, folds=5, free=None, prior_scale=1.0, workers=1)
    return _Search(model=None, meas=None, sigma=None, alpha=0.01, fit=fit, floor=0.1, pool=[], load_pool={},
                   current="mine", x_ref=None, ahead=True, **kw)


@pytest.mark.parametrize("taken", [True, False])
def test_a_search_begun_ahead_is_settled_once(taken):
    """Settled (taken or not), the search begins no second one: on the Motoman with its order (all 586 poses) a
    search taken within the first rounds left `ahead` on, the search from where it left began another, and its
    settling escaped the diagnosis ('_Settled', a failed job). Taken, the state comes back and _poll says so."""
    from calib_core.diagnosis.search import _Settled

    state = {"chosen": ["c"], "findings": [{}], "current": "theirs", "x_ref": None, "rejected": [], "untested": None,
             "play_memo": [], "last": []}
    search = _bare_search(pending=[(_Done((taken, state)), 2)])
    if taken:
        with pytest.raises(_Settled):
            search._poll()
    else:
        search._poll()
    assert not search.ahead and not search.pending and search.fit.workers == 2
    assert search.current == ("theirs" if taken else "mine") and search.chosen == (["c"] if taken else [])


@pytest.mark.parametrize("bad", [False, True])
def test_the_robust_fit_made_beside_the_plain_selection_gives_the_answer_in_order(bad):
    """`auto`'s first robust fit is made in a child while the geometry is selected on plain least squares here (the
    loss of every real set). Drawn: the seed and the robot, and with `bad`, 4-8 consecutive readings 200-2000 mm off
    (Huber then: the plain selection is dropped and made again on it). The loss, the outliers and the answer are
    those of one process."""
    seed = int(np.random.default_rng().integers(2**31))
    rng = np.random.default_rng(seed)
    model = parse_model(arm6() if seed % 2 else spray7())
    meas = null_world(model, seed).campaign(n=80).meas
    if bad:
        m = int(rng.integers(4, 9))
        k = int(rng.integers(0, meas.n_poses - m))
        way = rng.normal(size=(m, 3))
        points = meas.points.copy()
        points[k:k + m] += way / np.linalg.norm(way, axis=1, keepdims=True) * rng.uniform(200.0, 2000.0, (m, 1))
        meas = dataclasses.replace(meas, points=points)
    one, two = diagnose(model, meas, workers=1), diagnose(model, meas, workers=2)
    assert two.loss == one.loss and (one.loss == "huber" or not bad), seed
    assert two.calibration.metrics()["outliers"] == one.calibration.metrics()["outliers"], seed
    assert [two.selection[k] for k in ("chosen", "best", "prior_scale", "free")] == \
        [one.selection[k] for k in ("chosen", "best", "prior_scale", "free")], seed
    assert two.explanation == one.explanation, seed
    np.testing.assert_allclose(two.calibration.x, one.calibration.x, rtol=1e-9, atol=1e-9, err_msg=str(seed))


def test_a_smooth_correction_begun_ahead_is_used_for_its_model_alone():
    """The smooth correction begun ahead (_Search.speculate) leaves the search one process while it runs; it is
    handed over for the very model it was begun for, and dropped (its child stopped, the processes given back) as
    soon as the search's model changes."""
    began = _Done("field")
    search = _bare_search(speculated=[(("mine", [], None), began, 2)])
    assert search.speculation() is began and not began.cancelled
    assert search.fit.workers == 2 and not search.speculated
    moved = _Done("field")
    search = _bare_search(speculated=[(("mine", [], None), moved, 2)])
    search.current = "theirs"
    search._poll()
    assert moved.cancelled and search.fit.workers == 2 and not search.speculated
    other = _Done("field")
    search = _bare_search(speculated=[(("mine", [], None), other, 2)])
    search.chosen = ["a cause"]
    assert search.speculation() is None and other.cancelled and search.fit.workers == 2


class _Running(_Done):
    """A _sparser search begun ahead that has not ended yet (until `done`)."""

    def __init__(self, answer):
        super().__init__(answer)
        self.done = False

    def ready(self):
        return self.done


@pytest.mark.parametrize("moved", [False, True])
def test_a_smooth_correction_asked_for_beside_a_sparser_search_begins_once_it_has_settled(monkeypatch, moved):
    """Asked for while the _sparser search begun ahead still runs (two processes busy: the Motoman's revisits began
    0.02 s before it ended), the smooth correction is begun when that search settles, not taken, and only if the
    search's model is still the one it was asked for."""
    from calib_core.diagnosis import search as S

    begun = []
    monkeypatch.setattr(S, "_excess", lambda cal, floor: 0.0)  # structure left for a correction
    monkeypatch.setattr(S, "Ahead", lambda fn, shared: begun.append(fn) or _Done("field"))
    state = {"chosen": [], "findings": [], "current": "mine", "x_ref": None, "rejected": [], "untested": None,
             "play_memo": [], "last": []}
    sparser = _Running((False, state))
    search = _bare_search(pending=[(sparser, 2)])
    search.speculate()
    assert not begun and search.wanted is not None and search.fit.workers == 1
    if moved:
        search.current = "theirs"
    sparser.done = True
    search._poll()
    assert not search.pending and search.wanted is None
    if moved:
        assert not begun and not search.speculated and search.fit.workers == 2
    else:
        assert len(begun) == 1 and search.speculated and search.fit.workers == 1
        assert search.speculation() is not None and search.fit.workers == 2
