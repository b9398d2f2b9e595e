"""The IFToMM A02 benchmark page: the N four-bar (N = 40 over 20 s, the B0 position at
400 output points) through its flat configurations, as the benchmark library defines it.

    python -m harness.a02 [--t-end 20] [--loops 40] [--out DIR] [--no-peers] [--shorter 1,2,5,10,20]

writes DIR/a02.md, DIR/a02.csv and DIR/a02.png (DIR defaults to reports/). The
reference is the exact motion on the parallelogram branch (every bar parallel): the
one-degree-of-freedom ODE I θ̈ = −c g cos θ, I = (N+1)/3 + N, c = (N+1)/2 + N,
integrated by DOP853 at rtol 1e-13 (docs/benchmarks.md, section 2); B0 = (cos θ, sin θ).
The error of a run is max |B0 − B0_exact| over the output points (every 0.05 s). The
tolerances are the benchmark's: 1e-1 m ("low") and 1e-3 m ("high"). CPU time is the
process time of the call, in this process, each tool measured in the same run. The
shorter chains (`--shorter`, N = 1, 2, 5, 10 and 20 by default; `--shorter ""` for none)
are run by mbfg alone at the same steps, for whether every run converges and how its
error falls.
"""
from __future__ import annotations

import argparse
import csv
import math
import pathlib
import time

import numpy as np
from scipy.integrate import solve_ivp

import mbfg
from harness import pages
from harness import sweep as sweeps

ROOT = pathlib.Path(__file__).resolve().parent.parent
OUTPUT_EVERY = 0.05
TOLERANCES = {"low": 1e-1, "high": 1e-3}
TRAPEZOIDAL_DTS = [25e-3, 12.5e-3, 1 / 120, 6.25e-3, 5e-3, 2.5e-3, 1.25e-3, 1e-3,
                   6.25e-4, 5e-4, 2.5e-4, 1e-4]
# Hermite–Simpson's steps are square systems too (at about twice a trapezoidal step's
# cost): the same steps.
HERMITE_SIMPSON_DTS = TRAPEZOIDAL_DTS
# Down to 1e-10: at 1e-8 IDA's B0 error lands between 5.7e-4 and 1.0e-3 m from one page
# run to the next, at the high tolerance's edge; at 1e-10 it stops at the first flat
# configuration (the page shows it).
IDA_RTOLS = [1e-4, 1e-6, 1e-8, 1e-10]
# mbfg with a tolerance (Hermite–Simpson): on the run's rows (the default) at every
# level, and on each step alone at the coarse ones, whose runs end far off.
RUN_RTOLS = [1e-3, 1e-4, 1e-5, 1e-6, 1e-7, 1e-8, 1e-9, 1e-10]
STEP_RTOLS = [1e-3, 1e-4, 1e-5, 1e-6]
EXUDYN_STEPS = [5e-3, 1e-3, 2.5e-4]
SHORTER_CHAINS = [1, 2, 5, 10, 20]


def _failure(e: Exception) -> str:
    """A failure's first line, the checkout's paths written relative to it."""
    return str(e).splitlines()[0].replace(str(ROOT) + "/", "")[:160]


def scene_path(loops: int) -> pathlib.Path:
    folder = "benchmarks" if loops in (1, 5, 10, 40) else "scale"
    return ROOT / "scenes" / folder / f"n-fourbar-{loops}.yaml"


def exact_b0(loops: int, times: np.ndarray) -> np.ndarray:
    inertia, c = (loops + 1) / 3 + loops, (loops + 1) / 2 + loops
    sol = solve_ivp(lambda _, y: [y[1], -c * 9.81 * np.cos(y[0]) / inertia],
                    (0.0, float(times[-1])), [np.pi / 2, -1.0], t_eval=times,
                    rtol=1e-13, atol=1e-13, method="DOP853")
    return np.stack([np.cos(sol.y[0]), np.sin(sol.y[0])], axis=1)


