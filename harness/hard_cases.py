"""The hard-case stability suite (scenes/hard/): each case with explicit pass criteria.

A case passes when every run has no failed solve, stays on the reference branch,
keeps |Φ| below its bound and meets its error/energy bound — or, where the problem
itself is ill-posed, stops with the status that names the step and the cause (the
parallelogram in independent coordinates). `make test` runs the fast form (pytest,
harness/tests/test_hard_cases.py); `make report` the full one.

    python -m harness.hard_cases [--fast] [--scheduler ADDRESS]   # prints the pass table
"""
from __future__ import annotations

import argparse
import dataclasses
import math
import pathlib
import sys
import time

import numpy as np

import mbfg
from harness import reference as refs
from harness import sweep as sweeps
from harness import trajectory as tj

ROOT = pathlib.Path(__file__).resolve().parent.parent
HARD = ROOT / "scenes" / "hard"
PHI_BOUND = 1e-9


@dataclasses.dataclass
class Outcome:
    case: str
    setting: str
    passed: bool
    figures: str
    criteria: str
    wall_time: float


def run(scene, **kw):
    """A forward run; a solve that does not converge comes back as its message."""
    r, err, _ = run_with_failure(scene, **kw)
    return r, err


def run_with_failure(scene, **kw):
    """A forward run; a run that stopped comes back as its message and its
    structured failure (SolveError.failure: kind, step, t and the cause's fields)."""
    try:
        return mbfg.simulate(scene, **kw), None, None
    except mbfg.SolveError as e:
        return None, str(e), e.failure


def failed(case, setting, criteria, message, start) -> Outcome:
    return Outcome(case, setting, False, f"stopped: {message}", criteria, time.perf_counter() - start)


def parallelogram(dts, coords):
    """Five flat configurations in 5 s; exact motion θ = π/2 + 3t, coupler horizontal.
    In independent coordinates (θ alone) the first flat point is ill-posed: there θ
    does not determine P2's velocity. That run passes only by stopping ahead of it
    with the singular-configuration status, located within 3 steps of π/6."""
    criteria = ("converges; |θ − (π/2 + 3t)| ≤ 1e-3 rad; |y₁ − y₂| ≤ 1e-6 m (parallelogram branch); "
                "energy error ≤ 1e-3 J; |Φ| ≤ 1e-9")
    ill_posed = ("ill-posed at the first flat point (θ does not determine P2's velocity there): "
                 "stops with the singular-configuration status naming theta and rank 3 < 4, the "
                 "configuration located within 3 steps of π/6, the stop within 10 ms before it")
    scene = HARD / "parallelogram.yaml"
    flat = math.pi / 6
    for c in coords:
        for dt in dts:
            start = time.perf_counter()
            setting = f"{c.upper()}, dt = {dt:g} s, N_w = 1"
            r, err, failure = run_with_failure(scene, coords=c, dt=dt, t_end=5.0)
            if c == "ic":
                if not failure or failure["kind"] != "singular-configuration":
                    figures = f"stopped: {err}" if err else "ran through the flat point"
                    yield Outcome("parallelogram", setting, False, figures, ill_posed,
                                  time.perf_counter() - start)
                    continue
                located, stop = failure["located_t"], failure["t"]
                ok = (failure["independent"] == ["theta"]
                      and (failure["rank"], failure["full_rank"]) == (3, 4)
                      and abs(located - flat) <= 3 * dt and flat - 0.01 <= stop < flat)
                yield Outcome("parallelogram", setting, ok,
                              f"ill-posed, detected: singular configuration located at t = {located:.6f} s "
                              f"({(located - flat) / dt:+.2f} steps from π/6); stopped at step {failure['step']} "
                              f"(t = {stop:g} s, {(flat - stop) * 1e3:.1f} ms before it)",
                              ill_posed, time.perf_counter() - start)
                continue
            if err:
                yield failed("parallelogram", setting, criteria, err, start)
                continue
            theta = r.column("q:theta")
            theta_err = float(np.max(np.abs(theta - (math.pi / 2 + 3 * r.t))))
            branch = float(np.max(np.abs(r.column("q:P1.y") - r.column("q:P2.y"))))
            flats = int(np.sum(np.diff(np.floor(theta / math.pi)) != 0))
            energy = r.summary["energy_drift"]
            ok = (theta_err <= 1e-3 and branch <= 1e-6 and energy <= 1e-3
                  and r.summary["worst_phi"] <= PHI_BOUND and flats == 5)
            yield Outcome("parallelogram", setting, ok,
                          f"{flats} flats passed; θ error {theta_err:.1e} rad; |y₁ − y₂| {branch:.1e} m; "
                          f"energy {energy:.1e} J; |Φ| {r.summary['worst_phi']:.0e}",
                          criteria, time.perf_counter() - start)


