"""The mbfg Python module: the assembled model and the runs, against what the
model's definitions imply (docs/python.md)."""
import pathlib

import numpy as np
import pytest

import mbfg

ROOT = pathlib.Path(__file__).resolve().parents[2]
FOURBAR = ROOT / "scenes" / "fourbar.yaml"
ROBOT = ROOT / "scenes" / "pick-and-place.yaml"


def test_fourbar_layout_and_bodies():
    m = mbfg.load(FOURBAR)
    assert m.names == ["P1.x", "P1.y", "P2.x", "P2.y"]
    assert (m.n, m.m, m.dof) == (4, 3, 1)
    free = {p["name"]: p["index"] for p in m.points}
    assert free == {"A": None, "P1": 0, "P2": 2, "B": None}
    rocker = next(b for b in m.bodies if b["name"] == "rocker")
    assert rocker["points"] == ["P2", "B"]
    assert rocker["length"] == pytest.approx(np.sqrt(13))
    # Uniform rod: I about the centre = m L² / 12.
    assert rocker["inertia_cog"] == pytest.approx(4 * 13 / 12)
    assert m.effects == [{"type": "gravity", "vector": (0.0, -9.81)}]


def test_mass_matrix_gives_kinetic_energy():
    m = mbfg.load(ROBOT)
    rng = np.random.default_rng(1)
    dq = rng.normal(size=m.n)
    M = m.mass_matrix()
    assert M.shape == (m.n, m.n)
    np.testing.assert_allclose(M, M.T)
    assert m.kinetic_energy(dq) == pytest.approx(0.5 * dq @ M @ dq, rel=1e-12)


def test_phi_q_matches_finite_differences():
    m = mbfg.load(ROBOT)
    q = m.initial_q + 0.01 * np.random.default_rng(2).normal(size=m.n)
    J = m.phi_q(q)
    assert J.shape == (m.m, m.n)
    h = 1e-6
    fd = np.column_stack([(m.phi(q + h * e) - m.phi(q - h * e)) / (2 * h) for e in np.eye(m.n)])
    np.testing.assert_allclose(J, fd, atol=1e-7)
    assert np.max(np.abs(m.phi(m.initial_q))) < 1e-10
    # Φ̇q = d/dt Φq along q̇.
    dq = np.random.default_rng(3).normal(size=m.n)
    fd_dot = (m.phi_q(q + h * dq) - m.phi_q(q - h * dq)) / (2 * h)
    np.testing.assert_allclose(m.phi_q_dot(q, dq), fd_dot, atol=1e-7)


def test_accelerations_satisfy_the_constraints():
    m = mbfg.load(ROBOT)
    q, dq = m.initial_q, m.initial_dq + 0.0
    ddq = m.accelerations(q, dq, 0.0)
    # Φq q̈ + Φ̇q q̇ = 0, and M q̈ − Q lies in the range of Φqᵀ.
    np.testing.assert_allclose(m.phi_q(q) @ ddq + m.phi_q_dot(q, dq) @ dq, 0, atol=1e-10)
    r = m.mass_matrix() @ ddq - m.generalized_forces(q, dq, 0.0)
    J = m.phi_q(q)
    lam, *_ = np.linalg.lstsq(J.T, r, rcond=None)
    np.testing.assert_allclose(J.T @ lam, r, atol=1e-9)


def test_simulate_returns_the_csv_contract():
    r = mbfg.simulate(FOURBAR, coords="dc", dt=1e-3, t_end=0.2, window=2)
    assert r.columns[:3] == ["t", "q:P1.x", "q:P1.y"]
    assert len(r.columns) == 1 + 3 * 4 and r.Q is None
    assert r.q.shape == (201, 4)
    np.testing.assert_allclose(r.t[-1], 0.2)
    assert r.summary["worst_phi"] < 1e-9 and r.failures == []
    np.testing.assert_array_equal(r.column("q:P2.y"), r.q[:, 3])


@pytest.mark.parametrize("scene, coords", [("fourbar", "dc"), ("fourbar-theta", "ic")])
def test_the_general_solver_takes_the_square_steps_to_their_solution(scene, coords):
    # square_steps=False solves the window's graph where the default solves each step
    # as a square system: the same trajectory, to the step tolerance.
    path = ROOT / "scenes" / f"{scene}.yaml"
    square = mbfg.simulate(path, coords=coords, dt=1e-3, t_end=0.2, window=5)
    general = mbfg.simulate(path, coords=coords, dt=1e-3, t_end=0.2, window=5,
                            square_steps=False)
    assert general.summary["complete"] and general.q.shape == square.q.shape
    np.testing.assert_allclose(general.q, square.q, atol=1e-9)
    # The summary says what ran: the window of five taken one step at a time by the
    # square step, or run as asked through the general solver.
    ran = square.summary["plan"]
    assert (ran["schedule"], ran["window"], ran["asked"]) == ("stepwise", 1, "window 5")
    assert ran["square_step"] and square.summary["square_steps"] == 201
    assert square.summary["general_steps"] == 0
    assert ran["description"] == "window 5 asked, taken one step at a time, square steps"
    ran = general.summary["plan"]
    assert (ran["schedule"], ran["window"], ran["square_step"]) == ("fixed_lag", 5, False)
    assert general.summary["square_steps"] == 0
    assert ran["integrator"] == "trapezoidal" and ran["rescues"][0] != "GeneralSolver"


def test_inverse_from_a_mapping_matches_the_file():
    scene = ROOT / "scenes" / "fourbar-theta.yaml"
    csv = ROOT / "scenes" / "trajectories" / "fourbar-theta.csv"
    a = mbfg.inverse(scene, csv)
    data = np.loadtxt(csv, delimiter=",", skiprows=1)[:201]
    b = mbfg.inverse(scene, {"t": data[:, 0], "theta": data[:, 1]}, coords="ic")
    assert a.Q.shape[1] == 5 and b.Q.shape == (201, 5)
    # Same torque on the crank angle from DC and IC near the start (1e-3 of 66 N·m).
    np.testing.assert_allclose(a.column("Q:theta")[50:150], b.column("Q:theta")[50:150], atol=0.1)


def test_errors_are_clear():
    with pytest.raises(mbfg.SceneError, match="nope.yaml"):
        mbfg.load(ROOT / "nope.yaml")
    m = mbfg.load(FOURBAR)
    with pytest.raises(ValueError, match="4 coordinates"):
        m.phi([1.0, 2.0])
    with pytest.raises(ValueError, match="no point named 'Z'"):
        m.point_position(m.initial_q, "Z")
    with pytest.raises(ValueError, match="coords"):
        mbfg.simulate(FOURBAR, coords="xx", t_end=0.01)
    with pytest.raises(ValueError, match="time step must be positive"):
        mbfg.simulate(FOURBAR, dt=-1.0)
    with pytest.raises(ValueError, match="independent"):
        mbfg.simulate(FOURBAR, coords="ic", t_end=0.01)
    with pytest.raises(ValueError, match="unknown|no coordinate|not a coordinate"):
        mbfg.inverse(ROOT / "scenes" / "fourbar-theta.yaml", {"t": [0, 0.01, 0.02], "phi": [0, 0, 0]})


def test_a_solve_that_does_not_converge_raises():
    with pytest.raises(mbfg.SolveError, match="did not converge"):
        mbfg.simulate(FOURBAR, dt=1e-3, t_end=0.05, max_iterations=1)
