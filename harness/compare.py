"""Compare simulators on your own scene: one table and one plot.

Runs every chosen tool (registered in harness/generators.py) on the scene at its fast
defaults and measures each against a reference run (IDA by default: the most accurate
tool that runs the scene): RMSE and max error of the moving points' x, y, the largest
|Φ| of the constraints at the samples, the wall time of the whole call. A tool that
cannot model the scene, or fails on it, gets a row with the reason.

    python -m harness.compare my-scene.yaml
    python -m harness.compare my-scene.yaml --tools mbfg,ida,exudyn,pinocchio \\
        --t-end 2 --dt 1e-3 --out my-compare --coordinates theta
    python -m harness.compare my-scene.yaml --set exudyn.h=1e-5 --set mbfg.window=5

writes DIR/compare.md, DIR/compare.csv, DIR/compare.png and every trajectory with its
provenance (DIR/trajectories/TOOL.csv.gz, TOOL.json).
"""
from __future__ import annotations

import argparse
import csv
import pathlib
import sys
import time
import warnings

import numpy as np

import mbfg
from harness import generators
from harness import reference as refs
from harness import trajectory as tj

DEFAULT_TOOLS = "mbfg,ida,exudyn,pinocchio"


def progress(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


def choose_reference(outcomes: dict[str, generators.Outcome], wanted: str) -> tuple[str | None, str]:
    """The tool whose run is the truth: `wanted` if it ran, else the most accurate that
    did (mbfg itself is never the truth). Returns (name, a note for the table)."""
    if outcomes[wanted].status == "ok":
        return wanted, ""
    ran = [n for n, o in outcomes.items() if o.status == "ok" and generators.get(n).accuracy > 0]
    if not ran:
        return None, (f"no reference: {wanted} {outcomes[wanted].status} "
                      f"({outcomes[wanted].reason}) and no other reference tool ran")
    best = max(ran, key=lambda n: generators.get(n).accuracy)
    return best, (f"reference: {best}, as {wanted} {outcomes[wanted].status} "
                  f"({outcomes[wanted].reason})")


def max_phi(model: mbfg.Model, q: np.ndarray) -> float:
    return max(float(np.max(np.abs(model.phi(qk)))) for qk in q) if model.m else 0.0


def rows_of(model, outcomes, ref_name, overrides) -> list[dict]:
    truth = outcomes[ref_name].trajectory if ref_name else None
    rows = []
    for name, o in outcomes.items():
        gen = generators.get(name)
        row = {"tool": name, "label": gen.label, "status": o.status, "rmse_m": None,
               "max_m": None, "max_abs_phi": None, "wall_time_s": o.wall_time_s,
               "samples": None, "settings": "", "note": o.reason, "step": "", "warnings": ""}
        if o.status == "ok":
            traj = o.trajectory
            row["step"] = integrated_step(name, o.provenance)
            row["warnings"] = " / ".join(o.provenance.get("warnings", []))
            row["samples"] = len(traj.t)
            row["max_abs_phi"] = max_phi(model, traj.q)
            # What was asked for; the full settings are in trajectories/TOOL.json.
            row["settings"] = ", ".join(f"{k} {v}" for k, v in
                                        {**gen.defaults, **overrides.get(name, {})}.items())
            # What the tool decided on its own (exudyn's Newton tolerances with loads of
            # the state, a merged point mass, a floating body's joints).
            row["note"] = "; ".join(o.provenance.get("modelling_notes") or [])
            if name == ref_name:
                row["note"] = "the reference" + (f"; {row['note']}" if row["note"] else "")
            elif truth is not None:
                row["rmse_m"], row["max_m"] = refs.point_errors(model, traj.t, traj.q, truth)
        rows.append(row)
    return rows


def integrated_step(name: str, prov: dict) -> str:
    """The step the tool actually integrated at: for mbfg its dt, or the finer step a
    refinement took from where it began; a fixed-step peer's h; IDA's is adaptive."""
    settings = prov.get("settings", {})
    if name.startswith("mbfg"):
        dt = settings.get("dt")
        ref = (prov.get("summary") or {}).get("refinement")
        if ref:
            step, t = ref.get("after") or (None, None)
            return (f"{ref['dt']:.3g} (refined ×{ref['factor']} from t = {t:.4g} s; asked "
                    f"{dt:g})" if t is not None else f"{ref['dt']:.3g} (refined ×{ref['factor']})")
        return f"{dt:g}"
    if "h" in settings:
        return f"{settings['h']:g}"
    return "adaptive"


def fmt(v, spec: str) -> str:
    return "—" if v is None else format(v, spec)


def markdown(scene_label: str, model, rows, t_end, dt, ref_name, ref_note) -> str:
    lines = [f"# {scene_label}: {len(rows)} tools over {t_end:g} s, samples every {dt:g} s\n",
             f"Errors: RMSE and max over the x, y of the moving points against "
             f"**{ref_name or 'no reference'}**, at every sample. max |Φ|: the constraints at the "
             "samples. Wall time: the whole call (model building and output mapping "
             "included), one run.\n"]
    if ref_note:
        lines.append(ref_note + "\n")
    lines += ["| tool | status | step integrated (s) | RMSE (m) | max error (m) | max \\|Φ\\| | "
              "wall time (s) | settings or reason | warnings |",
              "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        why = r["note"] if r["status"] != "ok" else (
            r["settings"] + (f" ({r['note']})" if r["note"] else ""))
        lines.append(f"| {r['tool']} | {r['status']} | {r['step'] or '—'} | "
                     f"{fmt(r['rmse_m'], '.3e')} | "
                     f"{fmt(r['max_m'], '.3e')} | {fmt(r['max_abs_phi'], '.1e')} | "
                     f"{fmt(r['wall_time_s'], '.3f')} | {why.replace('|', '/')} | "
                     f"{(r['warnings'] or '—').replace('|', '/')} |")
    return "\n".join(lines) + "\n"


def write_csv(path: pathlib.Path, rows: list[dict]) -> None:
    with open(path, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)


def default_coordinates(model: mbfg.Model) -> list[str]:
    """The independent coordinates, else every q of a small model, else the first
    moving point's x and y."""
    if model.independent:
        return list(model.independent)
    if model.n <= 6:
        return list(model.names)
    return [model.names[i] for i in refs.point_columns(model)[:2]]


def plot_series(model, name: str, *trajs) -> tuple[str, list[np.ndarray]]:
    """What the plot shows of coordinate `name` in each trajectory, and its label: the
    coordinate, or for an angle that turns a full turn or more (a straight line of
    growing radians) its rate, which the eye can compare."""
    k = model.names.index(name)
    angles = {c["name"] for c in model.coordinates if c["type"] in ("angle", "relative_angle")}
    if name in angles and any(np.ptp(t.q[:, k]) >= 2 * np.pi for t in trajs):
        return f"rate({name}) (it turns)", [t.dq[:, k] for t in trajs]
    return name, [t.q[:, k] for t in trajs]


def plot(path: pathlib.Path, title: str, model, outcomes, ref_name, coords: list[str]) -> None:
    # matplotlib 3.10's mathtext (log-axis tick labels) calls pyparsing names that
    # pyparsing 3.3 deprecates: not the user's concern.
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        _plot(path, title, model, outcomes, ref_name, coords)


def _plot(path, title, model, outcomes, ref_name, coords) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    ran = [n for n, o in outcomes.items() if o.status == "ok"]
    color = {tool: f"C{i}" for i, tool in enumerate(ran)}    # a tool's colour in both columns
    fig, axes = plt.subplots(len(coords), 2, figsize=(12, 2.6 * len(coords) + 1.0),
                             sharex=True, squeeze=False)
    truth = outcomes[ref_name].trajectory if ref_name else None
    for row, name in enumerate(coords):
        k = model.names.index(name)
        left, right = axes[row]
        label, series = plot_series(model, name, *(outcomes[tool].trajectory for tool in ran))
        for tool, shown in zip(ran, series):
            traj = outcomes[tool].trajectory
            is_ref = tool == ref_name
            left.plot(traj.t, shown, "--" if is_ref else "-", color="k" if is_ref else color[tool],
                      lw=1.0 if is_ref else 1.4, label=f"{tool} (reference)" if is_ref else tool,
                      zorder=3 if is_ref else 2)
            if truth is not None and not is_ref and len(traj.t) == len(truth.t):
                err = np.maximum(np.abs(traj.q[:, k] - truth.q[:, k]), 1e-17)
                right.semilogy(traj.t, err, lw=1.0, color=color[tool], label=tool)
        left.set_ylabel(label)
        right.set_ylabel(f"|{name} − reference|")
        for ax in (left, right):
            ax.grid(True, which="both", alpha=0.3)
    axes[0][0].legend(fontsize=8)
    if truth is not None and axes[0][1].lines:
        axes[0][1].legend(fontsize=8)
    if truth is None:
        axes[0][1].set_title("no reference: errors not shown", fontsize=9)
    for ax in axes[-1]:
        ax.set_xlabel("t (s)")
    fig.suptitle(f"{title}: coordinates over time (left) and their error against "
                 f"{ref_name or 'no reference'} (right)")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def parse_overrides(items: list[str], ap) -> dict[str, dict]:
    """TOOL.KEY=VALUE → {TOOL: {KEY: VALUE}}."""
    out: dict[str, dict] = {}
    for item in items:
        tool, dot, rest = item.partition(".")
        if not dot or tool not in generators.REGISTRY:
            ap.error(f"--set {item!r}: expected TOOL.KEY=VALUE with TOOL one of "
                     f"{', '.join(generators.REGISTRY)}")
        try:
            out.setdefault(tool, {}).update(generators.parse_settings([rest]))
        except ValueError as e:
            ap.error(f"--set {item!r}: {e}")
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m harness.compare",
                                 description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter,
                                 epilog="\n\n".join(__doc__.split("\n\n")[1:]))
    ap.add_argument("scene", type=pathlib.Path, help="a scene file (any path)")
    ap.add_argument("--tools", default=DEFAULT_TOOLS,
                    help=f"comma-separated, of {', '.join(generators.REGISTRY)} "
                    "(default: %(default)s)")
    ap.add_argument("--reference", default="ida",
                    help="the tool the others are measured against (default: %(default)s; "
                    "run even when not in --tools)")
    ap.add_argument("--t-end", type=float, default=2.0, help="horizon in s (default: %(default)s)")
    ap.add_argument("--dt", type=float, default=1e-3,
                    help="sample step in s, mbfg's step (default: %(default)s)")
    ap.add_argument("--out", type=pathlib.Path,
                    help="output folder (default: compare-SCENE in the current folder)")
    ap.add_argument("--coordinates", metavar="NAMES",
                    help="coordinates to plot, comma-separated, or 'all' (default: the "
                    "independent ones, else all q of a small model, else the first point's x, y)")
    ap.add_argument("--set", action="append", default=[], metavar="TOOL.KEY=VALUE",
                    help="a tool's setting over its defaults, e.g. exudyn.h=1e-5, ida.rtol=1e-10")
    args = ap.parse_args(argv)

    tools = [t.strip() for t in args.tools.split(",") if t.strip()]
    unknown = [t for t in tools + [args.reference] if t not in generators.REGISTRY]
    if unknown or not tools:
        ap.error(f"unknown tool(s) {', '.join(unknown)}; registered: {', '.join(generators.REGISTRY)}")
    if generators.get(args.reference).accuracy <= 0:
        ap.error(f"--reference {args.reference}: pick a reference generator "
                 f"({', '.join(n for n, g in generators.REGISTRY.items() if g.accuracy > 0)})")
    steps = round(args.t_end / args.dt) if args.dt > 0 else 0
    if args.dt <= 0 or steps < 1 or abs(steps * args.dt - args.t_end) > 1e-9 * args.t_end:
        ap.error("--t-end must be a positive multiple of --dt")
    overrides = parse_overrides(args.set, ap)
    if not args.scene.is_file():
        print(f"compare: {args.scene}: no such scene file", file=sys.stderr)
        return 2
    try:
        model = mbfg.load(str(args.scene))
    except mbfg.SceneError as e:
        print(f"compare: {generators.one_line(e)}", file=sys.stderr)
        return 2
    coords = (list(model.names) if args.coordinates == "all" else
              [c.strip() for c in args.coordinates.split(",") if c.strip()]
              if args.coordinates else default_coordinates(model))
    missing = [c for c in coords if c not in model.names]
    if missing or not coords:
        ap.error(f"--coordinates: unknown {', '.join(missing)}; the scene has {', '.join(model.names)}")
    out = args.out or pathlib.Path(f"compare-{args.scene.name.removesuffix('.yaml')}")

    order = tools + ([args.reference] if args.reference not in tools else [])
    outcomes: dict[str, generators.Outcome] = {}
    start = time.perf_counter()
    with warnings.catch_warnings():
        # mbfg's plausibility warnings are in its provenance (warnings); not on the console.
        warnings.simplefilter("ignore", mbfg.PlausibilityWarning)
        for name in order:
            progress(f"{name} …")
            o = generators.attempt(generators.get(name), args.scene, args.t_end, args.dt,
                                   overrides.get(name), model=model)
            outcomes[name] = o
            progress(f"{name}: " + (f"{o.wall_time_s:.2f} s" if o.status == "ok"
                                     else f"{o.status}: {o.reason}"))
    ref_name, ref_note = choose_reference(outcomes, args.reference)
    rows = rows_of(model, outcomes, ref_name, overrides)
    label = tj.display_path(args.scene)

    out.mkdir(parents=True, exist_ok=True)
    (out / "compare.md").write_text(markdown(label, model, rows, args.t_end, args.dt,
                                             ref_name, ref_note))
    write_csv(out / "compare.csv", rows)
    if any(o.status == "ok" for o in outcomes.values()):
        plot(out / "compare.png", label, model, outcomes, ref_name, coords)
    for name, o in outcomes.items():
        if o.status == "ok":
            tj.write(out / "trajectories" / f"{name}.csv.gz", o.trajectory)
            tj.write_provenance(out / "trajectories" / f"{name}.json", o.provenance)
    record = {"scene": label, "scene_hash": tj.scene_hash(args.scene),
              "files": {tj.display_path(f): tj.file_hash(f) for f in tj.scene_files(args.scene)},
              "git": tj.git_state(), "t_end": args.t_end, "dt": args.dt,
              "reference": ref_name, "tools": rows,
              "wall_time_s": time.perf_counter() - start}
    tj.write_provenance(out / "compare.json", record)
    # Every progress line before the table, and the table in one piece.
    progress(f"wrote {out}/compare.md, compare.csv, compare.png, compare.json, trajectories/ "
             f"in {time.perf_counter() - start:.1f} s")
    sys.stderr.flush()
    sys.stdout.write((out / "compare.md").read_text() + "\n")
    sys.stdout.flush()
    return 0 if any(o.status == "ok" for o in outcomes.values()) else 1


if __name__ == "__main__":
    sys.exit(main())
