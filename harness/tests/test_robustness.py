"""The robustness matrix in its fast form (harness/robustness.py, docs/robustness.md),
cell by cell: every scene × DC/IC × N_w ∈ {1, 5, batch} × dt ∈ {1, 5, 10, 20} ms.

A cell passes when it converges, or when it stops as ill-posed where that is the right
answer (ILL_POSED). The cells that fail today are KNOWN_FAILING, strictly: a newly
failing cell fails the test, and a fixed one shows up as XPASS(strict) until its entry
goes. The selected cells run once, as tasks of a local Dask cluster (one worker per
core; harness/sweep.py), before the first test."""
import math
import os
import time

import pytest

import mbfg
from harness import robustness as rb
from harness.sweep import Sweep

# Scene × coordinates whose motion reaches a configuration the independent coordinates
# do not determine: stopping ahead of it (ill-posed) is the right answer there. An
# ill-posed stop anywhere else fails.
ILL_POSED = {
    ("hard/parallelogram", "ic"),         # every link flat at t = π/6 s
    ("benchmarks/n-fourbar-1", "ic"),     # every link flat at t ≈ 0.72 s
    ("benchmarks/n-fourbar-5", "ic"),
    ("benchmarks/n-fourbar-10", "ic"),
    ("benchmarks/n-fourbar-40", "ic"),
}

# Cell id → why it fails today: every cell of a fresh `python -m harness.robustness --fast`
# that `acceptable` refuses.
KNOWN_FAILING: dict[str, str] = {}


def acceptable(o: rb.Outcome) -> bool:
    return o.status == "converged" or (o.status == "ill-posed" and (o.scene, o.coords) in ILL_POSED)


def explain(o: rb.Outcome) -> str:
    """What a failing cell says, how to rerun it and what to do about it."""
    cell = o.cell
    kw = "batch=True" if cell.window == "batch" else f"window={cell.window}"
    scene = str(cell.path.relative_to(rb.ROOT))
    lines = [f"{cell.label()}, t_end = {o.t_end:g} s: {o.status}: {o.cause}",
             f"  rerun: {cell.command(o.t_end)}",
             f"     or: mbfg.simulate({scene!r}, coords={cell.coords!r}, dt={cell.dt:g}, "
             f"t_end={o.t_end:g}, {kw})"]
    if o.status == "ill-posed":
        lines.append(f"  ({o.scene!r}, {o.coords!r}) is not in ILL_POSED (harness/tests/"
                     "test_robustness.py): if the motion does reach a configuration its independent "
                     "coordinates do not determine, add it there; otherwise the stop is false.")
    else:
        lines.append(f"  If this failure is expected now, add {cell.id!r} to KNOWN_FAILING in "
                     "harness/tests/test_robustness.py with the reason.")
    return "\n".join(lines)


CELLS, _ = rb.matrix(rb.scenes(), fast=True)


def params():
    for cell in CELLS:
        why = KNOWN_FAILING.get(cell.id)
        marks = [pytest.mark.xfail(strict=True, reason=f"{why} (when it passes, remove "
                                   f"{cell.id!r} from KNOWN_FAILING)")] if why else []
        yield pytest.param(cell, id=cell.id, marks=marks)


@pytest.fixture(scope="module")
def outcomes(request):
    """The selected cells of the fast matrix, run once."""
    wanted = [item.callspec.params["cell"] for item in request.session.items
              if getattr(item, "function", None) is test_cell]
    return {o.cell: o for o in rb.run_cells(wanted, fast=True, progress=lambda _: None)}


@pytest.mark.parametrize("cell", params())
def test_cell(cell, outcomes):
    o = outcomes[cell]
    assert acceptable(o), explain(o)


def test_known_failing_names_cells():
    stale = set(KNOWN_FAILING) - {c.id for c in CELLS}
    assert not stale, f"KNOWN_FAILING names cells the fast matrix does not have: {sorted(stale)}"


# ---------------------------------------------------------------- the classifier

ILL_POSED_MESSAGE = (
    "singular configuration at t ≈ 0.523599 s (extrapolated): independent coordinates "
    "[theta] stop determining [P1.x, P1.y, P2.x, P2.y] (rank 3 < 4); stopped at step 521 "
    "(t = 0.521 s), distance to rank loss 5.0e-3")
ILL_POSED_FAILURE = {"kind": "singular-configuration", "message": ILL_POSED_MESSAGE, "step": 521,
             "t": 0.521, "located_t": 0.5235988750573793, "independent": ["theta"],
             "dependent": ["P1.x", "P1.y", "P2.x", "P2.y"], "rank": 3, "full_rank": 4,
             "distance": 5.0e-3}


def test_ill_posed_stop_is_classified_with_its_cause():
    v = rb.classify(ILL_POSED_FAILURE, ILL_POSED_MESSAGE)
    assert (v.status, v.step, v.t) == ("ill-posed", 521, 0.521)
    assert v.cause == ("singular configuration at t ≈ 0.523599 s: [theta] do not determine "
                       "the others (rank 3 < 4)")


