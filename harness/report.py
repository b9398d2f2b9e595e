"""`make report`: the validation pages in reports/, from the committed references.

    python -m harness.report            # everything (forward tables, accuracy against
                                        # time, hard cases, robustness matrix; the inverse
                                        # page comes from `cargo run --release --features
                                        # testing --example inverse_report`)
    python -m harness.report --ci       # the four-bar table, the fast hard cases, the
                                        # fast robustness matrix's summary line and one
                                        # identification run, printed (the end of every
                                        # CI log)
    python -m harness.report --only forward|timing|hard|inverse|robustness|scaling|horizons|estimation|identification|coverage|a02
    python -m harness.report --scheduler tcp://host:8786   # on a Dask cluster
                                        # (docs/sweeps.md; default: $MBFG_SCHEDULER, else
                                        # a local cluster, one worker per core)
"""
from __future__ import annotations

import argparse
import functools
import sys
import time

import numpy as np

import mbfg
from harness import generators, hard_cases
from harness import sweep as sweeps
from harness.pages import (REPORTS, ROOT, errors, load_reference, machine, progress,
                           scene_path, window_kw, write_csv)

WINDOWS = list(range(1, 11)) + ["batch"]

# The paper's Table 3 (RMSE in m, g = 9.8, ADAMS as truth) for N_w = 2…10: DC, IC.
PAPER = {2: (2.361e-3, 2.3834e-2), 3: (2.356e-3, 1.9645e-2), 4: (2.352e-3, 2.0019e-2),
         5: (2.348e-3, 1.6647e-2), 6: (2.344e-3, 1.6677e-2), 7: (2.341e-3, 1.6677e-2),
         8: (2.338e-3, 1.6677e-2), 9: (2.335e-3, 1.7056e-2), 10: (2.332e-3, 1.6677e-2)}

# Forward scenes of the RMSE tables: scene for DC, scene for IC (None: no independent
# coordinates declared), reference (a scene of references/).
FORWARD = [
    ("fourbar", "fourbar", "fourbar-theta", "fourbar"),
    ("pendulum", "pendulum", "pendulum", "pendulum"),
    ("double pendulum", "double-pendulum", "double-pendulum", "double-pendulum"),
    ("spring-damper pendulum", "spring-damper", "spring-damper", "spring-damper"),
    ("slider-crank", "slider-crank", "slider-crank", "slider-crank"),
    ("slotted lever", "slotted-lever", "slotted-lever", "slotted-lever"),
    ("pick-and-place robot (1 s)", "pick-and-place", "pick-and-place", "pick-and-place"),
]


# ---------------------------------------------------------------- forward tables

INTEGRATORS = ["trapezoidal", "hermite-simpson"]
# The trapezoidal rule with the paper's DC integrator factors (`dc_integrators="full"`):
# what the default's tangent ones are measured against.
PAPER_FACTORS = "trapezoidal, paper's DC factors"


def forward_tables(windows=WINDOWS, scenes=FORWARD, sweep=None) -> tuple[str, list[dict]]:
    """The RMSE-over-N_w table of every scene: the trapezoidal rule (the paper's, and
    its columns) and Hermite–Simpson beside it. One run per cell of `sweep`
    (harness/sweep.py; None: in this process)."""
    runs, heads = [], []
    for title, dc_scene, ic_scene, ref in scenes:
        truth, prov = load_reference(ref)
        t_end = float(truth.t[-1])
        coords = [("dc", dc_scene)] + ([("ic", ic_scene)] if ic_scene and mbfg.load(scene_path(ic_scene)).independent else [])
        heads.append((title, ref, prov, t_end))
        runs += [(ref, dc_scene, scene, c, integrator, w, t_end)
                 for integrator in INTEGRATORS for w in windows for c, scene in coords]
        # DC with the paper's integrator factors beside the default's.
        runs += [(ref, dc_scene, dc_scene, "dc", PAPER_FACTORS, w, t_end) for w in windows]
    rows = (sweep.map(forward_run, runs, "forward", cost=forward_cost) if sweep is not None
            else [forward_run(r) for r in runs])
    md = [scene_table(title, ref, prov, [r for r in rows if r["scene"] == ref], t_end)
          for title, ref, prov, t_end in heads]
    return "\n".join(md), rows


