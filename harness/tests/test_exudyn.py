"""The exudyn generator (harness/exudyn_ref.py) against expectations that owe nothing
to mbfg's integrators: rest, analytic oscillators, the constraints, energy
conservation and the equations of motion at exudyn's own states."""
import json
import pathlib

import numpy as np
import pytest

import mbfg
from harness import exudyn_ref
from harness import trajectory as tj

ROOT = pathlib.Path(__file__).resolve().parents[2]
SCENES = pathlib.Path(__file__).resolve().parent / "scenes"


def energy(model, traj):
    return np.array([model.kinetic_energy(dq) + model.potential_energy(q)
                     for q, dq in zip(traj.q, traj.dq)])


def column(traj, name):
    return traj.names.index(name)


@pytest.mark.parametrize("solver", ["generalized_alpha", "trapezoidal_index2"])
def test_rest_stays_at_rest(solver):
    scene = SCENES / "exu-rest.yaml"
    model = mbfg.load(scene)
    traj, prov = exudyn_ref.generate(scene, 0.5, 1e-2, solver=solver, h=1e-3)
    assert traj.names == model.names
    assert traj.q.shape == (51, model.n)
    np.testing.assert_allclose(traj.t, np.arange(51) * 1e-2, atol=1e-12)
    np.testing.assert_allclose(traj.q - model.initial_q, 0, atol=1e-12)
    # Generalized-α carries its own acceleration variables, which its Newton iteration
    # fits to the start's round-off (|Φ| ~ 1e-16) to its tolerance 1e-12 over h² = 1e-6:
    # q̈ up to ~1e-7, q̇ ~ h·q̈. The trapezoidal index-2 solver keeps exact zeros.
    rates = (1e-10, 1e-6) if solver == "generalized_alpha" else (1e-12, 1e-12)
    np.testing.assert_allclose(traj.dq, 0, atol=rates[0])
    np.testing.assert_allclose(traj.ddq, 0, atol=rates[1])
    assert prov["steps"] == 500 and prov["max_abs_phi"] < 1e-12


def test_spring_oscillates_at_its_analytic_frequency():
    # k = 20 N/m, m = 0.5 kg on a guide at 30°: s = 1 + 0.1 cos(ω t), ω = √40.
    scene = SCENES / "exu-spring.yaml"
    traj, prov = exudyn_ref.generate(scene, 2.0, 1e-3, h=1e-4)
    w = np.sqrt(20 / 0.5)
    s = traj.q[:, column(traj, "s")]
    np.testing.assert_allclose(s, 1 + 0.1 * np.cos(w * traj.t), atol=2e-7)
    np.testing.assert_allclose(traj.dq[:, column(traj, "s")], -0.1 * w * np.sin(w * traj.t), atol=2e-6)
    np.testing.assert_allclose(traj.ddq[:, column(traj, "s")], -0.1 * w ** 2 * np.cos(w * traj.t),
                               atol=1e-4)
    # The point stays on the inclined guide.
    x, y = traj.q[:, column(traj, "S.x")], traj.q[:, column(traj, "S.y")]
    np.testing.assert_allclose(y, np.tan(np.pi / 6) * x, atol=1e-12)
    # Frequency from the upward crossings of the rest length.
    d = s - 1
    up = np.flatnonzero((d[:-1] < 0) & (d[1:] >= 0))
    tc = traj.t[up] - d[up] * (traj.t[up + 1] - traj.t[up]) / (d[up + 1] - d[up])
    assert 2 * np.pi / np.mean(np.diff(tc)) == pytest.approx(w, rel=1e-5)


def test_rotational_spring_and_torque():
    # I = 0.25, k = 4: θ = 0.3 + 0.1 + 0.1 cos(4 t) with the constant 0.4 N·m torque.
    scene = SCENES / "exu-torsion.yaml"
    traj, _ = exudyn_ref.generate(scene, 2.0, 1e-3, h=1e-4)
    th = traj.q[:, column(traj, "theta")]
    np.testing.assert_allclose(th, 0.4 + 0.1 * np.cos(4 * traj.t), atol=1e-6)
    np.testing.assert_allclose(traj.dq[:, column(traj, "theta")], -0.4 * np.sin(4 * traj.t), atol=1e-5)


def test_refuses_what_it_cannot_model():
    # The pick-and-place robot's parallelograms make a rigid-body equation redundant:
    # exudyn's joints would be redundant too, and the generator says so.
    with pytest.raises(tj.Unsupported, match="redundant equation 'arm2b"):
        exudyn_ref.generate(ROOT / "scenes" / "pick-and-place.yaml", 0.1, 1e-2, h=1e-3)


def test_step_must_divide_the_sampling_step():
    with pytest.raises(ValueError, match="divide"):
        exudyn_ref.generate(ROOT / "scenes" / "pendulum.yaml", 0.1, 1e-2, h=3e-3)


