"""The robustness matrix: every scene × DC/IC × N_w × dt, each cell converged, stopped
ahead of an ill-posed (singular) configuration, or failed (docs/robustness.md).

    python -m harness.robustness [--fast] [--scenes GLOB ...] [--out DIR]

writes DIR/robustness.md and DIR/robustness.csv (DIR defaults to reports/) and prints
the summary line; progress goes to standard error. `make report` runs the full matrix,
the CI log shows the fast one's summary, and harness/tests/test_robustness.py holds
the fast matrix cell by cell.
"""
from __future__ import annotations

import argparse
import collections
import dataclasses
import functools
import math
import pathlib
import re
import sys
import time

import numpy as np

import mbfg
from harness import hard_cases
from harness import reference as refs
from harness import pages
from harness import sweep as sweeps
from harness import trajectory as tj

ROOT = pathlib.Path(__file__).resolve().parent.parent
SCENE_GLOBS = ["scenes/*.yaml", "scenes/hard/*.yaml", "scenes/driven/*.yaml",
               "scenes/benchmarks/*.yaml"]
COORDS = ["dc", "ic"]
WINDOWS = [1, 2, 5, 10, "batch"]
DTS = [1e-4, 1e-3, 5e-3, 1e-2, 2e-2]
FAST_WINDOWS = [1, 5, "batch"]
FAST_DTS = [1e-3, 5e-3, 1e-2, 2e-2]

# Horizons: the reference's where a scene has one (so RMSE covers all of it), else
# DEFAULT_HORIZON; at most FINE_HORIZON below 1 ms and FAST_HORIZON in the fast
# matrix, and at most BATCH_STEPS steps in one batch solve.
DEFAULT_HORIZON = 2.0
FINE_HORIZON = 1.0
FAST_HORIZON = 1.0
BATCH_STEPS = 5000
# A cell whose estimated run time exceeds its budget runs a shorter horizon (the CSV's
# t_end): an estimate, not a measurement, so that the cell is the same run on every
# machine. Near rank loss the iterations multiply past any estimate (a DC batch on the
# N four-bar: 100× it), so a run that has used KILL_AFTER s of CPU time is killed and
# the cell runs half its horizon, up to SHORTENINGS times; then, or below MIN_STEPS
# steps, it is skipped (and says why). CPU time, not wall time: on a loaded machine a
# wall-time limit killed runs that had only waited for a core (the squeezer's DC
# N_w = 5 cells, 8-11 s alone, at 40 s). A run stuck without using the CPU is killed
# after WALL_FACTOR × KILL_AFTER s of wall time.
BUDGET = {False: 20.0, True: 1.0}        # s per cell: full, fast
KILL_AFTER = {False: 120.0, True: 40.0}
WALL_FACTOR = 4.0
SHORTENINGS = 2
MIN_STEPS = 10
# The integrator of every cell (`--integrator`; passed to every task).
INTEGRATOR = "trapezoidal"

# What a failure message names: "step 521 (t = 0.521 s)" (also the batch warm start's
# "step 12 (t = 0.24)").
COUNTED = ("converged", "ill-posed", "failed", "error", "skipped")


@dataclasses.dataclass(frozen=True)
class Cell:
    scene: str            # path below scenes/ without .yaml: "hard/parallelogram"
    coords: str
    window: int | str     # N_w, or "batch"
    dt: float

    @property
    def path(self) -> pathlib.Path:
        return scene_path(self.scene)

    def key(self) -> tuple:
        """Order of the pages: scene, DC before IC, N_w ascending with batch last, dt."""
        return (self.scene, COORDS.index(self.coords),
                math.inf if self.window == "batch" else self.window, self.dt)

    @property
    def id(self) -> str:
        w = "batch" if self.window == "batch" else f"w{self.window}"
        return f"{self.scene}-{self.coords}-{w}-{self.dt * 1e3:g}ms"

    def label(self) -> str:
        w = "batch" if self.window == "batch" else f"N_w = {self.window}"
        return f"{self.scene} {self.coords.upper()} {w}, dt = {self.dt * 1e3:g} ms"

    def command(self, t_end: float) -> str:
        """The same run from the command line."""
        w = "--batch" if self.window == "batch" else f"--window {self.window}"
        return (f"target/release/mbfg simulate {self.path.relative_to(ROOT)} "
                f"--coords {self.coords} --dt {self.dt:g} --t-end {t_end:g} {w}")


