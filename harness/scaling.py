"""Per-step cost against the size of the mechanism: reports/scaling.md, .csv, .png.

The N four-bar (IFToMM A02, N = 1 … 100 loops: 2N + 3 coordinates) and the n-link
pendulum (n = 2 … 256 links: 3n coordinates) of scenes/scale/ (N = 40 from
scenes/benchmarks/), each in four series: DC with N_w = 1, IC with N_w = 1, DC batch (the
trapezoidal rule), and DC with N_w = 1 under Hermite–Simpson, whose µs/step the page
divides by the trapezoidal rule's; dt = 1 ms from the scene's start. µs/step is the cost of a step: the wall time of an
`mbfg.simulate` call over the common horizon of MAX_STEPS steps (0.6 s, before the N
four-bar's first flat configuration) less that of a one-step call (parsing, model
building, the sparse analyses and the first step), divided by the steps between,
each the median of the runs of REPEATS rounds over the series' sizes (a round runs
every size in turn, short runs several times, so that each median covers about
MIN_MEASURED seconds). The one-step call's time is
reported as the set-up. A size whose horizon would take more than LONG_RUN seconds
(from a one-step run in a child process and, where that takes SPLIT_FROM seconds or
more, a PROBE_STEPS-step one) is run over fewer steps, at least MIN_STEPS; a size
whose MIN_STEPS-step run would exceed BUDGET seconds (extrapolated from the smaller
sizes, or from that one step, which is stopped after BUDGET seconds) is skipped, with
every larger size of the series, and the page says so. The log-log slope of µs/step against the number of coordinates is fitted per
series over all sizes measured and over their upper half.

Beside the cost, every run is checked: max |Φ| over its steps; for the N four-bar the
distance from the parallelogram branch (every B_i at A_i + (cos θ, sin θ)) and θ
against the exact one-degree-of-freedom motion; for the pendulum the energy drift.
With a baseline CSV (an earlier reports/scaling.csv; by default
reports/scaling-baseline.csv when present) the page gives each time's speed-up
against it.

    python -m harness.scaling [--out DIR] [--repeats N] [--budget S] [--baseline CSV]
                              [--families n-fourbar,n-pendulum] [--max-size N | FAMILY=N,...]
"""
from __future__ import annotations

import argparse
import csv
import math
import pathlib
import statistics
import subprocess
import sys
import time

import numpy as np
from scipy.integrate import solve_ivp

import mbfg
from harness import pages

DT = 1e-3
REPEATS = 5           # rounds over a series' sizes
MIN_STEPS = 10
MAX_STEPS = 600       # the common horizon, 0.6 s: the N four-bar's first flat configuration is at ≥ 0.708 s
                      # (IC runs of 50 and 100 loops stop on its approach from 0.67 s)
LONG_RUN = 20.0       # s: a horizon expected to take longer is cut to about this
MIN_MEASURED = 0.5    # s: the least wall time the repeats of one median add up to
MAX_REPEATS = 40
BUDGET = 30.0         # s: the most a MIN_STEPS-step run may take
PROBE_START = 10.0    # s the one-step probe's child process is given to start
GUARD_FROM = 0.2      # a run expected to take more than this fraction of BUDGET is tried first
SPLIT_FROM = 0.02     # s: a one-step probe from which a second one separates the set-up
PROBE_STEPS = 5       # steps of that second probe
G = 9.81

FAMILIES = {
    "n-fourbar": ("N four-bar (IFToMM A02)", "N", [1, 2, 5, 10, 20, 40, 50, 100]),
    "n-pendulum": ("n-link pendulum", "n", [2, 4, 8, 16, 32, 64, 128, 256]),
}
# label, coords, keyword arguments of mbfg.simulate
SERIES = [
    ("DC N_w=1", "dc", {"window": 1}),
    ("IC N_w=1", "ic", {"window": 1}),
    ("DC batch", "dc", {"batch": True}),
    ("DC N_w=1 HS", "dc", {"window": 1, "integrator": "hermite-simpson"}),
]
# Hermite–Simpson's series and the trapezoidal one its cost per step is compared with.
HS_RATIO = ("DC N_w=1 HS", "DC N_w=1")
HS_RATIO_TARGET = 2.5


def scene(family: str, size: int) -> pathlib.Path:
    folder = "benchmarks" if (family, size) == ("n-fourbar", 40) else "scale"
    return pages.ROOT / "scenes" / folder / f"{family}-{size}.yaml"


