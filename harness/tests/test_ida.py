"""The IDA generator (harness/ida.py) against solutions that owe nothing to mbfg:
the four-bar's one-degree-of-freedom ODE, a mass on a spring, a mechanism at rest."""
import json
import pathlib

import numpy as np
import pytest
from scipy.integrate import solve_ivp

import mbfg
from harness import ida
from harness import trajectory as tj

ROOT = pathlib.Path(__file__).resolve().parents[2]
FOURBAR = ROOT / "scenes" / "fourbar.yaml"
SCENES = pathlib.Path(__file__).resolve().parent / "scenes"
G = 9.81


def fourbar_points(th, dth=0.0, ddth=0.0):
    """P1, P2 of scenes/fourbar.yaml (crank 1 m about A = 0, coupler 2 m, rocker √13 m
    about B = (4, 0), P2 on the branch above P1→B) and their first and second time
    derivatives for crank angle th and its rates."""
    B, L2, L3 = np.array([4.0, 0.0]), 2.0, np.sqrt(13.0)
    p1 = np.array([np.cos(th), np.sin(th)])
    d = np.linalg.norm(B - p1)
    u = (B - p1) / d
    a = (L2 ** 2 - L3 ** 2 + d ** 2) / (2 * d)
    p2 = p1 + a * u + np.sqrt(L2 ** 2 - a ** 2) * np.array([-u[1], u[0]])
    # Differentiate |P2 − P1|² = L2², |P2 − B|² = L3² once and twice.
    K = np.array([p2 - p1, p2 - B])
    v1 = np.array([-np.sin(th), np.cos(th)]) * dth
    v2 = np.linalg.solve(K, [(p2 - p1) @ v1, 0.0])
    a1 = np.array([-np.sin(th), np.cos(th)]) * ddth - p1 * dth ** 2
    a2 = np.linalg.solve(K, [(p2 - p1) @ a1 - (v2 - v1) @ (v2 - v1), -v2 @ v2])
    return np.concatenate([p1, p2]), np.concatenate([v1, v2]), np.concatenate([a1, a2])


def fourbar_reference(times):
    """The four-bar by virtual work in the crank angle: Jᵀ(M ẍ − Q) = 0 with x = x(θ),
    uniform rods (T = m/6 (|ȧ|² + ȧ·ḃ + |ḃ|²)), gravity half to each end."""
    I2 = np.eye(2)
    M = np.zeros((4, 4))
    M[:2, :2] += 1 / 3 * I2                                          # crank, A fixed
    M += 2 / 6 * np.block([[2 * I2, I2], [I2, 2 * I2]])              # coupler
    M[2:, 2:] += 4 / 3 * I2                                          # rocker, B fixed
    Q = -G * np.array([0, (1 + 2) / 2, 0, (2 + 4) / 2])

    def rhs(t, s):
        th, dth = s
        _, J, _ = fourbar_points(th, 1.0)             # ẋ = J θ̇
        _, _, b = fourbar_points(th, dth, 0.0)         # ẍ = J θ̈ + b
        return [dth, J @ (Q - M @ b) / (J @ M @ J)]

    sol = solve_ivp(rhs, (times[0], times[-1]), [0.0, 0.0], method="DOP853",
                    t_eval=times, rtol=1e-13, atol=1e-13)
    assert sol.success
    return np.array([fourbar_points(th)[0] for th in sol.y[0]])


@pytest.fixture(scope="module")
def fourbar_1s():
    times = np.arange(1001) * 1e-3
    return times, fourbar_reference(times)


def test_fourbar_ggl_matches_the_crank_angle_ode(fourbar_1s):
    times, ref = fourbar_1s
    traj, prov = ida.generate(FOURBAR, 1.0, 1e-3)
    np.testing.assert_allclose(traj.t, times, atol=1e-15)
    err = np.max(np.abs(traj.q - ref))
    print(f"GGL: max error {err:.2e} m, max |Φ| {prov['max_abs_phi']:.1e}, "
          f"{prov['steps']} steps, {prov['wall_time_s']:.2f} s")
    assert err <= 1e-9
    assert prov["max_abs_phi"] <= 1e-10
    assert prov["generator"] == "ida" and prov["formulation"] == "ggl"
    assert "scikit-sundae" in prov["versions"]
    # q̈ is the model's at the sampled state, so it matches the ODE's too.
    model = mbfg.load(FOURBAR)
    np.testing.assert_allclose(traj.ddq[0], model.accelerations(model.initial_q,
                                                                model.initial_dq, 0.0))