@dataclasses.dataclass
class Outcome:
    scene: str
    coords: str
    window: int | str
    dt: float
    t_end: float | None
    status: str           # converged, ill-posed, failed, error, skipped, n/a
    cause: str = ""
    step: int | None = None
    t_stop: float | None = None
    rmse: float | None = None
    mean_iterations: float | None = None
    max_iterations: int | None = None
    wall_time: float | None = None
    note: str = ""

    @property
    def cell(self) -> Cell:
        return Cell(self.scene, self.coords, self.window, self.dt)


# ---------------------------------------------------------------- classification

@dataclasses.dataclass(frozen=True)
class Verdict:
    status: str
    cause: str
    step: int | None = None
    t: float | None = None


def classify(failure: dict | None, message: str) -> Verdict:
    """A SolveError, from its structured failure (SolveError.failure): the
    singular-configuration stop of a run in independent coordinates is ill-posed, with
    its cause; anything else is a failed solve, at the step and time it names where it
    names them."""
    if failure and failure.get("kind") == "singular-configuration":
        cause = (f"singular configuration at t ≈ {failure['located_t']:g} s: "
                 f"[{', '.join(failure['independent'])}] do not determine the others "
                 f"(rank {failure['rank']} < {failure['full_rank']})")
        return Verdict("ill-posed", cause, failure["step"], failure["t"])
    failure = failure or {}
    return Verdict("failed", message, failure.get("step"), failure.get("t"))


def verdict_of(exc: BaseException) -> Verdict:
    if isinstance(exc, mbfg.SolveError):
        return classify(exc.failure, str(exc))
    return Verdict("error", f"{type(exc).__name__}: {exc}")


# ---------------------------------------------------------------- scenes and plan

def scene_path(name: str) -> pathlib.Path:
    return ROOT / "scenes" / f"{name}.yaml"


def scene_name(path: pathlib.Path) -> str:
    return path.resolve().relative_to(ROOT / "scenes").with_suffix("").as_posix()


def scenes(globs=SCENE_GLOBS) -> list[str]:
    """The scenes the globs (relative to the repository) match, at run time."""
    found = {p.resolve() for g in globs for p in ROOT.glob(g) if p.suffix == ".yaml"}
    return sorted(scene_name(p) for p in found)


@functools.lru_cache(maxsize=None)
def reference(name: str) -> tj.Trajectory | None:
    """The committed reference of a scene, if it has one for the scene as it is now."""
    try:
        truth, prov = pages.load_reference(name)
    except FileNotFoundError:
        return None
    return truth if tj.is_current(prov, scene_path(name)) else None


@functools.lru_cache(maxsize=None)
def size(name: str) -> int:
    return mbfg.load(scene_path(name)).n


def horizon(name: str) -> float:
    truth = reference(name)
    return float(truth.t[-1]) if truth is not None else DEFAULT_HORIZON


def planned_t_end(cell: Cell, fast: bool) -> float:
    t_end = horizon(cell.scene)
    if fast:
        t_end = min(t_end, FAST_HORIZON)
    if cell.dt < 1e-3:
        t_end = min(t_end, FINE_HORIZON)
    if cell.window == "batch":
        t_end = min(t_end, BATCH_STEPS * cell.dt)
    return round_down(t_end, cell.dt)