def dead_centres(coords):
    """Slider-crank through five dead centres without gravity: energy is conserved."""
    criteria = "converges; ≥ 5 dead centres passed, θ monotone; energy error ≤ 1e-3 J; |Φ| ≤ 1e-9"
    scene = HARD / "slider-crank-dead-centres.yaml"
    for c in coords:
        start = time.perf_counter()
        setting = f"{c.upper()}, dt = 1 ms, N_w = 1, 5 s"
        r, err = run(scene, coords=c, dt=1e-3, t_end=5.0)
        if err:
            yield failed("slider-crank dead centres", setting, criteria, err, start)
            continue
        theta = r.column("q:theta")
        centres = int(np.sum(np.diff(np.floor(theta / math.pi)) != 0))
        monotone = bool(np.all(np.diff(theta) > 0))
        energy = r.summary["energy_drift"]
        ok = centres >= 5 and monotone and energy <= 1e-3 and r.summary["worst_phi"] <= PHI_BOUND
        yield Outcome("slider-crank dead centres", setting, ok,
                      f"{centres} dead centres; θ monotone: {monotone}; energy {energy:.1e} J; "
                      f"|Φ| {r.summary['worst_phi']:.0e}", criteria, time.perf_counter() - start)


def long_run(t_end, coords):
    """The four-bar for a minute: energy drift stays bounded."""
    criteria = "converges; energy drift ≤ 1e-2 J (E ≈ 30 J swings); |Φ| ≤ 1e-9"
    for c in coords:
        scene = ROOT / "scenes" / ("fourbar.yaml" if c == "dc" else "fourbar-theta.yaml")
        start = time.perf_counter()
        setting = f"{c.upper()}, dt = 1 ms, N_w = 1, {t_end:g} s"
        r, err = run(scene, coords=c, dt=1e-3, t_end=t_end)
        if err:
            yield failed(f"four-bar {t_end:g} s", setting, criteria, err, start)
            continue
        energy = r.summary["energy_drift"]
        ok = energy <= 1e-2 and r.summary["worst_phi"] <= PHI_BOUND
        yield Outcome(f"four-bar {t_end:g} s", setting, ok,
                      f"energy drift {energy:.2e} J; |Φ| {r.summary['worst_phi']:.0e}; "
                      f"{r.summary['mean_iterations']:.2f} LM iterations per step", criteria,
                      time.perf_counter() - start)


def stiff_spring():
    """ω = 63.2 rad/s at dt = 10 ms (a tenth of the period). The trapezoidal rule keeps
    the energy of a linear oscillator exactly and turns at ω_h = (2/dt)·atan(ω dt/2)."""
    criteria = ("converges; energy error ≤ 1e-6 J; amplitude within 1e-6 m; the motion equals "
                "0.1 cos(ω_h t), the trapezoidal rule's exact discrete solution, to 1e-6 m")
    start = time.perf_counter()
    dt, k, m, a = 1e-2, 4000.0, 1.0, 0.1
    r, err = run(HARD / "stiff-spring.yaml", coords="dc", dt=dt, t_end=5.0)
    setting = "DC, dt = 10 ms ≈ period/10, N_w = 1, 5 s"
    if err:
        yield failed("stiff spring", setting, criteria, err, start)
        return
    w = math.sqrt(k / m)
    wh = 2 / dt * math.atan(w * dt / 2)
    x = r.column("q:S.x") - 1.0
    amplitude = float(np.max(np.abs(x)))
    discrete = float(np.max(np.abs(x - a * np.cos(wh * r.t))))
    exact = float(np.max(np.abs(x - a * np.cos(w * r.t))))
    energy = r.summary["energy_drift"]
    ok = energy <= 1e-6 and abs(amplitude - a) <= 1e-6 and discrete <= 1e-6
    yield Outcome("stiff spring", setting, ok,
                  f"energy {energy:.1e} J; amplitude {amplitude:.7f} m; vs discrete solution "
                  f"{discrete:.1e} m; vs exact {exact:.2e} m (phase, ω_h/ω − 1 = {wh / w - 1:.2e})",
                  criteria, time.perf_counter() - start)


def large_steps(coords):
    """The four-bar at dt = 10 and 20 ms against its reference (error grows as dt²)."""
    ref_path = ROOT / "references" / "fourbar" / "reference.csv.gz"
    truth = tj.read(ref_path) if ref_path.exists() else None
    criteria = "converges; |Φ| ≤ 1e-9; RMSE ≤ 50 m·s⁻² · dt² (5e-3 m at 10 ms)"
    for c in coords:
        scene = ROOT / "scenes" / ("fourbar.yaml" if c == "dc" else "fourbar-theta.yaml")
        for dt in (1e-2, 2e-2):
            start = time.perf_counter()
            setting = f"{c.upper()}, dt = {dt * 1e3:g} ms, N_w = 1, 5 s"
            r, err = run(scene, coords=c, dt=dt, t_end=5.0)
            if err:
                yield failed("large step", setting, criteria, err, start)
                continue
            rmse = float("nan")
            if truth is not None:
                rmse, _ = refs.point_errors(mbfg.load(scene), r.t, r.q, truth)
            ok = rmse <= 50 * dt * dt and r.summary["worst_phi"] <= PHI_BOUND
            yield Outcome("large step", setting, ok,
                          f"RMSE {rmse:.2e} m; |Φ| {r.summary['worst_phi']:.0e}; "
                          f"{r.summary['mean_iterations']:.2f} LM iterations per step", criteria,
                          time.perf_counter() - start)