def test_fourbar_index3_is_a_looser_cross_check(fourbar_1s):
    times, ref = fourbar_1s
    traj, prov = ida.generate(FOURBAR, 1.0, 1e-3, formulation="index3")
    err = np.max(np.abs(traj.q - ref))
    print(f"index-3: max error {err:.2e} m, {prov['steps']} steps")
    assert err <= 1e-5


def test_jacobian_matches_differences_of_the_residual():
    model = mbfg.load(ROOT / "scenes" / "spring-damper.yaml")   # Q depends on q and q̇
    for formulation in ida.FORMULATIONS:
        dae = ida.Dae(model, formulation)
        y0, yp0 = dae.initial()
        rng = np.random.default_rng(3)
        y, yp = y0 + 0.01 * rng.normal(size=dae.size), yp0 + 0.01 * rng.normal(size=dae.size)
        cj, res = 7.0, np.empty(dae.size)
        J = np.empty((dae.size, dae.size))
        dae.jacobian(0.2, y, yp, res, cj, J)
        fd = np.empty_like(J)
        for j in range(dae.size):
            e = np.zeros(dae.size)
            e[j] = 1e-6
            hi, lo = np.empty(dae.size), np.empty(dae.size)
            dae.residual(0.2, y + e, yp + cj * e, hi)
            dae.residual(0.2, y - e, yp - cj * e, lo)
            fd[:, j] = (hi - lo) / 2e-6
        np.testing.assert_allclose(J, fd, atol=1e-6)


def test_nothing_acting_stays_at_rest():
    scene = SCENES / "ida-rest.yaml"
    traj, _ = ida.generate(scene, 1.0, 0.01)
    q0 = mbfg.load(scene).initial_q
    assert np.max(np.abs(traj.q - q0)) <= 1e-12
    assert np.max(np.abs(traj.dq)) <= 1e-12
    assert np.max(np.abs(traj.ddq)) <= 1e-12


def test_spring_oscillates_at_sqrt_k_over_m():
    traj, _ = ida.generate(SCENES / "ida-spring.yaml", 2.0, 1e-3)
    w = np.sqrt(20 / 0.5)
    x = 1 + 0.1 * np.cos(w * traj.t)
    err = np.max(np.abs(traj.q[:, 0] - x))
    print(f"spring: max error {err:.2e} m")
    assert err <= 1e-9
    np.testing.assert_allclose(traj.dq[:, 0], -0.1 * w * np.sin(w * traj.t), atol=1e-8)
    np.testing.assert_allclose(traj.ddq[:, 0], -w ** 2 * (x - 1), atol=1e-8)
    assert np.max(np.abs(traj.q[:, 1])) <= 1e-12


def test_a_failed_run_raises():
    with pytest.raises(RuntimeError, match="max_num_steps"):
        ida.generate(FOURBAR, 1.0, 0.1, max_num_steps=5)
    # The parallelogram goes flat (Φq loses rank) at t ≈ 0.52 s: IDA's own failure,
    # reported with its message instead of a truncated trajectory.
    with pytest.raises(RuntimeError, match=r"failed after \d+ steps at t = 0\.52.*"
                                           r"Convergence tests failed"):
        ida.generate(ROOT / "scenes" / "hard" / "parallelogram.yaml", 1.0, 1e-3)


def test_cli_writes_trajectory_and_provenance(tmp_path):
    out = tmp_path / "spring.csv.gz"
    assert ida.main([str(SCENES / "ida-spring.yaml"), "--t-end", "0.1", "--dt", "0.01",
                     "--out", str(out)]) == 0
    traj = tj.read(out)
    assert traj.names == ["S.x", "S.y"] and len(traj.t) == 11
    prov = json.loads((tmp_path / "spring.json").read_text())
    assert prov["generator"] == "ida" and prov["settings"]["rtol"] == 1e-12