@functools.lru_cache(maxsize=None)
def scene_size(scene: str) -> int:
    return mbfg.load(scene_path(scene)).n


def forward_cost(run: tuple) -> float:
    """Roughly, a run's time: n² per step, a batch 3×, Hermite–Simpson 2×, IC 1.5×."""
    _, _, scene, c, integrator, w, t_end = run
    n = scene_size(scene)
    return (n * n * t_end * (3 if w == "batch" else 1) * (2 if integrator != "trapezoidal" else 1)
            * (1.5 if c == "ic" else 1))


@functools.lru_cache(maxsize=None)
def truth_of(ref: str, dc_scene: str):
    """The committed reference and the model of the DC scene (cached in each worker)."""
    return load_reference(ref)[0], mbfg.load(scene_path(dc_scene))


def forward_run(run: tuple) -> dict:
    """One row of the forward tables: (reference, DC scene, scene, coords, integrator,
    N_w, t_end)."""
    ref, dc_scene, scene, c, integrator, w, t_end = run
    truth, model = truth_of(ref, dc_scene)
    row = {"scene": ref, "integrator": integrator, "coords": c, "window": w, "dt": 1e-3}
    options = ({"integrator": "trapezoidal", "dc_integrators": "full"}
               if integrator == PAPER_FACTORS else {"integrator": integrator})
    try:
        r = mbfg.simulate(scene_path(scene), coords=c, dt=1e-3, t_end=t_end,
                          **options, **window_kw(w))
        rmse, mx = errors(model, r.t, r.q, truth)
        s = r.summary
        row.update({"rmse_m": rmse, "max_m": mx, "worst_phi": s["worst_phi"],
                    "energy_drift_j": s["energy_drift"],
                    "mean_iterations": s["mean_iterations"],
                    "wall_time_s": s["wall_time"], "status": "converged"})
    except mbfg.SolveError as e:
        row["status"] = str(e)
    return row


def fmt(v, spec=".2e"):
    return "—" if v is None else format(v, spec)


def scene_table(title, ref, prov, rows, t_end) -> str:
    fourbar = ref == "fourbar"
    checks = ", ".join(f"{c['generator']} (max {fmt(c.get('max_m'))} m)"
                       for c in prov.get("cross_checks", []) if "max_m" in c) or "—"
    lines = [f"## {title}\n",
             f"{t_end:g} s at dt = 1 ms, default noise models; the trapezoidal rule (the "
             f"paper's), and Hermite–Simpson (HS, fourth order) beside it. DC at the "
             f"defaults (tangent integrator factors), and with the "
             f"paper's integrator factors (`--dc-integrators full`). Reference: "
             f"{prov['generator']} ({prov.get('formulation', '')}), cross-checked by {checks}.\n"]
    head = ("| N_w | DC RMSE (m) | DC, paper's factors, RMSE (m) | IC RMSE (m) |"
            + (" paper DC | paper IC |" if fourbar else ""))
    head += (" worst \\|Φ\\| DC / IC | energy drift DC / IC (J) | LM iter. DC / IC | time DC / IC |"
             " HS DC RMSE (m) | HS IC RMSE (m) | HS time DC / IC |")
    lines += [head, "|" + "---|" * (head.replace("\\|", "").count("|") - 1)]

    def cell(r, key, spec=".3e"):
        if not r:
            return "—"
        if r["status"] != "converged":
            return "stopped"
        v = r[key]
        return "—" if v is None else format(v, spec)

    for w in WINDOWS:
        by = {(r.get("integrator", "trapezoidal"), r["coords"]): r for r in rows if r["window"] == w}
        dc, ic = by.get(("trapezoidal", "dc"), {}), by.get(("trapezoidal", "ic"), {})
        hdc, hic = by.get(("hermite-simpson", "dc"), {}), by.get(("hermite-simpson", "ic"), {})
        pdc = by.get((PAPER_FACTORS, "dc"), {})
        line = f"| {w} | {cell(dc, 'rmse_m')} | {cell(pdc, 'rmse_m')} | {cell(ic, 'rmse_m')} |"
        if fourbar:
            p = PAPER.get(w)
            line += f" {fmt(p[0]) if p else '—'} | {fmt(p[1]) if p else '—'} |"
        line += (f" {cell(dc, 'worst_phi', '.0e')} / {cell(ic, 'worst_phi', '.0e')} |"
                 f" {cell(dc, 'energy_drift_j', '.1e')} / {cell(ic, 'energy_drift_j', '.1e')} |"
                 f" {cell(dc, 'mean_iterations', '.2f')} / {cell(ic, 'mean_iterations', '.2f')} |"
                 f" {ms(dc)} / {ms(ic)} |"
                 f" {cell(hdc, 'rmse_m')} | {cell(hic, 'rmse_m')} | {ms(hdc)} / {ms(hic)} |")
        lines.append(line)
    stopped = [r for r in rows if r["status"] != "converged"]
    for r in stopped[:4]:
        name = {"hermite-simpson": "HS ", PAPER_FACTORS: "paper's factors, "}.get(
            r.get("integrator"), "")
        lines.append(f"\n{name}{r['coords'].upper()}, N_w = {r['window']}: {r['status']}")
    if fourbar:
        lines.append("\nTargets: DC with the paper's factors ≤ 2.8e-5 m and IC ≤ 2.6e-6 m for "
                     "every N_w (trapezoidal); "
                     "HS ≤ 1e-9 m. Paper: Table 3 "
                     "(ADAMS as truth, g = 9.8; its IC graph is our IC graph with the paper preset).")
    return "\n".join(lines) + "\n"


