"""Long horizons: `mbfg simulate` on the four-bar at dt = 1 ms for 1e3 … 1e6 steps,
with the fixed-lag smoother (N_w = 1 and 10) and the batch, each run a process of its
own: its wall time and its peak resident memory (the kernel's high-water mark, through
GNU `time`), the log-log slopes of both against the number of steps, and the page
reports/horizons.md (+ .csv, + .png).

    python -m harness.horizons                       # 1e3 … 1e6 steps (several minutes)
    python -m harness.horizons --steps 100,1000 --out-dir /tmp/h   # a quick look

The rows go to a CSV file as the steps become final (`--out`), so the smoother's
memory should stay flat. The batch asked of the four-bar's square steps (tangent
integrators, `--batch --dc-integrators tangent`) has the solution of one step at a
time, and the run plan takes it so (its summary says `batch asked, taken one step at
a time`): it streams its rows as the smoother does, and its memory stays flat too.
"""
from __future__ import annotations

import argparse
import math
import pathlib
import re
import subprocess
import sys
import tempfile
import time

from harness.pages import REPORTS, ROOT, machine, progress, write_csv

SCENE = "scenes/fourbar.yaml"
DT = 1e-3
STEPS = [1_000, 10_000, 100_000, 1_000_000]
# name → the options of `mbfg simulate` that choose the solve.
CONFIGS = {
    "smoother N_w=1": ["--window", "1"],
    "smoother N_w=10": ["--window", "10"],
    "batch": ["--batch", "--dc-integrators", "tangent"],
}
# A smoother's peak memory may vary by this much over the horizons and still be
# called constant (allocator and page granularity).
FLAT_MIB = 2.0


def t_end(steps: int, dt: float = DT) -> str:
    """The end time of a run of `steps` steps (step 0 included) at dt."""
    return repr(round((steps - 1) * dt, 9))


TIME = pathlib.Path("/usr/bin/time")


def run_once(binary: pathlib.Path, steps: int, options: list[str], workdir: pathlib.Path) -> dict:
    """One `mbfg simulate` process: its exit code, wall time (s), peak RSS (MiB, the
    kernel's rusage of the process), the solve time and peak memory its summary line
    reports, and the rows it wrote.

    The peak is measured through GNU time (`/usr/bin/time -f %M`): a child forked
    from this Python process would start its `ru_maxrss` at Python's own resident
    size (tens of MiB), which the small mbfg runs do not reach. Without GNU time,
    `os.wait4`'s rusage is used and says so."""
    out = workdir / f"run-{steps}.csv"
    cmd = [str(binary), "simulate", SCENE, "--dt", repr(DT), "--t-end", t_end(steps),
           *options, "--out", str(out)]
    measured = workdir / "time.txt"
    via = "GNU time"
    if TIME.exists():
        cmd = [str(TIME), "-f", "%M %U %S", "-o", str(measured), *cmd]
    else:
        via = "os.wait4"
    began = time.perf_counter()
    proc = subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    stdout, stderr = proc.communicate()
    wall = time.perf_counter() - began
    kib, cpu = math.nan, math.nan
    if via == "GNU time":
        text = measured.read_text().strip().splitlines()
        fields = text[-1].split() if text else []
        if len(fields) == 3:
            kib, cpu = float(fields[0]), float(fields[1]) + float(fields[2])
    else:
        kib = resource_peak_kib()
    summary = stdout.decode(errors="replace").strip()
    solve = re.search(r" in ([0-9.]+) s;", summary)
    reported = re.search(r"; peak memory ([0-9.]+) MiB", summary)
    iterations = re.search(r"iterations per solve: mean ([0-9.]+)", summary)
    rows = 0
    if out.exists():
        with open(out, "rb") as f:
            rows = sum(1 for _ in f) - 1
        out.unlink()
    return {
        "steps": steps,
        "exit": proc.returncode,
        "wall_s": wall,
        # User + system CPU time: on a shared machine, steadier than the wall time.
        "cpu_s": cpu,
        # %M and ru_maxrss are in KiB on Linux.
        "peak_rss_mib": kib / 1024.0,
        "solve_s": float(solve.group(1)) if solve else math.nan,
        "reported_mib": float(reported.group(1)) if reported else math.nan,
        # Per window solve (the smoother: per step); the batch's: its solve of all steps.
        "mean_iterations": float(iterations.group(1)) if iterations else math.nan,
        "rows": rows,
        "measured_by": via,
        "summary": summary,
        "error": stderr.decode(errors="replace").strip().splitlines()[-1:] if proc.returncode else [],
    }


