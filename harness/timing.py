"""Accuracy against wall time, every tool measured in one run on one machine.

For each scene of SCENES: mbfg (DC and IC; the trapezoidal rule with N_w = 1 and 5, dt
from 10 to 0.1 ms; Hermite–Simpson with N_w = 1, dt from 20 to 0.25 ms; error-controlled
steps at the tolerances of RTOL_SWEEPS) and every
registered generator's sweeps (harness/generators.py: exudyn generalized-alpha and
trapezoidal index-2, h from 1 ms to 10 µs; IDA, tolerances 1e-4…1e-12; Pinocchio RK4
and adaptive DOP853 where it models the scene). Errors (RMSE and max over the moving points' x, y)
against the committed reference; wall times are medians of REPEATS runs of the whole
call. Writes accuracy-vs-time.md, .csv and one PNG per scene (several minutes).

    python -m harness.timing [--out DIR] [--scenes four-bar,slider-crank] [--repeats N]
"""
from __future__ import annotations

import argparse
import functools
import itertools
import pathlib
import statistics
import sys
import time

import mbfg
from harness import generators, pages
from harness import sweep as sweeps
from harness import trajectory as tj

REPEATS = 3
MBFG_DTS = [1e-2, 5e-3, 2e-3, 1e-3, 5e-4, 2e-4, 1e-4]
# Hermite–Simpson: fourth order, so coarser steps reach the same levels.
HS_DTS = [2e-2, 1e-2, 5e-3, 2e-3, 1e-3, 5e-4, 2.5e-4]
# Error-controlled steps (--rtol = --atol): Hermite–Simpson over every level; the
# trapezoidal rule, second order, takes over a second beyond 1e-6.
RTOL_SWEEPS = [("hermite-simpson", [1e-3, 1e-4, 1e-5, 1e-6, 1e-7, 1e-8, 1e-9, 1e-10]),
               ("trapezoidal", [1e-3, 1e-4, 1e-5, 1e-6])]
LEVELS = [1e-3, 1e-4, 1e-5, 1e-6, 1e-7, 1e-8, 1e-9, 1e-10]

# scene title → DC scene, IC scene (None: DC only), reference, horizon (s)
SCENES = {
    "four-bar": ("fourbar", "fourbar-theta", "fourbar", 5.0),
    "slider-crank": ("slider-crank", "slider-crank", "slider-crank", 5.0),
    "double pendulum": ("double-pendulum", "double-pendulum", "double-pendulum", 5.0),
    "robot": ("pick-and-place", None, "pick-and-place", 1.0),
}


def timed(fn, repeats: int | None = None):
    """(result of the last run, median wall time); a failure ends the repetitions."""
    times, out = [], None
    for _ in range(repeats or REPEATS):
        start = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - start)
    return out, statistics.median(times)


def configurations(dc_scene, ic_scene, t_end):
    """(tool, variant, setting, callable returning (t, q)) for every point of the plot."""
    dc = pages.scene_path(dc_scene)
    variants = [("DC", dc)] + ([("IC", pages.scene_path(ic_scene))] if ic_scene else [])
    for coords, scene in variants:
        sweeps = [("trapezoidal", w, MBFG_DTS) for w in (1, 5)] + [("hermite-simpson", 1, HS_DTS)]
        for integrator, w, dts in sweeps:
            name = "HS " if integrator == "hermite-simpson" else ""
            for dt in dts:
                def run(scene=scene, coords=coords, w=w, dt=dt, integrator=integrator):
                    r = mbfg.simulate(scene, coords=coords.lower(), dt=dt, t_end=t_end, window=w,
                                      integrator=integrator)
                    return r.t, r.q
                yield "mbfg", f"{name}{coords}, N_w = {w}", f"dt = {dt * 1e3:g} ms", run
        # Error-controlled steps: the tolerance asked, rows on the 1 ms grid.
        for integrator, rtols in RTOL_SWEEPS:
            name = "HS " if integrator == "hermite-simpson" else ""
            for rtol in rtols:
                def run(scene=scene, coords=coords, rtol=rtol, integrator=integrator):
                    r = mbfg.simulate(scene, coords=coords.lower(), dt=1e-3, t_end=t_end,
                                      integrator=integrator, rtol=rtol)
                    return r.t, r.q
                yield "mbfg", f"{name}{coords}, rtol", f"rtol = {rtol:g}", run
    model = mbfg.load(str(dc))
    for gen in generators.REGISTRY.values():
        why = gen.refusal(model)       # checked here: not part of the timed call
        for variant, key, values, extra in gen.sweeps:
            for v in values:
                def run(gen=gen, key=key, v=v, extra=extra, why=why):
                    if why:
                        raise tj.Unsupported(why)
                    traj, _ = gen.generate(dc, t_end, 1e-3, {**extra, key: v})
                    return traj.t, traj.q
                yield gen.label, variant, f"{key} = {v:g}", run


