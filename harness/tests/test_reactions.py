"""The force each constraint carries (`--columns constraints`, `Model.constraint_forces`
of the module) against exudyn's joint forces, at exudyn's own states: every scene of the
repository with a slider or a distance tie, to 1e-6 of the largest force."""
from __future__ import annotations

import csv
import pathlib
import subprocess
import warnings

import numpy as np
import pytest

import mbfg
from harness import coverage
from harness import exudyn_ref
from harness.scene_file import SceneFile

ROOT = pathlib.Path(__file__).resolve().parents[2]
PEERS = sorted((pathlib.Path(__file__).resolve().parent / "scenes" / "peers").glob("*.yaml"))
# Every scene with a slider or a distance tie, but the estimation copies of the
# slider-crank (the same mechanism) and, of the peers' scenes, those without a tie.
SCENES = [p for p in coverage.scenes() + PEERS if SceneFile(p).constraints
          and "estimation" not in p.parts
          and (p not in PEERS or any(c["type"] == "distance" for c in SceneFile(p).constraints))]


def forces(model, q, dq, ddq, t) -> dict[str, float]:
    return dict(model._m.constraint_forces(q, dq, ddq, t))


@pytest.mark.parametrize("scene", SCENES, ids=lambda p: p.stem)
def test_constraint_forces_are_exudyns_joint_forces(scene):
    model = mbfg.load(str(scene))
    reactions: dict = {}
    # exudyn's index-2 trapezoidal rule (its accelerations, and the forces that go with
    # them, free of generalized-α's index-3 round-off) at a step fine enough for its
    # position drift to stay below 1e-6 of the forces over 10 ms (the six-bar press's
    # stiff ram spring, over 20 ms: 7e-7 at h = 5e-6, 3e-6 at 1e-5), Newton converged
    # to 1e-11.
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", mbfg.PlausibilityWarning)
        traj, _ = exudyn_ref.generate(scene, 0.01, 1e-3, h=5e-6, solver="trapezoidal_index2",
                                      newton_rtol=1e-11, newton_atol=1e-11,
                                      reactions=reactions)
    ours = [forces(model, q, dq, ddq, t) for q, dq, ddq, t in
            zip(traj.q, traj.dq, traj.ddq, traj.t)]
    largest = max(abs(v) for row in ours for v in row.values())
    for name in ours[0]:
        mine = np.array([row[name] for row in ours])
        if name in model.redundant:          # left out of the dynamics: carries none
            assert name not in reactions and np.all(mine == 0.0)
            continue
        theirs = reactions[name]
        # A guide that carries nothing (a spring along it, no gravity across it).
        scale = largest if largest > 1e-9 else 1.0
        assert np.max(np.abs(mine - theirs)) <= 1e-6 * scale, (name, largest)


def test_the_column_is_the_force_that_holds_the_block_on_its_guide(tmp_path):
    # slider-crank: the block S (0.5 kg) on the horizontal guide A→G, pinned to the rod.
    # Its balance: m_S a_S = m_S g + N n − F:rod@S, with n = (0, 1) the guide's left
    # normal and F:rod@S the force on the rod at S (the joints group).
    scene = ROOT / "scenes" / "slider-crank.yaml"
    out = tmp_path / "run.csv"
    subprocess.run([str(ROOT / "target" / "release" / "mbfg"), "simulate", str(scene),
                    "--dt", "1e-3", "--t-end", "0.5", "--columns", "joints,constraints",
                    "--out", str(out)], check=True, capture_output=True)
    with open(out) as f:
        rows = list(csv.DictReader(f))
    assert list(rows[0])[-1] == "R:guide"
    model = mbfg.load(str(scene))
    largest = max(abs(float(r["R:guide"])) for r in rows)
    for r in rows[::25]:
        a = np.array([float(r["ddq:S.x"]), float(r["ddq:S.y"])])
        pin = np.array([float(r["F:rod@S.x"]), float(r["F:rod@S.y"])])
        normal = 0.5 * (a - np.array([0.0, -9.81])) + pin
        assert abs(normal[0]) <= 1e-6 * largest
        assert float(r["R:guide"]) == pytest.approx(normal[1], abs=1e-6 * largest)
        q, dq, ddq = ([float(r[f"{c}:{n}"]) for n in model.names] for c in ("q", "dq", "ddq"))
        assert float(r["R:guide"]) == pytest.approx(
            forces(model, q, dq, ddq, float(r["t"]))["guide"], rel=1e-12)
