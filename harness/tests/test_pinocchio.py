"""The Pinocchio reference generator (harness/pinocchio_ref.py) against exact answers
and against the mbfg model's own equations."""
import math
import pathlib

import numpy as np
import pytest

import mbfg
from harness import pinocchio_ref as pr
from harness import trajectory as tj

ROOT = pathlib.Path(__file__).resolve().parents[2]
SCENES = ROOT / "scenes"
TEST_SCENES = pathlib.Path(__file__).resolve().parent / "scenes"
DOUBLE = SCENES / "double-pendulum.yaml"
DOUBLE_CSV = SCENES / "trajectories" / "double-pendulum.csv"


def energy(model, traj):
    return np.array([model.kinetic_energy(dq) + model.potential_energy(q)
                     for q, dq in zip(traj.q, traj.dq)])


def test_no_effects_stays_at_rest():
    scene = TEST_SCENES / "pin-rest.yaml"
    traj, prov = pr.generate(scene, 0.5, 0.05, h=1e-4)
    model = mbfg.load(scene)
    assert traj.names == model.names
    assert len(traj.t) == 11
    np.testing.assert_allclose(traj.q, np.tile(model.initial_q, (11, 1)), atol=1e-14)
    assert np.max(np.abs(traj.dq)) == 0.0
    assert np.max(np.abs(traj.ddq)) == 0.0
    assert prov["generator"] == "pinocchio" and prov["formulation"] == "ABA + RK4"


def test_rotational_spring_has_the_exact_frequency():
    # theta = 0.2 + 0.3 cos(ωt), ω = sqrt(k / I_A) with I_A = m L² / 3 = 4.
    scene = TEST_SCENES / "pin-torsion.yaml"
    traj, _ = pr.generate(scene, 3.0, 0.01, h=1e-4)
    w = math.sqrt(5.0 / 4.0)
    t = traj.t
    k = traj.names.index("theta")
    np.testing.assert_allclose(traj.q[:, k], 0.2 + 0.3 * np.cos(w * t), atol=1e-12)
    np.testing.assert_allclose(traj.dq[:, k], -0.3 * w * np.sin(w * t), atol=1e-12)
    np.testing.assert_allclose(traj.ddq[:, k], -0.3 * w * w * np.cos(w * t), atol=1e-12)
    theta = 0.2 + 0.3 * np.cos(w * t)
    x = traj.names.index("P.x")
    np.testing.assert_allclose(traj.q[:, x], 2 * np.cos(theta), atol=1e-12)
    np.testing.assert_allclose(traj.q[:, x + 1], 2 * np.sin(theta), atol=1e-12)


@pytest.mark.parametrize("scene", ["slider-crank.yaml", "slotted-lever.yaml",
                                   "driven/compressor-slider-crank.yaml"])
def test_sliders_are_prismatic_joints_whose_motion_solves_mbfg_equations(scene):
    # Fixed and mobile sliders as carriages on prismatic joints, a state-dependent gas
    # force: the accelerations at the start, mapped to natural coordinates, are mbfg's.
    traj, prov = pr.generate(SCENES / scene, 0.01, 0.01, h=1e-3)
    model = mbfg.load(SCENES / scene)
    want = model.accelerations(traj.q[0], traj.dq[0], 0.0)
    np.testing.assert_allclose(traj.ddq[0], want, atol=1e-6 * max(1.0, np.abs(want).max()))
    assert len(prov["joints"]) == len(model.bodies) + len(model.constraints)  # + carriages


TIED = """points:
  - {name: A, x: 0, y: 0, fixed: true}
  - {name: B, x: 2, y: 0, fixed: true}
  - {name: C, x: 1, y: 1, fixed: true}
  - {name: R1, x: -1, y: -0.5, fixed: true}
  - {name: R2, x: 3, y: -0.5, fixed: true}
  - {name: P, x: 1, y: -1}
  - {name: Q, x: 2, y: -1}
  - {name: F, x: 0.5, y: -0.5, mass: 0.3}
  - {name: K, x: 3, y: 1}
  - {name: L, x: 3, y: 2}
bodies:
  - {name: left, points: [A, P], mass: 1}
  - {name: right, points: [B, Q], mass: 1}
  - {name: plank, points: [K, L], mass: 0.5}
constraints:
  - {name: tie, type: distance, points: [P, Q]}
  - {name: rail, type: fixed_slider, point: F, line: [R1, R2]}
  - {name: slot, type: mobile_slider, point: F, line: [A, P]}
coordinates:
  - {name: theta, type: angle, points: [A, P]}
  - {name: phi, type: angle, points: [K, L]}
independent: [theta, K.x, K.y, phi]
initial:
  velocities: {theta: 1, phi: -0.5}
effects:
  - {type: gravity, vector: [0, -9.81]}
  - {name: hang, type: spring_damper, points: [C, K], stiffness: 30}
"""