def round_down(t: float, dt: float) -> float:
    """t down to a whole number of steps (and of 10 ms where dt allows: readable)."""
    unit = max(dt, 1e-2) if t >= 1e-2 else dt
    return math.floor(t / unit + 1e-9) * unit


def matrix(names: list[str], fast: bool) -> tuple[list[Cell], list[Outcome]]:
    """The cells to run, and the n/a ones (IC of a scene without independent coordinates)."""
    windows, dts = (FAST_WINDOWS, FAST_DTS) if fast else (WINDOWS, DTS)
    run, na = [], []
    for name in names:
        has_ic = bool(mbfg.load(scene_path(name)).independent)
        for c in COORDS:
            for w in windows:
                for dt in dts:
                    cell = Cell(name, c, w, dt)
                    if c == "ic" and not has_ic:
                        na.append(Outcome(name, c, w, dt, None, "n/a",
                                          "no independent coordinates declared"))
                    else:
                        run.append(cell)
    return run, na


# ---------------------------------------------------------------- one cell

def attempt(cell: Cell, t_end: float, integrator: str | None = None):
    """(the run, None) or (None, what it raised). A panic in the native module arrives
    as pyo3's PanicException, a BaseException: caught too, so that it is a cell's error."""
    try:
        return mbfg.simulate(cell.path, coords=cell.coords, dt=cell.dt, t_end=t_end,
                             integrator=integrator or INTEGRATOR,
                             **pages.window_kw(cell.window)), None
    except (KeyboardInterrupt, SystemExit):
        raise
    except BaseException as e:  # noqa: BLE001
        return None, e


def estimated_seconds(cell: Cell, n: int, steps: int) -> float:
    """Wall time of a run, roughly (fitted on the 2-core EPYC, 2026-11-25: four-bar,
    pick-and-place and the 40-loop four-bar; within 2× from n = 4 to 83). A step
    costs ~n² (assembly) + ~n³ (dense blocks); a window of N_w steps ~1 + 0.3 (N_w − 1)
    one-step solves, a batch ~1.5 (the warm start and its own iterations); IC ~1.5×."""
    per_step = 7.5e-7 * n ** 2 + 3.1e-8 * n ** 3
    window = 1.5 if cell.window == "batch" else 1 + 0.3 * (cell.window - 1)
    return steps * per_step * window * (1.5 if cell.coords == "ic" else 1.0)


def affordable_t_end(cell: Cell, t_end: float, budget: float) -> tuple[float, str]:
    """t_end, or a shorter one (and why) where the estimate exceeds the budget."""
    n = size(cell.scene)
    steps = round(t_end / cell.dt)
    if estimated_seconds(cell, n, steps) <= budget:
        return t_end, ""
    per_step = estimated_seconds(cell, n, 1)
    short = round_down(budget / per_step * cell.dt, cell.dt)
    return short, (f"t_end shortened from {t_end:g} s to fit the {budget:g} s budget per cell "
                   f"(estimated {per_step * 1e3:.2g} ms per step)")


def cell_t_end(cell: Cell, fast: bool, killed: tuple[float, ...] = ()) -> tuple[float, str]:
    """The horizon a cell runs, and why where it is shorter than planned. `killed`:
    the horizons of its earlier runs that were killed."""
    planned = planned_t_end(cell, fast)
    if not killed:
        return affordable_t_end(cell, planned, BUDGET[fast])
    return round_down(killed[-1] / 2, cell.dt), (
        f"t_end shortened from {planned:g} s: the runs of {', '.join(f'{t:g}' for t in killed)} s "
        f"were killed after {KILL_AFTER[fast]:g} s of CPU time")