def exact_theta(n_loops: int, times) -> np.ndarray:
    """θ(t) of the N four-bar on its parallelogram branch (docs/benchmarks.md):
    I θ̈ = −c g cos θ, I = (N+1)/3 + N, c = (N+1)/2 + N, θ(0) = π/2, θ̇(0) = −1 rad/s."""
    inertia, c = (n_loops + 1) / 3 + n_loops, (n_loops + 1) / 2 + n_loops
    sol = solve_ivp(lambda t, s: [s[1], -c * G / inertia * math.cos(s[0])], (0, times[-1]),
                    [math.pi / 2, -1.0], method="DOP853", t_eval=times, rtol=1e-12, atol=1e-12)
    return sol.y[0]


def checks(family: str, size: int, model, r) -> dict:
    """What the run's last repetition says about its accuracy (independent of mbfg's
    own summary)."""
    q = np.asarray(r.q)
    out = {"max_phi": max(float(np.max(np.abs(model.phi(qk)))) for qk in q)}
    if family == "n-fourbar":
        names = model.names
        th = q[:, names.index("theta")]
        dev = 0.0
        for i in range(size + 1):
            dev = max(dev, float(np.max(np.abs(q[:, names.index(f"B{i}.x")] - i - np.cos(th)))),
                      float(np.max(np.abs(q[:, names.index(f"B{i}.y")] - np.sin(th)))))
        out["branch_dev_m"] = dev
        out["theta_err_rad"] = float(np.max(np.abs(th - exact_theta(size, np.asarray(r.t)))))
    else:
        out["energy_drift_j"] = r.summary["energy_drift"]
    return out


def run_once(path, coords, kw, steps):
    start = time.perf_counter()
    r = mbfg.simulate(str(path), coords=coords, dt=DT, t_end=steps * DT, **kw)
    return r, time.perf_counter() - start


CHILD = """
import sys, time, mbfg
def one():
    start = time.perf_counter()
    mbfg.simulate(sys.argv[1], coords=sys.argv[2], dt=float(sys.argv[3]), t_end=float(sys.argv[4]),
                  integrator=sys.argv[7],
                  **({"batch": True} if sys.argv[5] == "batch" else {"window": int(sys.argv[5])}))
    return time.perf_counter() - start
first = one()
print(first if first > 0.1 or sys.argv[6] == "once" else min(first, one()))
"""


def in_child(path, coords, kw, steps, timeout, once) -> float | None:
    """Seconds of a `steps`-step run in a child process stopped after `timeout` seconds
    (then None); unless `once`, the better of two runs when short (a process's first run
    pays for more than its steps)."""
    mode = "batch" if kw.get("batch") else str(kw["window"])
    try:
        out = subprocess.run([sys.executable, "-c", CHILD, str(path), coords, repr(DT),
                              repr(steps * DT), mode, "once" if once else "best",
                              kw.get("integrator", "trapezoidal")],
                             capture_output=True, text=True, timeout=timeout, cwd=pages.ROOT)
    except subprocess.TimeoutExpired:
        return None
    if out.returncode != 0:
        lines = out.stderr.strip().splitlines()
        raise RuntimeError(lines[-1] if lines else f"child run exited with {out.returncode}")
    return float(out.stdout.strip().splitlines()[-1])


def probe(path, coords, kw, timeout):
    """Seconds of a one-step run (with the set-up a run pays once), or None after
    `timeout` seconds: a step can take minutes."""
    return in_child(path, coords, kw, 1, timeout, once=False)


def split_setup(path, coords, kw, one, budget) -> tuple[float, float]:
    """(seconds per step, seconds of set-up) from the one-step probe `one` and, when
    it is long enough for the set-up (parsing, assembly, first factorizations) to
    matter, a PROBE_STEPS-step one: so that a large mechanism's horizon is cut only
    where its steps, not its set-up, would make it longer than LONG_RUN."""
    if one < SPLIT_FROM:
        return one, 0.0
    few = in_child(path, coords, kw, PROBE_STEPS, timeout=budget + PROBE_START, once=False)
    if few is None:
        return one, 0.0
    if few <= one:
        # The set-up outweighs the steps' cost and the noise: few / PROBE_STEPS
        # bounds a step's cost from above.
        return few / PROBE_STEPS, max(0.0, one - few / PROBE_STEPS)
    per_step = max((few - one) / (PROBE_STEPS - 1), one / PROBE_STEPS)
    return per_step, max(0.0, one - per_step)


