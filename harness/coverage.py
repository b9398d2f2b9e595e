"""reports/coverage.md: every scene of the repository, and the simulators independent of
mbfg's equations that check it.

For each scene file under scenes/ and examples/: whether exudyn and Pinocchio take it
(or their reason, in one line), and their agreement with mbfg over a short horizon,
judged as `harness.crosscheck` does (within twice mbfg's own step error plus the peer's
floor). A scene no peer can model gets the reasons why.

    python -m harness.coverage                # writes reports/coverage.md, coverage.csv
    python -m harness.coverage --t-end 0.1 --out /tmp/cov
"""
from __future__ import annotations

import argparse
import pathlib
import sys
import time

import mbfg
from harness import crosscheck as cc
from harness.pages import REPORTS, ROOT, machine, progress, write_csv

# Low-cost settings: a fifth of a second at 1 ms (mbfg also at 0.5 ms), the peers at their
# fast defaults. Minutes for the whole repository.
T_END, DT = 0.2, 1e-3
# The scaling scenes (hundreds of coordinates, a hundred loops for Pinocchio's
# constraint solver): a tenth of the horizon.
LARGE_N, LARGE_T_END = 100, 0.02


def scenes() -> list[pathlib.Path]:
    """Every scene file of the repository (an MBSE mechanism file is one too)."""
    out = []
    for top in ("scenes", "examples"):
        for p in sorted((ROOT / top).rglob("*.yaml")):
            if "trajectories" not in p.relative_to(ROOT).parts:
                out.append(p)
    return out


def run(paths, t_end: float = T_END, dt: float = DT) -> list[dict]:
    rows = []
    for p in paths:
        rel = str(p.relative_to(ROOT))
        began = time.perf_counter()
        try:
            horizon = t_end if mbfg.load(str(p)).n <= LARGE_N else min(t_end, LARGE_T_END)
            checks = cc.check(p, horizon, dt)
        except Exception as e:  # mbfg itself cannot run it: said so, not hidden
            rows.append({"scene": rel, "verdict": "mbfg failed", "note": cc.generators.one_line(e)})
            progress(f"{rel}: mbfg failed: {e}")
            continue
        row = {"scene": rel, "t_end": horizon}
        for c in checks:
            row[f"{c.tool}_status"] = c.status
            row[f"{c.tool}_rmse_m"] = c.rmse_m
            row[f"{c.tool}_allowed_m"] = c.allowed_m
            row[f"{c.tool}_reason"] = c.reason
            row["mbfg_step_error_m"] = c.step_error_m if c.step_error_m is not None else row.get(
                "mbfg_step_error_m")
        agree = [c.tool for c in checks if c.status == "agrees"]
        bad = [c.tool for c in checks if c.status == "disagrees"]
        row["verdict"] = ("disagrees: " + ", ".join(bad) if bad else
                          "checked by " + ", ".join(agree) if agree else "no independent peer")
        row["seconds"] = time.perf_counter() - began
        rows.append(row)
        progress(f"{rel}: {row['verdict']} ({row['seconds']:.1f} s)")
    return rows


def cell(row: dict, tool: str) -> str:
    status = row.get(f"{tool}_status")
    if status is None:
        return "—"
    if status in ("agrees", "disagrees"):
        mark = "✓" if status == "agrees" else "✗"
        return f"{mark} {row[f'{tool}_rmse_m']:.1e} (≤ {row[f'{tool}_allowed_m']:.1e})"
    return f"{status}: {row[f'{tool}_reason']}".replace("|", "/")


def page(rows: list[dict], t_end: float, dt: float, seconds: float) -> str:
    checked = [r for r in rows if r["verdict"].startswith("checked")]
    unchecked = [r for r in rows if not r["verdict"].startswith("checked")]
    lines = [
        "# Coverage: which independent simulator checks each scene\n",
        f"Every scene file of the repository (scenes/, examples/), run by mbfg and by the two "
        f"simulators that share none of its equations: exudyn (planar rigid bodies, "
        f"generalized-α) and Pinocchio (joint coordinates, RK4). Both read the scene file "
        f"themselves (numbers and load expressions: harness/scene_file.py, "
        f"harness/expressions.py) and refuse a scene mbfg reads differently; from mbfg they "
        f"take only its assembled initial state ([docs/harness.md](../docs/harness.md)).\n",
        f"Horizon {t_end:g} s ({LARGE_T_END:g} s for the scenes of more than {LARGE_N} "
        f"coordinates), samples every {dt:g} s. A cell gives the peer's RMSE against "
        f"mbfg over the moving points' x, y, and what is allowed: twice mbfg's own step error "
        f"(from its run at dt/2, × 4/3) plus the peer's floor (exudyn 1e-5, Pinocchio 1e-8 of "
        f"the mechanism's size). `python -m harness.crosscheck SCENE` runs the same check on one "
        f"scene. Machine: {machine()}; the page took {seconds:.0f} s.\n",
        f"**{len(checked)} of {len(rows)} scenes** are checked by an independent simulator"
        + (f"; {len(unchecked)} are not, each with its reason below." if unchecked else ".")
        + "\n",
        "| scene | horizon (s) | mbfg's step error (m) | exudyn | Pinocchio | verdict |",
        "|---|---|---|---|---|---|"]
    for r in rows:
        step = r.get("mbfg_step_error_m")
        lines.append(f"| {r['scene']} | {r.get('t_end', '—')} | "
                     f"{'—' if step is None else format(step, '.1e')} | "
                     f"{cell(r, 'exudyn')} | {cell(r, 'pinocchio')} | {r['verdict']} |")
    if unchecked:
        lines += ["", "## Scenes no independent simulator checks, and why", ""]
        for r in unchecked:
            why = "; ".join(f"{t}: {r.get(f'{t}_reason') or r.get(f'{t}_status')}"
                            for t in cc.PEERS if r.get(f"{t}_status")) or r.get("note", "")
            lines.append(f"- `{r['scene']}`: {r['verdict']}. {why}")
    return "\n".join(lines) + "\n"


def write(out: pathlib.Path = REPORTS, t_end: float = T_END, dt: float = DT, paths=None) -> list[dict]:
    began = time.perf_counter()
    rows = run(paths or scenes(), t_end, dt)
    out.mkdir(parents=True, exist_ok=True)
    (out / "coverage.md").write_text(page(rows, t_end, dt, time.perf_counter() - began))
    write_csv(out / "coverage.csv", rows)
    progress(f"wrote {out}/coverage.md, {out}/coverage.csv")
    return rows


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m harness.coverage",
                                 description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter,
                                 epilog="\n\n".join(__doc__.split("\n\n")[1:]))
    ap.add_argument("--t-end", type=float, default=T_END)
    ap.add_argument("--dt", type=float, default=DT)
    ap.add_argument("--out", type=pathlib.Path, default=REPORTS)
    ap.add_argument("scenes", nargs="*", type=pathlib.Path, help="default: every scene")
    a = ap.parse_args(argv)
    paths = [p.resolve() for p in a.scenes] or None
    rows = write(a.out, a.t_end, a.dt, paths)
    return 1 if any(r["verdict"].startswith("disagrees") for r in rows) else 0


if __name__ == "__main__":
    sys.exit(main())