def ms(r) -> str:
    if not r or r.get("status") != "converged":
        return "—"
    return f"{r['wall_time_s'] * 1e3:.0f} ms"


# ---------------------------------------------------------------- hard cases

def hard_page(fast: bool, sweep=None) -> tuple[str, list]:
    progress("hard cases" + (" (fast form)" if fast else ""))
    outcomes = hard_cases.suite(fast, sweep)
    passed = sum(o.passed for o in outcomes)
    text = ("# Hard-case stability suite\n\n"
            f"{passed} of {len(outcomes)} runs pass. Scenes in `scenes/hard/`; criteria and code in "
            "`harness/hard_cases.py`. A case passes when the run converges at every step, stays on "
            "the reference branch, keeps |Φ| ≤ 1e-9 and meets its error/energy bound — or, where the "
            "problem itself is ill-posed, stops with the status that names the step and the cause.\n\n"
            + hard_cases.table(outcomes) + "\n")
    return text, outcomes


# ---------------------------------------------------------------- inverse vs RNEA

def rnea_section() -> str:
    """The double pendulum's joint torques from mbfg against Pinocchio's RNEA."""
    from harness import pinocchio_ref
    scene = scene_path("double-pendulum")
    csv_path = ROOT / "scenes" / "trajectories" / "double-pendulum.csv"
    t, exact = pinocchio_ref.inverse(scene, csv_path)
    lines = ["## Double pendulum against Pinocchio's RNEA\n",
             "Both joints driven (`scenes/trajectories/double-pendulum.csv`); RNEA with the exact "
             "derivatives of the prescription, mapped to the absolute angles (Q₁ = τ₁ − τ₂, "
             "Q₂ = τ₂). Target: RMSE ≤ 1e-4 of the peak.\n",
             "| coords | force | RMSE (N·m) | peak (N·m) | RMSE / peak |", "|---|---|---|---|---|"]
    for coords in ("dc", "ic"):
        r = mbfg.inverse(scene, csv_path, coords=coords)
        for name, q_exact in exact.items():
            err = r.column(f"Q:{name}") - q_exact
            rmse, peak = float(np.sqrt(np.mean(err ** 2))), float(np.max(np.abs(q_exact)))
            lines.append(f"| {coords.upper()} | Q:{name} | {rmse:.2e} | {peak:.2f} | {rmse / peak:.1e} |")
    return "\n".join(lines) + "\n"