def run_within(path, coords, kw, steps, timeout) -> bool:
    """Whether a `steps`-step run finishes within `timeout` seconds."""
    return in_child(path, coords, kw, steps, timeout, once=True) is not None


def measure_series(family, sizes, label, coords, kw, repeats, budget, models) -> list[dict]:
    """The rows of one series: each size planned (its horizon, or why it is skipped)
    and run once, then measured in rounds over all its sizes, so that the machine's
    slow spells (a run can take 1.7× its usual time for seconds on end) fall on every
    size alike instead of on the sizes measured during them."""
    rows, plans = [], []
    measured = []                  # (coordinates, seconds per step), ascending
    skipped_from = None
    for size in sizes:
        model = models[size]
        row = {"family": family, "size": size, "n": model.n, "m": model.m, "dof": model.dof,
               "series": label}
        rows.append(row)
        if skipped_from is not None:
            row["status"] = f"skipped: {family}-{skipped_from} already over the budget"
            continue
        reason = None            # why the size is skipped
        if measured:
            # Extrapolated from the sizes measured with the series' last local slope (at
            # least 1, the cost being at least linear in n): over the budget, the size is
            # skipped without running (one step of it alone could take many minutes).
            (n0, t0), (n1, t1) = (measured[-2] if len(measured) > 1 else measured[-1]), measured[-1]
            k = max(1.0, math.log(t1 / t0) / math.log(n1 / n0)) if n1 > n0 else 1.0
            guess = t1 * (model.n / n1) ** k * MIN_STEPS
            if guess > budget:
                reason = (f"{MIN_STEPS} steps ≈ {guess:.0f} s (extrapolated with slope "
                          f"{k:.1f}) > budget {budget:g} s")
        path = scene(family, size)
        try:
            if reason is None:
                one = probe(path, coords, kw, timeout=budget + PROBE_START)
                if one is None:
                    reason = f"one step did not finish within {budget:g} s"
                elif one * MIN_STEPS > budget:
                    reason = (f"{MIN_STEPS} steps ≈ {one * MIN_STEPS:.0f} s (one step "
                              f"{one:.1f} s) > budget {budget:g} s")
                else:
                    per_step, setup = split_setup(path, coords, kw, one, budget)
                    steps = MAX_STEPS
                    if setup + per_step * steps > LONG_RUN:
                        steps = int(max(MIN_STEPS, (LONG_RUN - setup) / per_step))
                    # A later step may take far longer than the first (a solve that
                    # crawls to its iteration limit): a long run is tried in a child
                    # process first, and given up after the budget.
                    if setup + per_step * steps > GUARD_FROM * budget and not run_within(
                            path, coords, kw, steps, budget + PROBE_START):
                        reason = (f"{steps} steps did not finish within {budget:g} s (the "
                                  f"first step took {one:.1f} s)")
            if reason is not None:
                skipped_from = size
                row["status"] = f"skipped: {reason}"
                pages.progress(f"  {family}-{size} {label}: {row['status']}")
                continue
            r, whole = run_once(path, coords, kw, steps)
            first = run_once(path, coords, kw, 1)[1]
            assert r.summary["complete"] and len(r.t) == steps + 1
            row.update(mean_iterations=r.summary["mean_iterations"],
                       mean_factorizations=r.summary.get("mean_factorizations"),
                       **checks(family, size, model, r))
            # Short runs are repeated within a round, up to MIN_MEASURED seconds in all.
            inner = max(1, min(MAX_REPEATS // repeats,
                               math.ceil(MIN_MEASURED / (repeats * (whole + first)))))
            plans.append({"row": row, "path": path, "steps": steps, "inner": inner,
                          "wholes": [whole], "firsts": [first]})
            measured.append((model.n, max(whole - first, 0.1 * whole) / steps))
        except (mbfg.SolveError, RuntimeError, ValueError) as e:
            row["status"] = f"failed: {str(e).splitlines()[0][:200]}"
            pages.progress(f"  {family}-{size} {label}: {row['status']}")
    for round_ in range(repeats):
        for plan in plans:
            if "status" in plan["row"]:
                continue
            try:
                for _ in range(plan["inner"] if round_ or repeats == 1 else plan["inner"] - 1):
                    plan["wholes"].append(run_once(plan["path"], coords, kw, plan["steps"])[1])
                    plan["firsts"].append(run_once(plan["path"], coords, kw, 1)[1])
            except (mbfg.SolveError, RuntimeError, ValueError) as e:
                plan["row"]["status"] = f"failed: {str(e).splitlines()[0][:200]}"
    for plan in plans:
        row, steps = plan["row"], plan["steps"]
        if "status" in row:
            continue
        whole, first = statistics.median(plan["wholes"]), statistics.median(plan["firsts"])
        if whole <= first:
            row["status"] = (f"failed: the {steps}-step run ({whole:.3g} s) was no slower "
                             f"than the one-step run ({first:.3g} s): timing noise")
            continue
        us = (whole - first) / (steps - 1) * 1e6
        row.update(steps=steps, us_per_step=us, setup_ms=first * 1e3,
                   us_per_step_whole=whole / steps * 1e6, wall_s=whole,
                   runs=len(plan["wholes"]), status="ok")
        pages.progress(f"  {family}-{row['size']} {label}: {us:.0f} µs/step ({steps} steps, "
                       f"set-up {first * 1e3:.1f} ms, {len(plan['wholes'])} runs, max |Φ| "
                       f"{row['max_phi']:.1e})")
    return rows