def test_ties_second_sliders_and_floating_bodies_solve_mbfg_equations(tmp_path):
    # A distance tie between two bodies, a point on two sliders (a massive block in a
    # rail and in the slot of a pendulum), a body held by a spring alone: the
    # accelerations at the start are mbfg's.
    scene = tmp_path / "tied.yaml"
    scene.write_text(TIED)
    traj, prov = pr.generate(scene, 0.01, 0.01, h=1e-3)
    model = mbfg.load(str(scene))
    want = model.accelerations(traj.q[0], traj.dq[0], 0.0)
    np.testing.assert_allclose(traj.ddq[0], want, atol=1e-6 * max(1.0, np.abs(want).max()))
    assert "distance ties" in prov["formulation"]
    assert prov["settings"]["ties"] == ["tie: P-Q"] and prov["settings"]["sliders"] == ["slot: F on A-P"]
    assert prov["modelling_notes"] == ["body plank floats: x, y joints at K"]


def test_loads_match_the_mbfg_equations_at_random_states():
    # Gravity with an x component, a time-dependent torque, a rotational spring-damper
    # on a relative angle, a point force, a linear spring-damper, a point mass and a
    # three-point body: Pinocchio's accelerations mapped to natural coordinates must
    # solve mbfg's KKT system.
    pm = pr.PinocchioModel(TEST_SCENES / "pin-loads.yaml")
    rng = np.random.default_rng(7)
    for _ in range(5):
        q, v = rng.normal(size=pm.model.nq), rng.normal(size=pm.model.nv)
        t = rng.uniform(0, 3)
        Q, dQ, ddQ = pm.scene_state(q, v, pm.acceleration(t, q, v))
        assert np.max(np.abs(pm.mb.phi(Q))) < 1e-12
        np.testing.assert_allclose(ddQ, pm.mb.accelerations(Q, dQ, t), atol=1e-11)


def test_double_pendulum_matches_kkt_and_conserves_energy():
    traj, prov = pr.generate(DOUBLE, 1.0, 0.01, h=2e-5)
    model = mbfg.load(DOUBLE)
    for k in range(0, len(traj.t), 10):
        ddq = model.accelerations(traj.q[k], traj.dq[k], traj.t[k])
        np.testing.assert_allclose(traj.ddq[k], ddq, atol=1e-11)
    e = energy(model, traj)
    assert np.max(np.abs(e - e[0])) < 1e-11
    assert prov["max_energy_drift_J"] == pytest.approx(np.max(np.abs(e - e[0])))
    assert prov["max_abs_phi"] < 1e-12
    # the pendulum swings down from horizontal: something happens
    assert np.min(traj.q[:, traj.names.index("P2.y")]) < -1.0


def test_rk4_converges_at_fourth_order():
    # Halving h divides the error by 16: measured against a run at h/8.
    runs = [pr.generate(DOUBLE, 0.5, 1e-3, h=h)[0] for h in (1e-3, 5e-4, 1.25e-4)]
    err = [np.max(np.abs(r.q[:, :4] - runs[-1].q[:, :4])) for r in runs[:2]]
    assert 12 < err[0] / err[1] < 20, err


def test_closed_loops_follow_the_kkt_accelerations():
    # The four-bar closes its loop by a CONTACT_3D constraint; the mechanism's
    # accelerations must be mbfg's and the loop must stay closed.
    scene = SCENES / "fourbar.yaml"
    traj, prov = pr.generate(scene, 0.5, 0.05, h=2e-5)
    model = mbfg.load(scene)
    for k in range(len(traj.t)):
        ddq = model.accelerations(traj.q[k], traj.dq[k], traj.t[k])
        np.testing.assert_allclose(traj.ddq[k], ddq, atol=1e-8)
    assert prov["max_abs_phi"] < 1e-10
    e = energy(model, traj)
    assert np.max(np.abs(e - e[0])) < 1e-9
    assert "constraintDynamics" in prov["formulation"]