def run_cell(cell: Cell, fast: bool, killed: tuple[float, ...] = (),
             integrator: str | None = None) -> Outcome:
    """Runs one cell (with `integrator`, default INTEGRATOR) and says what became of it;
    never raises (but on Ctrl-C)."""
    t_end, note = cell_t_end(cell, fast, killed)
    out = Outcome(cell.scene, cell.coords, cell.window, cell.dt, t_end, "converged", note=note)
    # A shortened horizon below MIN_STEPS steps says too little to count; a scene's own
    # short horizon (the squeezer's 0.03 s at 20 ms) is a run like any other.
    if t_end < cell.dt * (1 - 1e-9) or (note and t_end < MIN_STEPS * cell.dt):
        out.status, out.cause = "skipped", f"{out.note}: fewer than {MIN_STEPS} steps left"
        return out
    start = time.perf_counter()
    r, failed = attempt(cell, t_end, integrator)
    out.wall_time = time.perf_counter() - start
    if failed:
        v = verdict_of(failed)
        out.status, out.cause, out.step, out.t_stop = v.status, v.cause, v.step, v.t
        return out
    s = r.summary
    out.mean_iterations, out.max_iterations = s.get("mean_iterations"), s.get("max_iterations")
    if not np.all(np.isfinite(r.data)):
        out.status, out.cause = "error", "NaN or Inf in the trajectory"
        return out
    truth = reference(cell.scene)
    if truth is not None:
        out.rmse, _ = refs.point_errors(mbfg.load(cell.path), r.t, r.q, truth)
    return out


# ---------------------------------------------------------------- the matrix

def run(names: list[str], fast: bool, progress=pages.progress, sweep=None) -> list[Outcome]:
    """Every cell of the matrix over `names`, n/a cells included, in page order."""
    cells, na = matrix(names, fast)
    return sorted(na + run_cells(cells, fast, progress=progress, sweep=sweep),
                  key=lambda o: o.cell.key())


def run_cells(cells: list[Cell], fast: bool, progress=pages.progress,
              sweep=None) -> list[Outcome]:
    """run_cell for every cell, in the cells' order: tasks of `sweep` (harness/sweep.py;
    None: a sweep of its own, a local cluster by default), each cell in a process of its
    own (isolated_cell). Reports every cell that does not converge, and the count."""
    if sweep is None:
        with sweeps.Sweep() as own:
            return run_cells(cells, fast, progress, own)

    def done(_, o: Outcome) -> None:
        if o.status != "converged":
            progress(f"  {o.status}: {o.cell.label()}: {o.cause}")

    def cost(c: Cell) -> float:
        return estimated_seconds(c, size(c.scene), round(planned_t_end(c, fast) / c.dt))

    task = functools.partial(isolated_cell, fast=fast, integrator=INTEGRATOR)
    return sweep.map(task, cells, "robustness", done=done, progress=progress, cost=cost)


def isolated_cell(cell: Cell, fast: bool, integrator: str = "trapezoidal") -> Outcome:
    """run_cell in a child process (sweep.isolated), so that a crash in the native
    module (a panic is an exception, not a crash) or a run over KILL_AFTER ends that
    process alone. A killed run is run again over half its horizon, up to SHORTENINGS
    times; then the cell is skipped."""
    tried = ()
    while True:
        t_end = cell_t_end(cell, fast, tried)[0]
        status, value = sweeps.isolated(run_cell, (cell, fast, tried, integrator),
                                        WALL_FACTOR * KILL_AFTER[fast],
                                        cpu_seconds=KILL_AFTER[fast])
        if status == "ok":
            return value
        if status == "died":
            return Outcome(cell.scene, cell.coords, cell.window, cell.dt, t_end, "error",
                           f"the process running the cell died (exit code {value}): a crash "
                           "in the native module")
        tried += (t_end,)
        if len(tried) > SHORTENINGS:
            ends = ", ".join(f"{t:g}" for t in tried)
            return Outcome(cell.scene, cell.coords, cell.window, cell.dt, t_end, "skipped",
                           f"killed after {KILL_AFTER[fast]:g} s of CPU time at t_end = {ends} s")


# ---------------------------------------------------------------- pages