def check_mechanism(scene, t_end=1.0, h=1e-4):
    """On the constraints, energy conserved, and q̈ equal to the equations of motion's
    (mbfg's KKT solve at exudyn's state: an independent formulation's state checked
    against the model's definition)."""
    model = mbfg.load(scene)
    traj, prov = exudyn_ref.generate(scene, t_end, 1e-3, h=h)
    assert prov["steps"] == round(t_end / h)
    assert prov["max_abs_phi"] < 1e-12
    velocity_phi = max(np.max(np.abs(model.phi_q(q) @ dq)) for q, dq in zip(traj.q, traj.dq))
    assert velocity_phi < 1e-5
    # Generalized-α at h = 1e-4 loses O(h²) energy: 3.1e-5 J of the four-bar's 47 J of
    # peak kinetic energy (6.6e-7), ten times less at h = 1e-5.
    e = energy(model, traj)
    peak = max(model.kinetic_energy(dq) for dq in traj.dq)
    assert np.max(np.abs(e - e[0])) < 1e-6 * peak
    for k in range(0, len(traj.t), len(traj.t) // 5):
        a = model.accelerations(traj.q[k], traj.dq[k], traj.t[k])
        np.testing.assert_allclose(traj.ddq[k], a, atol=1e-4 * max(1.0, np.max(np.abs(a))))
    return model, traj, prov


def test_fourbar_on_constraints_conserves_energy_and_obeys_the_dynamics():
    model, traj, prov = check_mechanism(ROOT / "scenes" / "fourbar.yaml")
    # It falls: the crank turns well away from its start.
    assert np.max(np.abs(traj.q[:, 1])) > 0.3


def test_double_pendulum_on_constraints_conserves_energy_and_obeys_the_dynamics():
    model, traj, _ = check_mechanism(ROOT / "scenes" / "double-pendulum.yaml")
    # The angles are continuous and agree with the points.
    th1 = traj.q[:, column(traj, "theta1")]
    p1 = traj.q[:, [column(traj, "P1.x"), column(traj, "P1.y")]]
    np.testing.assert_allclose(np.cos(th1), p1[:, 0], atol=1e-12)
    np.testing.assert_allclose(np.sin(th1), p1[:, 1], atol=1e-12)
    assert np.max(np.abs(np.diff(th1))) < 0.1


def test_cli_writes_trajectory_and_provenance(tmp_path):
    out = tmp_path / "pendulum.csv.gz"
    assert exudyn_ref.main([str(ROOT / "scenes" / "pendulum.yaml"), "--t-end", "0.1", "--dt",
                            "1e-2", "--h", "1e-3", "--solver", "trapezoidal_index2",
                            "--out", str(out)]) == 0
    traj = tj.read(out)
    assert traj.names == ["P.x", "P.y", "theta"] and len(traj.t) == 11
    prov = json.loads((tmp_path / "pendulum.json").read_text())
    assert prov["generator"] == "exudyn" and prov["settings"]["solver"] == "trapezoidal_index2"
    assert prov["steps"] == 100 and "exudyn" in prov["versions"]


def test_parallelogram_through_its_flat_configurations():
    # θ = π/2 + 3t, coupler horizontal; flat (Φ_q rank-deficient) at t = π/6, π/2.
    # exudyn fails there unless told to pass a singular Jacobian, and its Newton
    # iteration does not reach the tight default tolerance at the flat configuration.
    scene = ROOT / "scenes" / "hard" / "parallelogram.yaml"
    with pytest.raises(exudyn_ref.SolveError, match=r"failed at t = 0\.52"):
        exudyn_ref.generate(scene, 1.0, 1e-3, h=1e-4)
    traj, prov = exudyn_ref.generate(scene, 2.0, 1e-3, h=1e-4, newton_rtol=1e-8,
                                     newton_atol=1e-10, ignore_singular_jacobian=True)
    theta = traj.q[:, column(traj, "theta")]
    np.testing.assert_allclose(theta, np.pi / 2 + 3 * traj.t, atol=1e-6)
    np.testing.assert_allclose(traj.q[:, column(traj, "P1.y")], traj.q[:, column(traj, "P2.y")],
                               atol=1e-9)
    assert prov["max_abs_phi"] < 1e-12


@pytest.mark.parametrize("scene", [SCENES / "exu-loads.yaml", ROOT / "scenes" / "slotted-lever.yaml"])
def test_loads_and_mobile_slider_obey_the_dynamics(scene):
    # Forces and torques (constant and time-dependent); the slotted lever's pin slides
    # on the moving lever (a prismatic joint on the lever's frame) under a motor torque.
    model = mbfg.load(scene)
    traj, _ = exudyn_ref.generate(scene, 1.0, 1e-3, h=1e-4)
    assert max(np.max(np.abs(model.phi(q))) for q in traj.q) < 1e-12
    for k in range(0, len(traj.t), len(traj.t) // 5):
        a = model.accelerations(traj.q[k], traj.dq[k], traj.t[k])
        np.testing.assert_allclose(traj.ddq[k], a, atol=1e-4 * max(1.0, np.max(np.abs(a))))