def test_tree_is_depth_first_for_a_branched_mechanism():
    # The robot branches at its fixed points; with joints in breadth-first order
    # Pinocchio's CRBA and constraint Cholesky are wrong. Its initial accelerations
    # (five loop closures, one of them redundant) must be mbfg's.
    pm = pr.PinocchioModel(SCENES / "pick-and-place.yaml")
    q, v = pm.initial_state()
    Q, dQ, ddQ = pm.scene_state(q, v, pm.acceleration(0.0, q, v))
    np.testing.assert_allclose(ddQ, pm.mb.accelerations(Q, dQ, 0.0), atol=1e-10)


def lagrange_double_pendulum(th1, th2, w1, w2, a1, a2, m1=1.0, m2=1.0, l1=1.0, l2=1.0,
                             g=9.81):
    """Generalized forces on the absolute angles of two uniform rods (closed form)."""
    c = m2 * l1 * l2 / 2
    m11, m22 = (m1 / 3 + m2) * l1 ** 2, m2 * l2 ** 2 / 3
    m12 = c * np.cos(th1 - th2)
    s = c * np.sin(th1 - th2)
    q1 = m11 * a1 + m12 * a2 + s * w2 ** 2 + (m1 / 2 + m2) * g * l1 * np.cos(th1)
    q2 = m12 * a1 + m22 * a2 - s * w1 ** 2 + m2 * g * l2 / 2 * np.cos(th2)
    return q1, q2


def test_rnea_torques_are_the_lagrange_forces_on_the_absolute_angles():
    t, Q, method = pr.inverse(DOUBLE, DOUBLE_CSV, with_method=True)
    assert method == "closed form"
    w = np.array([1.5, 2.3])
    amp = np.array([-0.8, -1.1])
    wt = np.outer(t, w)
    th, om, al = amp * (1 - np.cos(wt)), amp * w * np.sin(wt), amp * w ** 2 * np.cos(wt)
    q1, q2 = lagrange_double_pendulum(th[:, 0], th[:, 1], om[:, 0], om[:, 1],
                                      al[:, 0], al[:, 1])
    np.testing.assert_allclose(Q["theta1"], q1, atol=1e-11)
    np.testing.assert_allclose(Q["theta2"], q2, atol=1e-11)


def test_inverse_by_finite_differences_and_against_mbfg(tmp_path):
    # Without the closed form (another file name) the table is differentiated: close
    # to the exact forces; and mbfg's own inverse dynamics meets the project's target
    # of an RMSE within 1e-4 of the peak.
    copy = tmp_path / "prescribed.csv"
    copy.write_bytes(DOUBLE_CSV.read_bytes())
    t, exact = pr.inverse(DOUBLE, DOUBLE_CSV)
    t2, fd, method = pr.inverse(DOUBLE, copy, with_method=True)
    assert method.startswith("finite differences")
    for name in exact:
        peak = np.max(np.abs(exact[name]))
        assert np.sqrt(np.mean((fd[name] - exact[name]) ** 2)) < 1e-6 * peak
    result = mbfg.inverse(str(DOUBLE), str(DOUBLE_CSV))
    np.testing.assert_allclose(result.t, t, atol=1e-12)
    for name in exact:
        peak = np.max(np.abs(exact[name]))
        rmse = np.sqrt(np.mean((result.column(f"Q:{name}") - exact[name]) ** 2))
        assert rmse < 1e-4 * peak, (name, rmse / peak)


def test_cli_writes_the_contract_and_provenance(tmp_path):
    out = tmp_path / "dp.csv.gz"
    assert pr.main([str(DOUBLE), "--t-end", "0.05", "--dt", "0.01", "--h", "1e-4",
                    "--out", str(out)]) == 0
    traj = tj.read(out)
    assert traj.names == mbfg.load(DOUBLE).names and len(traj.t) == 6
    prov = (tmp_path / "dp.json").read_text()
    assert '"generator": "pinocchio"' in prov and '"pin"' in prov