def b0_error(names, t, q, loops: int, t_end: float) -> tuple[float, float]:
    """max |B0 − exact| over the output points the run reached, and the last time."""
    times = np.arange(0.0, t_end + 1e-9, OUTPUT_EVERY)
    ix, iy = list(names).index("B0.x"), list(names).index("B0.y")
    rows = [int(np.argmin(np.abs(t - s))) for s in times if s <= t[-1] + 1e-9]
    b0 = exact_b0(loops, times[:len(rows)])
    err = np.hypot(q[rows, ix] - b0[:, 0], q[rows, iy] - b0[:, 1])
    return float(err.max()), float(t[rows[-1]])


def run_mbfg(loops, integrator, dt, t_end) -> dict:
    start = time.process_time()
    row = {"tool": "mbfg", "setting": f"{integrator}, dt {dt * 1e3:g} ms", "integrator": integrator,
           "dt": dt}
    try:
        r = mbfg.simulate(str(scene_path(loops)), dt=dt, t_end=t_end, integrator=integrator)
        row["cpu"] = time.process_time() - start
        row["error"], row["t_last"] = b0_error(r.names, r.t, r.q, loops, t_end)
        s = r.summary
        p = s["passages"]
        row["status"] = "converged" if not s.get("failures") else "failed"
        row["passages"] = p["count"]
        row["energy_jump"] = p["energy_jump"]
        row["warnings"] = "; ".join(s.get("warnings", []))
    except Exception as e:      # a failed run is a row with its reason
        row["cpu"] = time.process_time() - start
        row["status"] = f"failed: {_failure(e)}"
    return row


def run_mbfg_rtol(loops, rtol, scope, t_end) -> dict:
    """mbfg with `rtol` (= atol), Hermite–Simpson, rows every 0.05 s; `scope` "run"
    (the rows checked, the run made again tighter where they miss it) or "steps"."""
    start = time.process_time()
    row = {"tool": "mbfg", "setting": f"hermite-simpson, rtol {rtol:g} ({scope})",
           "integrator": "hermite-simpson", "rtol": rtol, "scope": scope}
    try:
        r = mbfg.simulate(str(scene_path(loops)), dt=OUTPUT_EVERY, t_end=t_end,
                          integrator="hermite-simpson", rtol=rtol, tolerance_scope=scope)
        row["cpu"] = time.process_time() - start
        row["error"], row["t_last"] = b0_error(r.names, r.t, r.q, loops, t_end)
        c = r.summary["error_control"]
        row["status"] = "converged" if not r.summary.get("failures") else "failed"
        row["estimated"] = c["estimated_error"]
        row["step_rtols"] = " ".join(f"{x:.1e}" for x in c["step_rtols"] or [])
        row["warnings"] = "; ".join(r.summary.get("warnings", []))
    except Exception as e:      # a failed run is a row with its reason
        row["cpu"] = time.process_time() - start
        row["status"] = f"failed: {_failure(e)}"
    return row