def measure(title, dc_scene, ic_scene, ref, t_end, sweep=None) -> list[dict]:
    """Every point of a scene's plot: timing cells, run one at a time (`sweep`'s timing
    phase, harness/sweep.py; None: in this process)."""
    n = sum(1 for _ in configurations(dc_scene, ic_scene, t_end))
    cells = [(title, k, REPEATS) for k in range(n)]

    def done(_, row):
        pages.progress(f"  {title}: {row['tool']} {row['variant']} {row['setting']}: "
                       + (f"RMSE {row['rmse_m']:.2e} m in {row['wall_time_s'] * 1e3:.0f} ms"
                          if row["status"] == "ok" else row["status"]))
    if sweep is None:
        rows = []
        for cell in cells:
            rows.append(measure_point(cell))
            done(cell, rows[-1])
        return rows
    return sweep.one_at_a_time(measure_point, cells, f"accuracy against time: {title}",
                               done=done)


@functools.lru_cache(maxsize=None)
def truth_of(ref: str):
    return pages.load_reference(ref)[0], mbfg.load(pages.scene_path(ref))


def measure_point(cell: tuple) -> dict:
    """One timing cell: (scene title, index of the configuration, repeats) → its row."""
    title, k, repeats = cell
    dc_scene, ic_scene, ref, t_end = SCENES[title]
    tool, variant, setting, run = next(itertools.islice(
        configurations(dc_scene, ic_scene, t_end), k, None))
    truth, model = truth_of(ref)
    row = {"scene": title, "tool": tool, "variant": variant, "setting": setting}
    try:
        (t, q), wall = timed(run, repeats)
        rmse, mx = pages.errors(model, t, q[:, :model.n], truth)
        row.update(rmse_m=rmse, max_m=mx, wall_time_s=wall, status="ok")
    except tj.Unsupported as e:
        row.update(status=f"refused: {e}")
    except (mbfg.SolveError, RuntimeError, ValueError) as e:
        row.update(status=f"failed: {str(e).splitlines()[0][:160]}")
    return row


def fastest_table(rows: list[dict]) -> str:
    lines = ["| RMSE ≤ | fastest tool (setting) | its time | mbfg's fastest (setting) | mbfg time "
             "| mbfg / fastest | mbfg with a tolerance (setting) | its time |",
             "|---|---|---|---|---|---|---|---|"]
    ok = [r for r in rows if r["status"] == "ok"]
    for level in LEVELS:
        reach = [r for r in ok if r["rmse_m"] <= level]
        # The error-controlled setting beside the fixed steps: its fastest that reaches it.
        tolerance = [r for r in reach if r["tool"] == "mbfg" and r["variant"].endswith("rtol")]
        tol = min(tolerance, key=lambda r: r["wall_time_s"]) if tolerance else None
        tol_cells = (f"{tol['variant']} ({tol['setting']}) | {tol['wall_time_s'] * 1e3:.0f} ms |"
                     if tol else "does not reach it | — |")
        if not reach:
            lines.append(f"| {level:.0e} | nobody | — | — | — | — | — | — |")
            continue
        best = min(reach, key=lambda r: r["wall_time_s"])
        ours = [r for r in reach if r["tool"] == "mbfg"]
        mine = min(ours, key=lambda r: r["wall_time_s"]) if ours else None
        lines.append(
            f"| {level:.0e} | {best['tool']} {best['variant']} ({best['setting']}) | "
            f"{best['wall_time_s'] * 1e3:.0f} ms | "
            + (f"{mine['variant']} ({mine['setting']}) | {mine['wall_time_s'] * 1e3:.0f} ms | "
               f"{mine['wall_time_s'] / best['wall_time_s']:.2f} | " if mine
               else "does not reach it | — | — | ")
            + tol_cells)
    return "\n".join(lines)