def resource_peak_kib() -> float:
    """The largest peak RSS of any waited-for child (KiB): the fallback without GNU
    time, an upper bound (it includes Python's own size at the fork)."""
    import resource
    return float(resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss)


def slope(xs: list[float], ys: list[float]) -> float:
    """Least-squares slope of log y against log x (NaN with fewer than two points)."""
    pts = [(math.log(x), math.log(y)) for x, y in zip(xs, ys) if x > 0 and y > 0]
    if len(pts) < 2:
        return math.nan
    mx = sum(p[0] for p in pts) / len(pts)
    my = sum(p[1] for p in pts) / len(pts)
    sxx = sum((p[0] - mx) ** 2 for p in pts)
    return sum((p[0] - mx) * (p[1] - my) for p in pts) / sxx


def run(binary: pathlib.Path, steps: list[int], configs: dict[str, list[str]]) -> list[dict]:
    rows = []
    with tempfile.TemporaryDirectory(prefix="mbfg-horizons-") as tmp:
        for name, options in configs.items():
            for n in steps:
                progress(f"horizons: {name}, {n} steps")
                r = run_once(binary, n, options, pathlib.Path(tmp))
                r["config"] = name
                rows.append(r)
                progress(f"  {r['wall_s']:.2f} s, peak {r['peak_rss_mib']:.1f} MiB"
                         + (f", exit {r['exit']}: {r['error']}" if r["exit"] else ""))
    return rows


def fits(rows: list[dict]) -> dict[str, dict]:
    """Per configuration: the log-log slopes of wall time and peak memory over the
    steps (all points, and the last two), and the memory's spread."""
    out = {}
    for name in dict.fromkeys(r["config"] for r in rows):
        ok = [r for r in rows if r["config"] == name and r["exit"] == 0]
        xs = [r["steps"] for r in ok]
        wall = [r["wall_s"] for r in ok]
        cpu = [r["cpu_s"] for r in ok]
        mem = [r["peak_rss_mib"] for r in ok]
        out[name] = {
            "time_slope": slope(xs, wall),
            "time_slope_last": slope(xs[-2:], wall[-2:]),
            "cpu_slope": slope(xs, cpu),
            "cpu_slope_last": slope(xs[-2:], cpu[-2:]),
            "memory_slope": slope(xs, mem),
            "memory_slope_last": slope(xs[-2:], mem[-2:]),
            "memory_spread_mib": (max(mem) - min(mem)) if mem else math.nan,
            "points": len(ok),
        }
    return out