def tolerance_section(rows) -> list[str]:
    """The runs with a tolerance: B0 error against the tolerance, and what the check
    estimated."""
    lines = ["", "## With a tolerance", "",
             "mbfg `--rtol` (= `--atol`), Hermite–Simpson, rows every 0.05 s. **run** (the "
             "default, `--tolerance-scope run`): the rows are compared with a run at 4 times "
             "the tolerance (its largest step and largest turn a step 4^(1/4) times "
             "larger, as its steps are) and the run is made again at tighter step tolerances (at most "
             "three times, not below 1e-12: its steps next to the flat configurations damp "
             "their projections and keep their size) while their estimated error exceeds it. "
             "**steps**: each step's local error per second only, one run. Estimated: the "
             "check's estimate of the rows' error, in units of the tolerance (weighted RMS "
             "of q); step rtols: the runs made, the last one's rows kept.", "",
             "| scope | rtol | status | B0 error (m) | error / rtol | estimated | step rtols "
             "| CPU (s) |",
             "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        ratio = f"{r['error'] / r['rtol']:.2f}" if r.get("error") is not None else ""
        lines.append(f"| {r['scope']} | {r['rtol']:g} | {r['status']} | {fmt(r.get('error'))} "
                     f"| {ratio} | {fmt(r.get('estimated'), '.2f')} | {r.get('step_rtols', '')} "
                     f"| {fmt(r.get('cpu'), '.2f')} |")
    return lines


def run_ida(loops, rtol, t_end) -> dict:
    from harness import ida
    start = time.process_time()
    row = {"tool": "IDA", "setting": f"GGL, rtol {rtol:g}", "integrator": "BDF", "dt": None}
    try:
        traj, _ = ida.generate(scene_path(loops), t_end, OUTPUT_EVERY, rtol=rtol)
        row["cpu"] = time.process_time() - start
        row["error"], row["t_last"] = b0_error(traj.names, traj.t, traj.q, loops, t_end)
        row["status"] = "converged"
    except Exception as e:
        row["cpu"] = time.process_time() - start
        row["status"] = f"failed: {_failure(e)}"
    return row


def run_exudyn(loops, h, t_end) -> dict:
    from harness import exudyn_ref
    start = time.process_time()
    row = {"tool": "exudyn", "setting": f"trapezoidal index 2, h {h * 1e3:g} ms",
           "integrator": "trapezoidal_index2", "dt": h}
    try:
        traj, _ = exudyn_ref.generate(scene_path(loops), t_end, OUTPUT_EVERY,
                                      solver="trapezoidal_index2", h=h,
                                      ignore_singular_jacobian=True)
        row["cpu"] = time.process_time() - start
        row["error"], row["t_last"] = b0_error(traj.names, traj.t, traj.q, loops, t_end)
        row["status"] = "converged"
    except Exception as e:
        row["cpu"] = time.process_time() - start
        row["status"] = f"failed: {_failure(e)}"
    return row


def fastest(rows, tolerance, t_end):
    """Per tool, the least CPU time of a run that reached t_end within the tolerance."""
    best = {}
    for r in rows:
        ok = r.get("error") is not None and r["error"] <= tolerance \
            and r.get("t_last", 0) >= t_end - 1e-9 and r["status"] == "converged"
        if ok and (r["tool"] not in best or r["cpu"] < best[r["tool"]]["cpu"]):
            best[r["tool"]] = r
    return best


def fmt(x, spec=".2e"):
    return "" if x is None else format(x, spec)


def observed_orders(rows, integrator):
    """(dt, finer dt, error ratio, observed order) between consecutive converged mbfg
    runs of `integrator`, coarse to fine: the order log(e₁/e₂)/log(dt₁/dt₂)."""
    runs = sorted(((r["dt"], r["error"]) for r in rows if r["tool"] == "mbfg"
                   and r["integrator"] == integrator and r["status"] == "converged"
                   and r.get("error")), reverse=True)
    return [(d1, d2, e1 / e2, math.log(e1 / e2) / math.log(d1 / d2))
            for (d1, e1), (d2, e2) in zip(runs, runs[1:])]


def write(rows, loops, t_end, out: pathlib.Path, seconds: float, shorter=(),
          tolerance_rows=()) -> None:
    """The page, its CSV (the main chain's runs, then the shorter chains', each with its
    `loops`) and its figure; `shorter` the shorter chains' rows."""
    out.mkdir(parents=True, exist_ok=True)
    fields = ["tool", "setting", "integrator", "dt", "status", "t_last", "error", "cpu",
              "passages", "energy_jump", "warnings", "loops", "rtol", "scope", "estimated",
              "step_rtols"]
    with open(out / "a02.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=fields, extrasaction="ignore")
        w.writeheader()
        w.writerows({"loops": loops, **r} for r in rows)
        w.writerows({"loops": loops, **r} for r in tolerance_rows)
        w.writerows(shorter)
    lines = [
        f"# IFToMM A02: the {loops}-loop four-bar through its flat configurations",
        "",
        f"`python -m harness.a02 --loops {loops} --t-end {t_end:g}` ({seconds:.0f} s); "
        f"{sweeps.machine_line()}",
        "",
        f"The N four-bar (scenes/benchmarks/n-fourbar-{loops}.yaml; docs/benchmarks.md) over "
        f"{t_end:g} s: every half turn the linkage is flat and Φ_q loses {loops} ranks. The "
        "error is max |B0 − B0_exact| over the output points (every 0.05 s), B0_exact from "
        "the exact motion on the parallelogram branch (the one-degree-of-freedom ODE, "
        "DOP853 at rtol 1e-13). mbfg: DC, N_w = 1, defaults otherwise. CPU: process time "
        "of the run, every tool in this run.",
        "",
        "## Error against the step",
        "",
        "| tool | setting | status | reached (s) | B0 error (m) | CPU (s) | passages | "
        "largest energy change at one (J) |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['tool']} | {r['setting']} | {r['status']} | {fmt(r.get('t_last'), '.3f')} "
            f"| {fmt(r.get('error'))} | {fmt(r.get('cpu'), '.2f')} | {r.get('passages', '')} "
            f"| {fmt(r.get('energy_jump'))} |")
    lines += ["", "## Order between consecutive steps", "",
              "The error's ratio from one dt to the next finer and the order it shows, "
              "log(e₁/e₂)/log(dt₁/dt₂) (2 for the trapezoidal rule, 4 for Hermite–Simpson "
              "where the error is the integrator's).", "",
              "| integrator | dt (ms) | finer dt (ms) | error ratio | observed order |",
              "|---|---|---|---|---|"]
    for integrator in ["trapezoidal", "hermite-simpson"]:
        for d1, d2, ratio, order in observed_orders(rows, integrator):
            lines.append(f"| {integrator} | {d1 * 1e3:.4g} | {d2 * 1e3:.4g} | {ratio:.3g} "
                         f"| {order:.2f} |")
    if tolerance_rows:
        lines += tolerance_section(tolerance_rows)
    lines += ["", "## CPU time to reach each tolerance", "",
              "The least CPU time of a run within it: fixed steps, or a tolerance on the run "
              "(not one on each step, whose error is not the tolerance's).", "",
              "| tolerance | " + " | ".join(["mbfg", "IDA", "exudyn"]) + " |",
              "|---|---|---|---|"]
    for name, tol in TOLERANCES.items():
        # A tolerance on each step alone is not one on the rows: only the run's counts.
        best = fastest(list(rows) + [r for r in tolerance_rows if r["scope"] == "run"], tol,
                       t_end)
        cells = [f"{best[t]['cpu']:.2f} s ({best[t]['setting']}: {best[t]['error']:.1e} m)"
                 if t in best else "not reached" for t in ["mbfg", "IDA", "exudyn"]]
        lines.append(f"| {name} (≤ {tol:g} m) | " + " | ".join(cells) + " |")
    if shorter:
        lines += shorter_section(shorter, t_end)
    lines.append("")
    (out / "a02.md").write_text("\n".join(lines))
    try:
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
        fig, ax = plt.subplots(figsize=(6, 4))
        for integrator, style in [("trapezoidal", "o-"), ("hermite-simpson", "s--")]:
            pts = [(r["dt"], r["error"]) for r in rows if r["tool"] == "mbfg"
                   and r["integrator"] == integrator and r.get("error") is not None
                   and r["status"] == "converged"]
            if pts:
                ax.loglog(*zip(*pts), style, label=f"mbfg {integrator}")
        for tol in TOLERANCES.values():
            ax.axhline(tol, color="grey", lw=0.5)
        ax.set_xlabel("dt (s)")
        ax.set_ylabel("max B0 error (m)")
        ax.legend()
        fig.tight_layout()
        fig.savefig(out / "a02.png", dpi=100)
    except ImportError:
        pass


def shorter_section(shorter, t_end) -> list[str]:
    """The shorter chains' table: per chain and integrator, the B0 error at each step
    (✗ where the run failed), the runs converged, and the smallest observed order
    between consecutive steps while the error is above 1e-7 m (the floor of the steps
    that end just clear of a flat, docs/benchmarks.md)."""
    dts = sorted({r["dt"] for r in shorter}, reverse=True)
    lines = ["", "## The shorter chains", "",
             f"mbfg alone, the same steps over {t_end:g} s, DC, N_w = 1: max B0 error (m) at "
             "each dt (ms); ✗ a run that failed. Lowest order: the smallest observed order "
             "between consecutive steps while both errors are above 1e-7 m.", "",
             "| N | integrator | converged | " + " | ".join(f"{d * 1e3:.4g}" for d in dts)
             + " | lowest order |",
             "|---|---|---|" + "---|" * len(dts) + "---|"]
    for loops in sorted({r["loops"] for r in shorter}):
        for integrator in ["trapezoidal", "hermite-simpson"]:
            mine = {r["dt"]: r for r in shorter
                    if r["loops"] == loops and r["integrator"] == integrator}
            if not mine:
                continue
            ok = sum(r["status"] == "converged" for r in mine.values())
            cells = [fmt(mine[d].get("error"), ".1e") if d in mine
                     and mine[d]["status"] == "converged" else "✗" for d in dts]
            above = [r for r in mine.values() if r["status"] == "converged"
                     and r.get("error") is not None and r["error"] > 1e-7]
            orders = [o for _, _, _, o in observed_orders(above, integrator)]
            lowest = f"{min(orders):.2f}" if orders else ""
            lines.append(f"| {loops} | {integrator} | {ok} of {len(mine)} | "
                         + " | ".join(cells) + f" | {lowest} |")
    return lines


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m harness.a02", description=__doc__.split("\n")[0])
    ap.add_argument("--loops", type=int, default=40)
    ap.add_argument("--t-end", type=float, default=20.0)
    ap.add_argument("--out", type=pathlib.Path, default=pages.REPORTS)
    ap.add_argument("--no-peers", action="store_true", help="mbfg only")
    ap.add_argument("--shorter", default=",".join(map(str, SHORTER_CHAINS)),
                    help="the shorter chains run by mbfg alone, comma-separated ('' for none)")
    args = ap.parse_args(argv)
    started = time.perf_counter()
    rows = []
    for dt in TRAPEZOIDAL_DTS:
        rows.append(run_mbfg(args.loops, "trapezoidal", dt, args.t_end))
    for dt in HERMITE_SIMPSON_DTS:
        rows.append(run_mbfg(args.loops, "hermite-simpson", dt, args.t_end))
    tolerance_rows = [run_mbfg_rtol(args.loops, rtol, "run", args.t_end) for rtol in RUN_RTOLS]
    tolerance_rows += [run_mbfg_rtol(args.loops, rtol, "steps", args.t_end)
                       for rtol in STEP_RTOLS]
    if not args.no_peers:
        rows += [run_ida(args.loops, rtol, args.t_end) for rtol in IDA_RTOLS]
        rows += [run_exudyn(args.loops, h, args.t_end) for h in EXUDYN_STEPS]
    shorter = []
    for loops in [int(x) for x in args.shorter.split(",") if x.strip()]:
        for integrator, dts in [("trapezoidal", TRAPEZOIDAL_DTS),
                                ("hermite-simpson", HERMITE_SIMPSON_DTS)]:
            for dt in dts:
                shorter.append({"loops": loops, **run_mbfg(loops, integrator, dt, args.t_end)})
    write(rows, args.loops, args.t_end, args.out, time.perf_counter() - started, shorter,
          tolerance_rows)
    print(f"wrote {args.out / 'a02.md'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