def summary(outcomes: list[Outcome], fast: bool = False) -> str:
    """The one line the CI log and the page start with."""
    n = collections.Counter(o.status for o in outcomes)
    total = sum(n[s] for s in COUNTED)
    stops = collections.Counter(f"{o.scene} {o.coords.upper()}" for o in outcomes
                                if o.status == "ill-posed")
    named = ", ".join(f"{k} ×{v}" for k, v in sorted(stops.items()))
    failed = n["failed"] + n["error"]
    line = (f"robustness{' (fast)' if fast else ''}: {n['converged']} of {total} cells converge, "
            f"{n['ill-posed']} ill-posed stops{f' ({named})' if named else ''}, {failed} failed")
    if n["error"]:
        line += f" ({n['error']} with an error)"
    if n["skipped"]:
        line += f", {n['skipped']} skipped"
    return line


def mark(o: Outcome) -> str:
    if o.status == "converged":
        return "✓" + (f" {o.rmse:.1e}" if o.rmse is not None else "") + (" †" if o.note else "")
    if o.status == "ill-posed":
        return f"ill-posed @ {o.t_stop:g} s"
    if o.status == "failed":
        return "✗" + (f" @ {o.t_stop:g} s" if o.t_stop is not None else "")
    return {"error": "✗ error", "skipped": "skipped"}.get(o.status, o.status)


def scene_section(name: str, outcomes: list[Outcome]) -> str:
    dts = sorted({o.dt for o in outcomes})
    rows = list(dict.fromkeys((o.coords, o.window) for o in outcomes))
    by = {(o.coords, o.window, o.dt): o for o in outcomes}
    ends = sorted({o.t_end for o in outcomes if o.t_end}, reverse=True)
    has_ref = reference(name) is not None
    origin = "the reference" if has_ref else "no reference: default"
    runs = ", ".join(f"{t:g}" for t in ends)
    lines = [f"## {name}\n",
             f"Horizon {horizon(name):g} s ({origin}); runs of {runs} s. "
             + ("Cells show position RMSE (m) against the reference." if has_ref
                else "No reference: no RMSE.") + "\n",
             "| | " + " | ".join(f"{dt * 1e3:g} ms" for dt in dts) + " |",
             "|---|" + "---|" * len(dts)]
    for c, w in rows:
        if all(by[(c, w, dt)].status == "n/a" for dt in dts):
            continue
        head = f"{c.upper()} " + ("batch" if w == "batch" else f"N_w = {w}")
        lines.append(f"| {head} | " + " | ".join(mark(by[(c, w, dt)]) for dt in dts) + " |")
    if all(o.status == "n/a" for o in outcomes if o.coords == "ic"):
        lines.append("\nIC: n/a (no independent coordinates declared).")
    # Below the grid, what each cell that did not simply converge says; cells saying
    # the same (one dt, every window) on one line.
    said = collections.defaultdict(list)
    for o in outcomes:
        if o.status not in ("converged", "n/a") or o.note:
            text = o.note if o.status == "converged" else o.cause
            said[(o.coords, o.dt, o.t_end, o.status, text)].append(o.window)
    if said:
        lines.append("")
    for (c, dt, t_end, status, text), ws in said.items():
        sizes = ", ".join(str(w) for w in ws if w != "batch")
        w = ", ".join(([f"N_w = {sizes}"] if sizes else []) + (["batch"] if "batch" in ws else []))
        what = status if status in ("converged", "skipped") else f"**{status}**"
        text = text if len(text) <= 300 else text[:299] + "…"
        lines.append(f"- {c.upper()} {w}, dt = {dt * 1e3:g} ms, t_end {t_end:g} s: {what}: "
                     f"{text.replace('|', '/')}")
    return "\n".join(lines) + "\n"