def plot(rows: list[dict], path: pathlib.Path) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, (a, b) = plt.subplots(1, 2, figsize=(10, 4))
    for name in dict.fromkeys(r["config"] for r in rows):
        ok = [r for r in rows if r["config"] == name and r["exit"] == 0]
        xs = [r["steps"] for r in ok]
        a.loglog(xs, [r["cpu_s"] for r in ok], "o-", label=f"{name} (CPU)")
        a.loglog(xs, [r["wall_s"] for r in ok], ":", color=a.lines[-1].get_color(), alpha=0.6,
                 label=f"{name} (wall)")
        b.loglog(xs, [r["peak_rss_mib"] for r in ok], "o-", label=name)
    a.set(xlabel="steps", ylabel="time (s)", title="CPU time (wall dotted)")
    b.set(xlabel="steps", ylabel="peak resident memory (MiB)", title="memory")
    for ax in (a, b):
        ax.grid(True, which="both", alpha=0.3)
        ax.legend()
    fig.suptitle(f"mbfg simulate {SCENE}, dt = {DT:g} s")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def page(rows: list[dict], fitted: dict[str, dict], seconds: float) -> str:
    def num(v, spec):
        return "–" if v is None or (isinstance(v, float) and math.isnan(v)) else format(v, spec)

    lines = [
        "# Long horizons: time and memory against the number of steps",
        "",
        f"`mbfg simulate {SCENE} --dt {DT:g} --t-end T … --out run.csv`, one process per run, "
        "for the fixed-lag smoother (N_w = 1, 10) and the batch "
        "(`--batch --dc-integrators tangent`, whose square steps the run plan takes one at a time). Wall time is the process's; peak memory is its "
        "peak resident set size as the kernel measured it (`ru_maxrss`, through GNU "
        "`time -f %M`); the summary line's own figure (`peak memory`, the process's `VmHWM`) "
        "is beside it. "
        f"Made by `python -m harness.horizons` in {seconds:.0f} s. Machine: {machine()}.",
        "",
        "| solve | steps | wall time (s) | CPU time (s) | CPU µs a step | solve (s) | iterations per solve | CPU µs per step and iteration | peak memory (MiB) | reported (MiB) | rows written | exit |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        lines.append(
            f"| {r['config']} | {r['steps']:,} | {num(r['wall_s'], '.2f')} | {num(r['cpu_s'], '.2f')} "
            f"| {num(1e6 * r['cpu_s'] / r['steps'], '.1f')} "
            f"| {num(r['solve_s'], '.2f')} | {num(r['mean_iterations'], '.2f')} "
            f"| {num(per_iteration(r), '.2f')} "
            f"| {num(r['peak_rss_mib'], '.1f')} | {num(r['reported_mib'], '.1f')} | {r['rows']:,} | {r['exit']} |")
    lines += [
        "",
        "Log-log slopes (least squares over every horizon that ran; and between the last two):",
        "",
        "| solve | wall time slope | last two | CPU time slope | last two | memory slope | last two | memory spread (MiB) |",
        "|---|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for name, f in fitted.items():
        lines.append(
            f"| {name} | {num(f['time_slope'], '.3f')} | {num(f['time_slope_last'], '.3f')} "
            f"| {num(f['cpu_slope'], '.3f')} | {num(f['cpu_slope_last'], '.3f')} "
            f"| {num(f['memory_slope'], '.3f')} | {num(f['memory_slope_last'], '.3f')} "
            f"| {num(f['memory_spread_mib'], '.2f')} |")
    lines += ["", "![time and memory against steps](horizons.png)", "", "## Verdicts", ""]
    lines += verdicts(rows, fitted)
    lines.append("")
    return "\n".join(lines)


def per_iteration(r: dict) -> float:
    """CPU µs per step and iteration of a run whose iterations are per step (the
    smoother's, and a batch taken one step at a time: its work per step grows with
    the iterations the motion asks, not with the horizon); NaN otherwise."""
    its = r.get("mean_iterations", math.nan)
    if not its > 0:
        return math.nan
    return 1e6 * r["cpu_s"] / (r["steps"] * its)


def verdicts(rows: list[dict], fitted: dict[str, dict]) -> list[str]:
    out = []
    failed = [r for r in rows if r["exit"] != 0]
    for r in failed:
        out.append(f"- **{r['config']} at {r['steps']:,} steps did not run** (exit {r['exit']}): "
                   f"{' '.join(r['error'])}")
    for name, f in fitted.items():
        if f["points"] < 2:
            continue
        t, c = f["time_slope"], f.get("cpu_slope", math.nan)
        judged = c if not math.isnan(c) else t
        word = "linear" if judged <= 1.05 else "**super-linear**"
        ok = [r for r in rows if r["config"] == name and r["exit"] == 0]
        trend = ""
        per = [per_iteration(r) for r in ok]
        if per and not any(math.isnan(p) for p in per):
            trend = ("; CPU µs per step and iteration "
                     + " → ".join(f"{p:.1f}" for p in per)
                     + ", iterations per step "
                     + " → ".join(f"{r['mean_iterations']:.2f}" for r in ok))
        elif ok and all("mean_iterations" in r for r in ok):
            trend = ("; iterations of the solve of all steps "
                     + " → ".join(f"{r['mean_iterations']:.0f}" for r in ok))
        out.append(f"- {name}: time {word} (CPU time slope {c:.3f}, between the last two "
                   f"{f.get('cpu_slope_last', math.nan):.3f}; wall time {t:.3f}; "
                   f"target ≤ 1.05{trend}).")
        # Streamed runs: the smoother's, and the batch the plan takes one step at a time.
        if name.startswith("smoother") or name == "batch":
            flat = f["memory_spread_mib"] <= FLAT_MIB
            out.append(f"- {name}: memory {'constant' if flat else '**growing**'} "
                       f"(spread {f['memory_spread_mib']:.2f} MiB over the horizons, "
                       f"tolerance {FLAT_MIB} MiB).")
        else:
            big = [r for r in rows if r["config"] == name and r["exit"] == 0]
            per_step = ""
            if len(big) >= 2:
                a, b = big[-2], big[-1]
                kib = (b["peak_rss_mib"] - a["peak_rss_mib"]) * 1024 / (b["steps"] - a["steps"])
                per_step = f", {kib:.2f} KiB a step between the last two"
            out.append(f"- {name}: memory slope {f['memory_slope']:.3f} "
                       f"(last two {f['memory_slope_last']:.3f}{per_step}).")
    return out


def read_rows(path: pathlib.Path) -> list[dict]:
    """The rows of a horizons.csv, with their numbers as numbers."""
    import csv
    rows = []
    for r in csv.DictReader(open(path)):
        row = {}
        for k, v in r.items():
            if k in ("config", "measured_by"):
                row[k] = v
            elif k in ("steps", "exit", "rows"):
                row[k] = int(v)
            else:
                row[k] = float(v) if v else math.nan
        rows.append(row)
    return rows


def write(rows: list[dict], out_dir: pathlib.Path, seconds: float) -> dict[str, dict]:
    out_dir.mkdir(parents=True, exist_ok=True)
    for r in rows:
        r["seconds"] = seconds
    fitted = fits(rows)
    (out_dir / "horizons.md").write_text(page(rows, fitted, seconds))
    write_csv(out_dir / "horizons.csv",
              [{k: v for k, v in r.items() if k not in ("summary", "error")} for r in rows])
    plot(rows, out_dir / "horizons.png")
    progress(f"wrote {out_dir / 'horizons.md'}, horizons.csv, horizons.png")
    return fitted


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m harness.horizons",
                                 description=__doc__.split("\n\n")[0])
    ap.add_argument("--steps", default=",".join(str(s) for s in STEPS),
                    help="comma-separated step counts (default %(default)s)")
    ap.add_argument("--configs", default=",".join(CONFIGS),
                    help="comma-separated solves, of: " + ", ".join(CONFIGS))
    ap.add_argument("--mbfg", type=pathlib.Path, default=ROOT / "target" / "release" / "mbfg",
                    help="the mbfg binary (default %(default)s; `cargo build --release`)")
    ap.add_argument("--out-dir", type=pathlib.Path, default=REPORTS,
                    help="where the page goes (default %(default)s)")
    ap.add_argument("--from-csv", type=pathlib.Path,
                    help="write the page again from a horizons.csv of an earlier run")
    args = ap.parse_args(argv)
    if args.from_csv:
        rows = read_rows(args.from_csv)
        write(rows, args.out_dir, float(rows[0].get("seconds", math.nan)) if rows else 0.0)
        return 0
    steps = [int(float(s)) for s in args.steps.split(",") if s.strip()]
    names = [c.strip() for c in args.configs.split(",") if c.strip()]
    unknown = [c for c in names if c not in CONFIGS]
    if unknown or any(s < 2 for s in steps):
        ap.error(f"unknown solve(s) {unknown}" if unknown else "every step count must be ≥ 2")
    if not args.mbfg.exists():
        ap.error(f"{args.mbfg} does not exist: build it (cargo build --release) or pass --mbfg")
    began = time.perf_counter()
    rows = run(args.mbfg.resolve(), steps, {c: CONFIGS[c] for c in names})
    write(rows, args.out_dir, time.perf_counter() - began)
    return 0


if __name__ == "__main__":
    sys.exit(main())