def plot(rows: list[dict], title: str, path: pathlib.Path) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    ok = [r for r in rows if r["status"] == "ok"]
    fig, axes = plt.subplots(1, 2, figsize=(12, 5), sharex=True)
    series = sorted({(r["tool"], r["variant"]) for r in ok})
    for tool, variant in series:
        pts = sorted((r for r in ok if (r["tool"], r["variant"]) == (tool, variant)),
                     key=lambda r: r["wall_time_s"])
        style = "o-" if tool == "mbfg" else "s--"
        for ax, key in zip(axes, ["rmse_m", "max_m"]):
            ax.loglog([p["wall_time_s"] for p in pts], [max(p[key], 1e-16) for p in pts], style,
                      label=f"{tool} {variant}", markersize=4)
    for ax, name in zip(axes, ["RMSE (m)", "max error (m)"]):
        ax.set_xlabel("wall time (s, median of 3)")
        ax.set_ylabel(name)
        ax.grid(True, which="both", alpha=0.3)
    axes[0].legend(fontsize=7)
    fig.suptitle(f"{title}: error against wall time (smaller and further left is better)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def write(reports: pathlib.Path, machine: str | None = None, scenes=None,
          sweep=None) -> list[dict]:
    """The page, its CSV and plots; `machine`: the line of the machine the times are
    from (default: sweep.machine(), else this one's)."""
    if machine is None:
        machine = sweep.machine() if sweep is not None else pages.machine()
    all_rows, parts = [], []
    reports.mkdir(parents=True, exist_ok=True)
    for title, (dc, ic, ref, t_end) in SCENES.items():
        if scenes is not None and title not in scenes:
            continue
        pages.progress(f"accuracy against time: {title}")
        rows = measure(title, dc, ic, ref, t_end, sweep)
        all_rows += rows
        png = f"accuracy-vs-time-{ref}.png"
        plot(rows, title, reports / png)
        failed = [r for r in rows if r["status"] != "ok"]
        parts.append(f"## {title} ({t_end:g} s)\n\n![{title}]({png})\n\n" + fastest_table(rows)
                     + ("\n\nRuns that did not finish or were refused:\n\n"
                        + "\n".join(f"- {r['tool']} {r['variant']} {r['setting']}: {r['status']}"
                                    for r in failed) if failed else "") + "\n")
    page = ("# Accuracy against wall time\n\n"
            f"All tools measured in one run on one machine ({machine}); wall times are medians of "
            f"{REPEATS} runs of the whole call (model building included, files not written), each "
            "point measured alone, with nothing else of the report running. Errors "
            "over the x, y of the moving points against the committed reference, at its 1 ms "
            "samples. mbfg: default noise; the trapezoidal rule at dt ∈ {10, 5, 2, 1, 0.5, 0.2, "
            "0.1} ms, and Hermite–Simpson (`HS`, fourth order) at dt ∈ {20, 10, 5, 2, 1, 0.5, "
            "0.25} ms; and error-controlled steps (`rtol`: `rtol = atol`, the steps' sizes "
            "chosen by mbfg, rows on the 1 ms grid), Hermite–Simpson at rtol ∈ {1e-3 … 1e-10} "
            "and the trapezoidal rule at rtol ∈ {1e-3 … 1e-6}. Pinocchio: RK4 at fixed h, and scipy's adaptive DOP853 at rtol = atol. "
            "IDA: BDF with the module's closed-form Jacobians. "
            "Raw numbers: [accuracy-vs-time.csv](accuracy-vs-time.csv).\n\n" + "\n".join(parts))
    (reports / "accuracy-vs-time.md").write_text(page)
    pages.write_csv(reports / "accuracy-vs-time.csv", all_rows)
    pages.progress(f"wrote {tj.display_path(reports)}/accuracy-vs-time.md, .csv, .png")
    return all_rows


def main(argv=None) -> int:
    global REPEATS
    ap = argparse.ArgumentParser(prog="python -m harness.timing",
                                 description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=pathlib.Path, default=pages.REPORTS,
                    help="folder for accuracy-vs-time.md, .csv, .png (default: reports/)")
    ap.add_argument("--scenes", default=",".join(SCENES),
                    help="comma-separated scene titles (default: %(default)s)")
    ap.add_argument("--repeats", type=int, default=REPEATS,
                    help="runs per point, the median is kept (default: %(default)s)")
    sweeps.add_argument(ap)
    args = ap.parse_args(argv)
    chosen = [t.strip() for t in args.scenes.split(",") if t.strip()]
    unknown = [t for t in chosen if t not in SCENES]
    if unknown or not chosen:
        ap.error(f"unknown scene title(s) {', '.join(unknown)}; one of {', '.join(SCENES)}")
    if args.repeats < 1:
        ap.error("--repeats must be at least 1")
    REPEATS = args.repeats
    with sweeps.from_args(args) as sweep:
        write(args.out, scenes=chosen, sweep=sweep)
    return 0


if __name__ == "__main__":
    # As harness.timing, not __main__: the sweep's tasks name its functions, which the
    # Dask scheduler and workers import.
    from harness import timing
    sys.exit(timing.main())