def page(outcomes: list[Outcome], fast: bool, seconds: float, globs=SCENE_GLOBS,
         where: str = "") -> str:
    windows, dts = (FAST_WINDOWS, FAST_DTS) if fast else (WINDOWS, DTS)
    names = list(dict.fromkeys(o.scene for o in outcomes))
    integrator = "" if INTEGRATOR == "trapezoidal" else f" --integrator {INTEGRATOR}"
    ran = f" on {where}" if where else ""
    head = f"""# Robustness matrix{' (fast)' if fast else ''}{f' ({INTEGRATOR})' if integrator else ''}

{summary(outcomes, fast)}

Every scene ({len(names)} files: `{'`, `'.join(globs)}`) × DC/IC × N_w ∈
{{{', '.join(map(str, windows))}}} × dt ∈ {{{', '.join(f'{dt * 1e3:g}' for dt in dts)}}} ms.
A cell is ✓ (converged at every step; the number is the position RMSE against the
reference), ill-posed (a run in independent coordinates stopped ahead of a
configuration they do not determine, at the time shown), ✗ (a solve did not converge,
at the time shown; the message is listed under the grid) or n/a (IC of a scene without
independent coordinates). † marks a horizon shortened to fit the time per cell (why:
under the grid).
Per cell, `robustness.csv` has the horizon run, the cause, RMSE, LM iterations and wall
time. How to read and rerun it: [docs/robustness.md](../docs/robustness.md).

Generated by `python -m harness.robustness{' --fast' if fast else ''}{integrator}` in {seconds:.0f} s{ran}.
Machine: {pages.machine()}.
"""
    by_scene = collections.defaultdict(list)
    for o in outcomes:
        by_scene[o.scene].append(o)
    return head + "\n" + "\n".join(scene_section(n, by_scene[n]) for n in names)


def write(outcomes: list[Outcome], out: pathlib.Path, fast: bool, seconds: float,
          globs=SCENE_GLOBS, where: str = "") -> None:
    """`where`: where the cells ran (Sweep.describe)."""
    out.mkdir(parents=True, exist_ok=True)
    (out / "robustness.md").write_text(page(outcomes, fast, seconds, globs, where))
    pages.write_csv(out / "robustness.csv", [dataclasses.asdict(o) for o in outcomes])


def main(argv=None) -> int:
    global INTEGRATOR
    ap = argparse.ArgumentParser(prog="python -m harness.robustness",
                                 description=__doc__.splitlines()[0])
    ap.add_argument("--fast", action="store_true",
                    help="dt ∈ {1, 5, 10, 20} ms, N_w ∈ {1, 5, batch}, horizons ≤ 1 s")
    ap.add_argument("--scenes", nargs="+", metavar="GLOB", default=SCENE_GLOBS,
                    help="scene files, globs relative to the repository (default: %(default)s)")
    ap.add_argument("--out", type=pathlib.Path, default=pages.REPORTS,
                    help="folder for robustness.md and robustness.csv (default: reports/)")
    ap.add_argument("--integrator", choices=["trapezoidal", "hermite-simpson", "euler"],
                    default=INTEGRATOR, help="the integrator of every cell (default: %(default)s)")
    sweeps.add_argument(ap)
    args = ap.parse_args(argv)
    INTEGRATOR = args.integrator
    try:
        names = scenes(args.scenes)
    except ValueError:
        ap.error("--scenes: the files must be under scenes/")
    if not names:
        ap.error(f"no scene matches {' '.join(args.scenes)}")
    start = time.perf_counter()
    with sweeps.from_args(args) as cluster:
        outcomes = run(names, args.fast, sweep=cluster)
        where = cluster.describe()
    write(outcomes, args.out, args.fast, time.perf_counter() - start, args.scenes, where)
    pages.progress(f"wrote {args.out / 'robustness.md'}, {args.out / 'robustness.csv'}")
    print(summary(outcomes, args.fast))
    return 0


if __name__ == "__main__":
    # As harness.robustness, not __main__: the sweep's tasks name its functions, which the
    # Dask scheduler and workers import.
    from harness import robustness
    sys.exit(robustness.main())
