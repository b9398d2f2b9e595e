"""mbfg checked on a scene by the simulators that share none of its equations.

exudyn and Pinocchio read the scene themselves (harness/scene_file.py: numbers and load
expressions, checked against `mbfg.load`), build their own formulations and integrate
them. A check runs mbfg at the step dt and at dt/2: the difference, × 4/3 for its
second-order rules, estimates mbfg's own error at dt. mbfg passes when every peer that
models the scene agrees with it to within twice that estimate plus the peer's own
floor (FLOOR × the mechanism's size): agreement to the accuracy of the step.

    python -m harness.crosscheck examples/everyday/*.yaml --t-end 0.5 --dt 1e-3

prints a line per scene and peer, and exits 1 when mbfg disagrees with a peer on a
scene (the line names the scene), 2 when no peer can model one.
"""
from __future__ import annotations

import argparse
import dataclasses
import math
import pathlib
import sys
import warnings

import numpy as np

import mbfg
from harness import generators
from harness import reference as refs
from harness import trajectory as tj

PEERS = ("exudyn", "pinocchio")
# A peer's own error at its fast settings, relative to the mechanism's size: exudyn at
# h = 1e-4 is within 2e-6 of IDA on the everyday mechanisms (reports/coverage.md).
FLOOR = {"exudyn": 1e-5, "pinocchio": 1e-8}


class Disagreement(AssertionError):
    """mbfg and an independent peer disagree beyond the accuracy of the step."""


@dataclasses.dataclass
class Check:
    scene: str
    tool: str
    status: str                   # "agrees", "disagrees", "refused", "failed"
    reason: str = ""
    rmse_m: float | None = None   # peer against mbfg at dt, moving points
    max_m: float | None = None
    allowed_m: float | None = None
    step_error_m: float | None = None
    wall_time_s: float | None = None

    def line(self) -> str:
        if self.status in ("agrees", "disagrees"):
            return (f"{self.scene}: {self.tool} {self.status} with mbfg: RMSE {self.rmse_m:.2e} m "
                    f"(max {self.max_m:.2e}), allowed {self.allowed_m:.2e} m (mbfg's step error "
                    f"{self.step_error_m:.2e} m)")
        return f"{self.scene}: {self.tool} {self.status}: {self.reason}"


def size_of(model) -> float:
    q0 = np.asarray(model.initial_q)
    cols = refs.point_columns(model)
    return max(1e-3, float(np.max(np.abs(q0[cols]))) if len(cols) else 1.0)


def mbfg_run(scene, t_end: float, dt: float) -> tuple[tj.Trajectory, tj.Trajectory, list[str]]:
    """mbfg at dt and dt/2 (its samples at the multiples of dt), and its warnings."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", mbfg.PlausibilityWarning)
        coarse, prov = generators.run_mbfg(scene, t_end, dt)
        fine, _ = generators.run_mbfg(scene, t_end, dt / 2)
    k = np.arange(len(coarse.t)) * 2
    fine = tj.Trajectory(fine.names, fine.t[k], fine.q[k], fine.dq[k], fine.ddq[k])
    return coarse, fine, list(prov.get("warnings", []))


def check(scene, t_end: float = 0.5, dt: float = 1e-3, tools=PEERS, mbfg_scene=None,
          settings: dict | None = None) -> list[Check]:
    """Every peer on `scene` against mbfg on `mbfg_scene` (default: the same file)."""
    label = tj.display_path(mbfg_scene or scene)
    model = mbfg.load(str(scene))
    coarse, fine, _ = mbfg_run(mbfg_scene or scene, t_end, dt)
    step = 4.0 / 3.0 * refs.point_errors(model, coarse.t, coarse.q, fine)[0]
    out = []
    for name in tools:
        o = generators.attempt(generators.get(name), scene, t_end, dt,
                               (settings or {}).get(name), model=model)
        if o.status != "ok":
            out.append(Check(label, name, o.status, o.reason))
            continue
        rmse, worst = refs.point_errors(model, o.trajectory.t, o.trajectory.q, coarse)
        allowed = 2.0 * step + FLOOR.get(name, 1e-6) * size_of(model)
        out.append(Check(label, name, "agrees" if rmse <= allowed else "disagrees", "",
                         rmse, worst, allowed, step, o.wall_time_s))
    return out


def require_agreement(scene, **kw) -> list[Check]:
    """`check`, raising Disagreement naming the scene when mbfg disagrees with a peer or
    no peer models the scene."""
    checks = check(scene, **kw)
    bad = [c for c in checks if c.status == "disagrees"]
    if bad:
        raise Disagreement("; ".join(c.line() for c in bad))
    if not any(c.status == "agrees" for c in checks):
        raise Disagreement(f"{checks[0].scene}: no independent peer models it: "
                           + "; ".join(c.line() for c in checks))
    return checks


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m harness.crosscheck",
                                 description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter,
                                 epilog="\n\n".join(__doc__.split("\n\n")[1:]))
    ap.add_argument("scenes", nargs="+", type=pathlib.Path)
    ap.add_argument("--t-end", type=float, default=0.5)
    ap.add_argument("--dt", type=float, default=1e-3)
    ap.add_argument("--tools", default=",".join(PEERS))
    a = ap.parse_args(argv)
    steps = round(a.t_end / a.dt) if a.dt > 0 else 0
    if steps < 1 or abs(steps * a.dt - a.t_end) > 1e-9 * a.t_end:
        ap.error("--t-end must be a positive multiple of --dt")
    status = 0
    for scene in a.scenes:
        try:
            checks = check(scene, a.t_end, a.dt, tuple(a.tools.split(",")))
        except (mbfg.SceneError, OSError) as e:
            print(f"{scene}: {generators.one_line(e)}")
            status = max(status, 2)
            continue
        for c in checks:
            print(c.line(), flush=True)
        if any(c.status == "disagrees" for c in checks):
            status = max(status, 1)
        elif not any(c.status == "agrees" for c in checks):
            status = max(status, 2)
    return status


if __name__ == "__main__":
    sys.exit(main())