def slope(rows: list[dict], upper_half: bool) -> float | None:
    """Least-squares slope of log µs/step against log n over the rows measured (the
    upper half of them by size when asked); None with fewer than two."""
    ok = sorted((r for r in rows if r.get("status") == "ok"), key=lambda r: r["n"])
    if upper_half:
        ok = ok[len(ok) // 2:]
    if len(ok) < 2:
        return None
    x = np.log([r["n"] for r in ok])
    y = np.log([r["us_per_step"] for r in ok])
    return float(np.polyfit(x, y, 1)[0])


def read_baseline(path: pathlib.Path | None) -> dict:
    """(family, size, series) → µs/step of an earlier scaling.csv."""
    if path is None or not path.exists():
        return {}
    out = {}
    with open(path, newline="") as f:
        for r in csv.DictReader(f):
            if r.get("status") == "ok" and r.get("us_per_step"):
                out[(r["family"], int(r["size"]), r["series"])] = float(r["us_per_step"])
    return out


def plot(rows: list[dict], fits: dict, path: pathlib.Path) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, ax = plt.subplots(figsize=(9, 6))
    styles = {"n-fourbar": "o-", "n-pendulum": "s--"}
    for family, (title, _, _) in FAMILIES.items():
        for label, _, _ in SERIES:
            ok = sorted((r for r in rows if r["family"] == family and r["series"] == label
                         and r.get("status") == "ok"), key=lambda r: r["n"])
            if not ok:
                continue
            s_all, s_up = fits[(family, label)]
            ax.loglog([r["n"] for r in ok], [r["us_per_step"] for r in ok], styles[family],
                      markersize=4,
                      label=f"{title}, {label}: slope {fmt(s_up, '.2f')} (upper half), "
                            f"{fmt(s_all, '.2f')} (all)")
    ns = sorted({r["n"] for r in rows if r.get("status") == "ok"})
    if ns:
        ref = min(r["us_per_step"] for r in rows if r.get("status") == "ok")
        ax.loglog(ns, [ref * n / ns[0] for n in ns], ":", color="grey", label="slope 1 (linear)")
    ax.set_xlabel("n, number of coordinates")
    ax.set_ylabel("µs per step (horizon's wall time less one step's, per step)")
    ax.set_title("Per-step cost against the size of the mechanism (dt = 1 ms)")
    ax.grid(True, which="both", alpha=0.3)
    if ax.get_legend_handles_labels()[0]:
        ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def fmt(v, spec=".2e") -> str:
    return "—" if v is None else format(v, spec)


def hs_ratios(rows: list[dict]) -> list[tuple[str, int, float]]:
    """(family, size, Hermite–Simpson's µs/step ÷ the trapezoidal rule's) where both
    series measured the size."""
    ok = {(r["family"], r["size"], r["series"]): r["us_per_step"] for r in rows
          if r.get("status") == "ok"}
    hs, tr = HS_RATIO
    return [(family, size, ok[(family, size, hs)] / ok[(family, size, tr)])
            for family, (_, _, sizes) in FAMILIES.items() for size in sizes
            if (family, size, hs) in ok and (family, size, tr) in ok]


def hs_ratio_lines(rows: list[dict]) -> list[str]:
    ratios = hs_ratios(rows)
    if not ratios:
        return []
    lines = [f"| mechanism | size | HS ÷ trapezoidal µs/step | target ≤ {HS_RATIO_TARGET:g} |",
             "|---|---|---|---|"]
    for family, size, ratio in ratios:
        verdict = "met" if ratio <= HS_RATIO_TARGET else "not met"
        lines.append(f"| {FAMILIES[family][0]} | {size} | {ratio:.2f} | {verdict} |")
    return lines


def family_table(family: str, rows: list[dict], baseline: dict) -> str:
    title, letter, sizes = FAMILIES[family]
    head = f"| {letter} | coordinates | equations | dof |"
    for label, _, _ in SERIES:
        head += f" {label} µs/step (steps; set-up ms) |" + (f" {label} × baseline |" if baseline else "")
    head += " max \\|Φ\\| |"
    head += " branch deviation (m) | θ − exact (rad) |" if family == "n-fourbar" else " energy drift (J) |"
    lines = [head, "|" + "---|" * (head.replace("\\|", "").count("|") - 1)]
    for size in sizes:
        by = {r["series"]: r for r in rows if r["family"] == family and r["size"] == size}
        if not by:
            continue
        any_row = next(iter(by.values()))
        line = f"| {size} | {any_row['n']} | {any_row['m']} | {any_row['dof']} |"
        oks = [r for r in by.values() if r.get("status") == "ok"]
        for label, _, _ in SERIES:
            r = by.get(label, {})
            if r.get("status") == "ok":
                line += f" {r['us_per_step']:.0f} ({r['steps']}; {r['setup_ms']:.1f}) |"
                b = baseline.get((family, size, label))
                if baseline:
                    line += f" {b / r['us_per_step']:.2f} |" if b else " — |"
            else:
                line += " skipped |" if str(r.get("status", "")).startswith("skipped") else " failed |"
                if baseline:
                    line += " — |"
        line += f" {fmt(max((r['max_phi'] for r in oks), default=None), '.0e')} |"
        if family == "n-fourbar":
            line += (f" {fmt(max((r['branch_dev_m'] for r in oks), default=None), '.0e')} |"
                     f" {fmt(max((r['theta_err_rad'] for r in oks), default=None), '.1e')} |")
        else:
            drifts = [r["energy_drift_j"] for r in oks if r.get("energy_drift_j") is not None]
            line += f" {fmt(max(drifts, default=None), '.1e')} |"
        lines.append(line)
    return "\n".join(lines)


def write(reports: pathlib.Path, machine: str, families=None, repeats=REPEATS,
          budget=BUDGET, baseline_path=None, max_size=None) -> list[dict]:
    reports.mkdir(parents=True, exist_ok=True)
    if baseline_path is None:
        baseline_path = reports / "scaling-baseline.csv"
    baseline = read_baseline(baseline_path)
    began = time.perf_counter()
    rows = []
    left_out = []
    for family, (title, _, sizes) in FAMILIES.items():
        if families is not None and family not in families:
            continue
        # One bound for every family, or per family ({family: size}).
        bound = max_size.get(family) if isinstance(max_size, dict) else max_size
        left_out += [f"{family}-{s}" for s in sizes if bound is not None and s > bound]
        sizes = [s for s in sizes if bound is None or s <= bound]
        models = {s: mbfg.load(str(scene(family, s))) for s in sizes}
        for label, coords, kw in SERIES:
            pages.progress(f"scaling: {title}, {label}")
            rows += measure_series(family, sizes, label, coords, kw, repeats, budget, models)
    fits = {(f, label): (slope([r for r in rows if r["family"] == f and r["series"] == label], False),
                         slope([r for r in rows if r["family"] == f and r["series"] == label], True))
            for f in FAMILIES for label, _, _ in SERIES}
    plot(rows, fits, reports / "scaling.png")
    pages.write_csv(reports / "scaling.csv", rows)

    slope_lines = ["| mechanism | series | sizes measured | slope, all sizes | slope, upper half | target ≤ 1.2 |",
                   "|---|---|---|---|---|---|"]
    for family, (title, _, _) in FAMILIES.items():
        for label, _, _ in SERIES:
            ok = sorted(r["size"] for r in rows if r["family"] == family and r["series"] == label
                        and r.get("status") == "ok")
            if not ok and not any(r["family"] == family for r in rows):
                continue
            s_all, s_up = fits[(family, label)]
            verdict = "—" if s_up is None else ("met" if s_up <= 1.2 else "not met")
            span = f"{ok[0]} … {ok[-1]} ({len(ok)})" if ok else "none"
            slope_lines.append(f"| {title} | {label} | {span} | {fmt(s_all, '.2f')} | "
                               f"{fmt(s_up, '.2f')} | {verdict} |")
    ratio_lines = hs_ratio_lines(rows)
    not_run = [r for r in rows if r.get("status") != "ok"]
    measured = [r for r in rows if r.get("status") == "ok"]
    worst_phi = max((r["max_phi"] for r in measured), default=None)
    summary = (f"scaling: {len(measured)} of {len(rows)} runs measured, "
               f"{sum(str(r.get('status')).startswith('skipped') for r in rows)} skipped over the "
               f"budget, {sum(str(r.get('status')).startswith('failed') for r in rows)} failed; "
               f"max |Φ| {fmt(worst_phi, '.0e')}")
    parts = [
        "# Per-step cost against the size of the mechanism\n",
        summary + "\n",
        f"Machine: {machine}. Generated by `python -m harness.scaling` "
        f"(`python -m harness.report --only scaling`) in {time.perf_counter() - began:.0f} s.\n",
        "Scenes: `scenes/scale/` (written by `python -m harness.scale_scenes`; N = 40 is "
        "`scenes/benchmarks/n-fourbar-40.yaml`), described in "
        "[docs/benchmarks.md](../docs/benchmarks.md). The N four-bar has N + 1 cranks and N "
        "couplers (2N + 3 coordinates, one degree of freedom), the n-link pendulum n links "
        "(3n coordinates: the points' x, y and the link angles, n degrees of freedom). "
        f"dt = {DT * 1e3:g} ms from the scene's start. µs/step is the cost of a step: the "
        f"wall time of an `mbfg.simulate` call over the common horizon ({MAX_STEPS} steps, "
        f"{MAX_STEPS * DT:g} s) less that of a one-step call, divided by the steps between; "
        "the one-step call's time (parsing, model building, the sparse analyses and the "
        "first step) is the set-up, in milliseconds after the steps in parentheses. Each "
        f"time is the median of the runs of {repeats} rounds over the series' sizes, made "
        "one at a time, the two kinds alternating (a round runs every size in turn, so that "
        "the machine's slow spells fall on every size alike; short runs several times a "
        f"round, until they add up to {MIN_MEASURED:g} s, at most {MAX_REPEATS}; the runs "
        "of each are in the CSV). A size whose horizon would take more "
        f"than {LONG_RUN:g} s is run over fewer steps (at least {MIN_STEPS}; estimated from a "
        f"one-step run in a child process and, where that takes {SPLIT_FROM:g} s or more, a "
        f"{PROBE_STEPS}-step one); a size whose {MIN_STEPS}-step run would take more than "
        f"{budget:g} s (extrapolated from the smaller sizes with the series' last local slope, "
        "at least 1, or estimated from one step) is skipped, with the larger sizes of its "
        "series; so is a size whose run, expected to take more than "
        f"{GUARD_FROM * budget:g} s, does not finish within {budget:g} s when tried first in a "
        "child process (a later step can take far longer than the first). "
        "The whole call's time divided by its steps is in the CSV (`us_per_step_whole`). "
        "The slopes are least-squares fits of "
        "log µs/step against log n (n = number of coordinates); the upper half is the larger "
        "half of the sizes measured. Raw numbers: [scaling.csv](scaling.csv).\n",
        "![µs per step against the number of coordinates](scaling.png)\n",
        "## Slopes\n",
        "\n".join(slope_lines) + "\n",
    ]
    if ratio_lines:
        parts += ["## Hermite–Simpson against the trapezoidal rule\n",
                  f"µs/step of {HS_RATIO[0]} divided by {HS_RATIO[1]}'s, size by size (both "
                  "medians of this run's rounds): what a Hermite–Simpson step costs in "
                  "trapezoidal steps, target ≤ "
                  f"{HS_RATIO_TARGET:g}.\n",
                  "\n".join(ratio_lines) + "\n"]
    if baseline:
        parts.append(f"`× baseline` is the baseline's µs/step divided by this run's "
                     f"(`{baseline_path.name}`: an earlier run of this page; > 1 is faster "
                     f"now).\n")
    for family, (title, _, _) in FAMILIES.items():
        if not any(r["family"] == family for r in rows):
            continue
        check = ("max |Φ| over every step of the runs; branch deviation: the largest "
                 "|B_i − A_i − (cos θ, sin θ)| (0 on the parallelogram branch); θ − exact: "
                 "against the one-degree-of-freedom motion I θ̈ = −c g cos θ (scipy, "
                 "rtol 1e-12), over the horizon run" if family == "n-fourbar" else
                 "max |Φ| over every step of the runs; energy drift: mbfg's max |E(t) − E(0)| "
                 "(the pendulum is conservative)")
        parts.append(f"## {title}\n\n{check}; each the worst of the series measured.\n\n"
                     + family_table(family, rows, baseline) + "\n")
        work = [r for r in rows if r["family"] == family and r["series"] == SERIES[0][0]
                and r.get("status") == "ok" and r.get("mean_factorizations") is not None]
        if work:
            parts.append(f"What a {SERIES[0][0]} step did, on average (Newton iterations / "
                         "sparse LU factorizations): " + ", ".join(
                             f"{r['size']}: {r['mean_iterations']:.1f} / "
                             f"{r['mean_factorizations']:.2f}" for r in work) + ".\n")
    if not_run:
        parts.append("## Not measured\n\n" + "\n".join(
            f"- {r['family']}-{r['size']} {r['series']}: {r['status']}" for r in not_run) + "\n")
    if left_out:
        parts.append("## Left out\n\nAbove `--max-size`, not run: " + ", ".join(left_out)
                     + ".\n")
    (reports / "scaling.md").write_text("\n".join(parts))
    pages.progress(f"wrote {reports}/scaling.md, scaling.csv, scaling.png")
    return rows


def parse_max_size(text: str | None) -> int | dict | None:
    """`--max-size`: None, one size for every family, or {family: size}."""
    if text is None:
        return None
    if "=" not in text:
        try:
            return int(text)
        except ValueError:
            raise ValueError(f"--max-size: '{text}' is not a whole number") from None
    bounds = {}
    for pair in text.split(","):
        family, _, size = pair.partition("=")
        family = family.strip()
        if family not in FAMILIES:
            raise ValueError(f"--max-size: unknown family '{family}'; one of "
                             f"{', '.join(FAMILIES)}")
        try:
            bounds[family] = int(size)
        except ValueError:
            raise ValueError(f"--max-size: '{size}' for {family} is not a whole number") from None
    return bounds


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m harness.scaling",
                                 description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=pathlib.Path, default=pages.REPORTS,
                    help="folder for scaling.md, .csv, .png (default: reports/)")
    ap.add_argument("--repeats", type=int, default=REPEATS,
                    help="rounds over each series' sizes; each time is the median of their runs "
                         "(default: %(default)s)")
    ap.add_argument("--budget", type=float, default=BUDGET,
                    help=f"seconds a {MIN_STEPS}-step run may take before its size is skipped "
                         "(default: %(default)s)")
    ap.add_argument("--baseline", type=pathlib.Path, default=None,
                    help="an earlier scaling.csv to compare with (default: "
                         "OUT/scaling-baseline.csv when present)")
    ap.add_argument("--families", default=",".join(FAMILIES),
                    help="comma-separated (default: %(default)s)")
    ap.add_argument("--max-size", default=None,
                    help="largest N or n measured: one number for every family, or "
                         "FAMILY=SIZE pairs, comma-separated (n-pendulum=64)")
    args = ap.parse_args(argv)
    chosen = [f.strip() for f in args.families.split(",") if f.strip()]
    unknown = [f for f in chosen if f not in FAMILIES]
    if unknown or not chosen:
        ap.error(f"unknown famil(ies) {', '.join(unknown)}; one of {', '.join(FAMILIES)}")
    if args.repeats < 1 or args.budget <= 0:
        ap.error("--repeats must be at least 1 and --budget positive")
    try:
        max_size = parse_max_size(args.max_size)
    except ValueError as e:
        ap.error(str(e))
    write(args.out, pages.machine(), chosen, args.repeats, args.budget, args.baseline,
          max_size)
    return 0


if __name__ == "__main__":
    sys.exit(main())