@pytest.mark.parametrize("failure, step, t", [
    # A solve that did not converge, near a singular configuration: failed, whatever
    # the hint says.
    ({"kind": "not-converged", "step": 708, "t": 0.708, "termination": "iteration limit",
      "constraint_conditioning": 9.1e-4}, 708, 0.708),
    ({"kind": "not-converged", "step": 1, "t": 0.02, "termination": "diverged"}, 1, 0.02),
    # No step named.
    ({"kind": "position-problem", "step": None, "t": None}, None, None),
    # No structured failure at all (a SolveError made by hand).
    (None, None, None),
])
def test_other_solve_errors_fail_with_step_and_time(failure, step, t):
    v = rb.classify(failure, "the message")
    assert (v.status, v.cause, v.step, v.t) == ("failed", "the message", step, t)


def test_exceptions_other_than_solve_errors_are_errors():
    # A SolveError as the module raises it: classified by its failure, not its text.
    with pytest.raises(mbfg.SolveError) as info:
        mbfg.simulate(rb.scene_path("hard/parallelogram"), coords="ic", dt=1e-2, t_end=1.0)
    v = rb.verdict_of(info.value)
    assert v.status == "ill-posed" and v.step == info.value.failure["step"]
    assert rb.verdict_of(mbfg.SolveError("step 3 (t = 0.003 s) did not converge")).status == "failed"
    v = rb.verdict_of(BaseException("called `Option::unwrap()` on a `None` value"))
    assert v == rb.Verdict("error", "BaseException: called `Option::unwrap()` on a `None` value")


def test_summary_counts_and_names():
    def o(status, scene="fourbar", coords="dc"):
        return rb.Outcome(scene, coords, 1, 1e-3, 1.0, status)
    line = rb.summary([o("converged"), o("converged"), o("n/a", coords="ic"),
                       o("ill-posed", "hard/parallelogram", "ic"),
                       o("ill-posed", "hard/parallelogram", "ic"), o("failed"), o("error"),
                       o("skipped")])
    assert line == ("robustness: 2 of 7 cells converge, 2 ill-posed stops (hard/parallelogram "
                    "IC ×2), 2 failed (1 with an error), 1 skipped")


# ---------------------------------------------------------------- plan and pool

def test_horizons_are_capped():
    fine = rb.Cell("fourbar", "dc", "batch", 1e-4)
    assert rb.planned_t_end(fine, fast=False) == pytest.approx(rb.BATCH_STEPS * 1e-4)
    assert rb.planned_t_end(rb.Cell("fourbar", "dc", 10, 1e-4), fast=False) == rb.FINE_HORIZON
    assert rb.planned_t_end(rb.Cell("fourbar", "dc", 1, 2e-2), fast=False) == 5.0   # its reference
    assert rb.planned_t_end(rb.Cell("fourbar", "dc", 1, 2e-2), fast=True) == rb.FAST_HORIZON
    steps = rb.planned_t_end(rb.Cell("driven/slider-crank-docs", "dc", 1, 1e-3), fast=False) / 1e-3
    assert math.isclose(steps, rb.DEFAULT_HORIZON / 1e-3)


def test_scene_without_independent_coordinates_has_no_ic_cells():
    run, na = rb.matrix(["fourbar"], fast=True)
    assert {c.coords for c in run} == {"dc"}
    assert len(na) == len(rb.FAST_WINDOWS) * len(rb.FAST_DTS)
    assert {o.status for o in na} == {"n/a"}


# In this process (a sweep without Dask), so that the monkeypatches hold in the cells.
SERIAL = Sweep("serial")


def test_a_crashed_cell_is_an_error(monkeypatch):
    monkeypatch.setattr(rb, "run_cell", lambda *args: os._exit(3))
    [o] = rb.run_cells([rb.Cell("pendulum", "dc", 1, 2e-2)], fast=True, progress=lambda _: None,
                       sweep=SERIAL)
    assert o.status == "error" and "exit code 3" in o.cause


def spin(*args):
    while True:
        pass


def test_a_cell_over_the_time_limit_is_shortened_then_skipped(monkeypatch):
    # Busy: stopped by its CPU-time limit (whole seconds: 1 s here).
    monkeypatch.setattr(rb, "run_cell", spin)
    monkeypatch.setitem(rb.KILL_AFTER, True, 0.2)
    [o] = rb.run_cells([rb.Cell("pendulum", "dc", 1, 2e-2)], fast=True, progress=lambda _: None,
                       sweep=SERIAL)
    assert o.status == "skipped"
    assert o.cause == "killed after 0.2 s of CPU time at t_end = 1, 0.5, 0.24 s"


def test_a_cell_stuck_without_using_the_cpu_is_stopped_by_the_wall_clock(monkeypatch):
    monkeypatch.setattr(rb, "run_cell", lambda *args: time.sleep(60))
    monkeypatch.setitem(rb.KILL_AFTER, True, 0.2)
    began = time.perf_counter()
    [o] = rb.run_cells([rb.Cell("pendulum", "dc", 1, 2e-2)], fast=True, progress=lambda _: None,
                       sweep=SERIAL)
    assert o.status == "skipped"
    assert time.perf_counter() - began < 3 * rb.WALL_FACTOR * 0.2 + 10