def redundant():
    """A repeated constraint changes nothing: same motion as the plain four-bar. The two
    solves differ only in an equivalent constraint basis, so they agree to the solver's
    step tolerance (1e-8), not to round-off."""
    criteria = "converges; positions equal the plain four-bar's to 1e-7 m (10× the step tolerance)"
    start = time.perf_counter()
    setting = "DC, dt = 1 ms, N_w = 1, 5 s"
    r, err = run(HARD / "redundant-fourbar.yaml", coords="dc", dt=1e-3, t_end=5.0)
    plain, err2 = run(ROOT / "scenes" / "fourbar.yaml", coords="dc", dt=1e-3, t_end=5.0)
    if err or err2:
        yield failed("redundant constraints", setting, criteria, err or err2, start)
        return
    diff = float(np.max(np.abs(r.q - plain.q)))
    yield Outcome("redundant constraints", setting, diff <= 1e-7,
                  f"max difference {diff:.1e} m; |Φ| {r.summary['worst_phi']:.0e}", criteria,
                  time.perf_counter() - start)


def branch():
    """θ alone admits two assemblies: IC must stay on the lower one it started on."""
    criteria = ("converges; sign of (P2 − P1) × (B − P2) never changes; IC equals DC (which "
                "cannot switch branch) to 1e-4 m")
    start = time.perf_counter()
    setting = "IC, dt = 1 ms, N_w = 1, 5 s"
    scene = HARD / "fourbar-lower-branch.yaml"
    ic, err = run(scene, coords="ic", dt=1e-3, t_end=5.0)
    dc, err2 = run(scene, coords="dc", dt=1e-3, t_end=5.0)
    if err or err2:
        yield failed("IC branch ambiguity", setting, criteria, err or err2, start)
        return
    x1, y1, x2, y2 = (ic.q[:, i] for i in range(4))
    cross = (x2 - x1) * (0.0 - y2) - (y2 - y1) * (4.0 - x2)
    same = bool(np.all(np.sign(cross) == np.sign(cross[0])))
    diff = float(np.max(np.abs(ic.q[:, :4] - dc.q[:, :4])))
    yield Outcome("IC branch ambiguity", setting, same and diff <= 1e-4,
                  f"branch kept: {same}; max |IC − DC| {diff:.1e} m", criteria,
                  time.perf_counter() - start)


def cases(fast: bool) -> list[tuple]:
    """The suite: (case function, its arguments), each a task of a sweep; a case with
    several runs is one task per coordinates (and dt), in the order it runs them."""
    dts = [1e-3] if fast else [1e-3, 1e-4, 1e-5]
    return [
        *[(parallelogram, ([dt], [c])) for c in ("dc", "ic") for dt in dts],
        *[(dead_centres, ([c],)) for c in ("dc", "ic")],
        *[(long_run, (60.0, [c])) for c in (["dc"] if fast else ["dc", "ic"])],
        (stiff_spring, ()),
        *[(large_steps, ([c],)) for c in ("dc", "ic")],
        (redundant, ()),
        (branch, ()),
    ]


def run_case(case: tuple) -> list[Outcome]:
    fn, args = case
    return list(fn(*args))


def suite(fast: bool, sweep=None) -> list[Outcome]:
    """Every case's outcomes, in the suite's order; the cases are tasks of `sweep`
    (harness/sweep.py; None: in this process, one after the other)."""
    def done(_, outcomes):
        for o in outcomes:
            print(f"  {'pass' if o.passed else 'FAIL'}  {o.case} ({o.setting}): {o.figures}",
                  file=sys.stderr, flush=True)
    if sweep is None:
        per_case = []
        for case in cases(fast):
            per_case.append(run_case(case))
            done(case, per_case[-1])
    else:
        per_case = sweep.map(run_case, cases(fast), "hard cases", done=done)
    return [o for outcomes in per_case for o in outcomes]


def table(outcomes: list[Outcome]) -> str:
    lines = ["| case | run | result | figures | pass criteria |", "|---|---|---|---|---|"]
    for o in outcomes:
        lines.append(f"| {o.case} | {o.setting} | {'pass' if o.passed else '**FAIL**'} | "
                     f"{o.figures.replace('|', '/')} | {o.criteria.replace('|', '/')} |")
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m harness.hard_cases",
                                 description=__doc__.splitlines()[0])
    ap.add_argument("--fast", action="store_true", help="the fast form run by make test")
    sweeps.add_argument(ap)
    args = ap.parse_args(argv)
    with sweeps.from_args(args) as sweep:
        outcomes = suite(args.fast, sweep)
    print(table(outcomes))
    passed = sum(o.passed for o in outcomes)
    print(f"\n{passed} of {len(outcomes)} hard-case runs pass")
    return 0 if passed == len(outcomes) else 1


if __name__ == "__main__":
    # As harness.hard_cases, not __main__: the sweep's tasks name its functions, which the
    # Dask scheduler and workers import.
    from harness import hard_cases
    sys.exit(hard_cases.main())