# ---------------------------------------------------------------- page

def section(page: str, heading: str) -> str:
    """The section of a generated page that starts with `heading`, if present."""
    path = REPORTS / page
    if not path.exists():
        return ""
    text = path.read_text()
    if heading not in text:
        return ""
    rest = text[text.index(heading):]
    end = rest.find("\n## ", 1)
    return rest if end < 0 else rest[:end]


def summary_line(page: str, start: str) -> str:
    """The first line of a generated page that starts with `start`, if any."""
    path = REPORTS / page
    lines = path.read_text().splitlines() if path.exists() else []
    return next((line for line in lines if line.startswith(start)), "")


def other_tools() -> str:
    """"exudyn, IDA and Pinocchio": the registered generators the timing page sweeps."""
    labels = [g.label for g in generators.REGISTRY.values() if g.sweeps]
    return labels[0] if len(labels) < 2 else ", ".join(labels[:-1]) + " and " + labels[-1]


def estimation_line() -> str:
    """The estimation page's summary line."""
    line = summary_line("estimation.md", "Summary: ")
    return line.removeprefix("Summary: ") if line else "not generated (`python -m harness.report --only estimation`)"


def identification_line() -> str:
    """The identification page's summary line."""
    line = summary_line("identification.md", "Summary: ")
    return line.removeprefix("Summary: ") if line else "not generated (`python -m harness.report --only identification`)"


def write_index() -> None:
    hard = (REPORTS / "hard-cases.md").read_text().splitlines()[2] if (REPORTS / "hard-cases.md").exists() else ""
    robust = summary_line("robustness.md", "robustness")
    page = f"""# mbfg validation report

Generated by `make report` from the committed references (`references/`, written by
`make reference`). Machine: {machine()}.

- [Forward dynamics: RMSE over window sizes, DC and IC, every scene](forward.md) ([csv](forward.csv))
- [Accuracy against wall time, next to {other_tools()}](accuracy-vs-time.md) ([csv](accuracy-vs-time.csv))
- [Hard-case stability suite](hard-cases.md) ([csv](hard-cases.csv)) — {hard}
- [Robustness matrix: every scene × DC/IC × N_w × dt](robustness.md) ([csv](robustness.csv)) — {robust}
- [Inverse dynamics against the classical solution](inverse.md)
- [Per-step cost against the size of the mechanism](scaling.md) ([csv](scaling.csv)) — {summary_line("scaling.md", "scaling")}
- [State estimation: the three-simulation benchmark against the EKF and the UKF](estimation.md) ([csv](estimation/summary.csv)) — {estimation_line()}
- [Parameter identification, and inverse dynamics from measured motion](identification.md) ([csv](identification/runs.csv)) — {identification_line()}
- [Coverage: the independent simulator that checks each scene](coverage.md) ([csv](coverage.csv)) — {summary_line("coverage.md", "**").replace("**", "")}
- [Long horizons: time and memory from 10³ to 10⁶ steps](horizons.md) ([csv](horizons.csv); `python -m harness.report --only horizons`, not in the default parts)
- [IFToMM A02: the 40-loop four-bar through its flat configurations, error against dt and CPU time to each tolerance beside IDA and exudyn, and the shorter chains (N = 1 … 20) at the same steps](a02.md) ([csv](a02.csv); `python -m harness.report --only a02`, not in the default parts)
- [Scene summaries (`mbfg check`)](check.txt)

{section("forward.md", "## fourbar")}
{section("accuracy-vs-time.md", "## four-bar")}
"""
    (REPORTS / "index.md").write_text(page)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m harness.report",
                                 description=__doc__.split("\n\n")[0])
    ap.add_argument("--ci", action="store_true",
                    help="print the four-bar table, the fast hard cases and the fast robustness summary")
    ap.add_argument("--only", choices=["forward", "timing", "hard", "inverse", "robustness",
                                       "scaling", "horizons", "estimation", "identification",
                                       "coverage", "a02"],
                    help="one part")
    sweeps.add_argument(ap)
    args = ap.parse_args(argv)
    start = time.perf_counter()
    # The sweeps' cells are tasks on Dask (harness/sweep.py, docs/sweeps.md); the timing
    # part's run one at a time, with nothing else running.
    sweep = sweeps.from_args(args).start()
    progress(f"sweeps: {sweep.describe()}")
    if args.ci:
        text, _ = forward_tables(scenes=FORWARD[:1], sweep=sweep)
        print(text)
        hard, outcomes = hard_page(fast=True, sweep=sweep)
        print(hard)
        from harness import robustness
        progress("robustness matrix (fast form)")
        cells = robustness.run(robustness.scenes(), fast=True, progress=lambda _: None,
                               sweep=sweep)
        print(robustness.summary(cells, fast=True))
        from harness import identification
        print(identification.ci_line())
        return 0
    REPORTS.mkdir(exist_ok=True)
    parts = [args.only] if args.only else ["forward", "inverse", "timing", "hard", "robustness",
                                           "scaling", "estimation", "identification", "coverage"]
    if "forward" in parts:
        text, rows = forward_tables(sweep=sweep)
        (REPORTS / "forward.md").write_text(
            "# Forward dynamics: RMSE over window sizes, DC and IC\n\n"
            "RMSE and max error over the x, y of every moving point against the committed "
            "reference (`references/`); wall times are single runs, taken beside the other runs of "
            "the table (one per core; medians, measured alone: `make bench` and "
            f"[accuracy against time](accuracy-vs-time.md)). Machine: {machine()}.\n\n" + text)
        write_csv(REPORTS / "forward.csv", rows)
        progress("wrote reports/forward.md, reports/forward.csv")
    if "timing" in parts:
        from harness import timing
        timing.write(REPORTS, sweep=sweep)
    if "inverse" in parts and (REPORTS / "inverse.md").exists():
        # The Rust example writes the page; the comparison with Pinocchio is added here.
        page = (REPORTS / "inverse.md").read_text().split("\n## Double pendulum against")[0]
        (REPORTS / "inverse.md").write_text(page.rstrip() + "\n\n" + rnea_section())
    if "hard" in parts:
        text, outcomes = hard_page(fast=False, sweep=sweep)
        (REPORTS / "hard-cases.md").write_text(text)
        write_csv(REPORTS / "hard-cases.csv", [o.__dict__ for o in outcomes])
        progress("wrote reports/hard-cases.md, reports/hard-cases.csv")
    if "a02" in parts:  # not in the default parts: its runs take minutes
        from harness import a02
        a02.main(["--out", str(REPORTS)])
    if "horizons" in parts:  # not in the default parts: 1e6-step runs take minutes
        from harness import horizons
        horizons.main([])
    if "robustness" in parts:
        from harness import robustness
        progress("robustness matrix")
        began = time.perf_counter()
        outcomes = robustness.run(robustness.scenes(), fast=False, sweep=sweep)
        robustness.write(outcomes, REPORTS, fast=False, seconds=time.perf_counter() - began,
                         where=sweep.describe())
        progress(robustness.summary(outcomes))
        progress("wrote reports/robustness.md, reports/robustness.csv")
    if "scaling" in parts:
        from harness import scaling
        scaling.write(REPORTS, machine())
    if "estimation" in parts:
        from harness import estimation
        progress("estimation: the three-simulation benchmark")
        estimation.write(REPORTS, sweep=sweep)
    if "identification" in parts:
        from harness import identification
        progress("identification: parameters from readings, against the output-error fit")
        identification.write(REPORTS, sweep=sweep)
    if "coverage" in parts:
        from harness import coverage
        progress("coverage: every scene against exudyn and Pinocchio")
        coverage.write(REPORTS)
    write_index()
    progress(f"report done in {time.perf_counter() - start:.0f} s")
    return 0


if __name__ == "__main__":
    # As harness.report, not __main__: the sweep's tasks name its functions, which the
    # Dask scheduler and workers import.
    from harness import report
    sys.exit(report.main())
