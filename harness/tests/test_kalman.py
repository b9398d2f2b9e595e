"""The peer estimators (harness/kalman.py) on the three-simulation benchmark: the true
four-bar simulated by IDA, noisy readings of it, the bad model open loop and corrected."""
import pathlib

import numpy as np
import pytest

pytest.importorskip("sksundae")
pytest.importorskip("filterpy")

from harness import generators, kalman  # noqa: E402

ROOT = pathlib.Path(__file__).resolve().parents[2]
SCENES = ROOT / "scenes" / "estimation"
TRUE, BAD = SCENES / "fourbar.yaml", SCENES / "fourbar-bad.yaml"
DT, T_END, SEED = 0.005, 10.0, 0
ENCODER = kalman.Sensor("enc", "encoder", "theta", np.deg2rad(1.0))
GYRO = kalman.Sensor("gyro", "gyroscope", "coupler", 9.84e-4)


def rmse(a, b):
    return float(np.sqrt(np.mean((np.asarray(a) - np.asarray(b)) ** 2)))


@pytest.fixture(scope="module")
def bench():
    """Truth (IDA, 10 s at 5 ms), the models, seeded noisy readings of both sensors and
    the generalized force on theta that the bad model lacks along the truth."""
    truth, _ = generators.get("ida").generate(TRUE, T_END, DT)
    true, bad = kalman.Independent(TRUE), kalman.Independent(BAD)
    meas = kalman.Measurements(true, [ENCODER, GYRO])
    clean = np.array([meas.values(q, dq) for q, dq in zip(truth.q, truth.dq)])
    noisy = clean + np.random.default_rng(SEED).standard_normal(clean.shape) * meas.sigma
    force = np.array([true.R(q).T @ (true.model.generalized_forces(q, dq, t)
                                     - bad.model.generalized_forces(q, dq, t))
                      for t, q, dq in zip(truth.t, truth.q, truth.dq)])[:, 0]
    i = truth.names.index("theta")
    return dict(truth=truth, i=i, true=true, bad=bad, force=force,
                readings=kalman.Readings(truth.t, {"enc": noisy[:, 0], "gyro": noisy[:, 1]}))


def test_true_fourbar_has_the_published_range_of_motion(bench):
    tr, i = bench["truth"], bench["i"]
    assert 4.8 < np.max(np.abs(tr.q[:, i])) < 5.0
    assert 6.7 < np.max(np.abs(tr.dq[:, i])) < 6.9
    assert 26 < np.max(np.abs(tr.ddq[:, i])) < 28


def test_open_loop_bad_model_is_far_off(bench):
    tr, i = bench["truth"], bench["i"]
    ol = kalman.simulate(bench["bad"], tr.t)
    assert 6.5 < rmse(ol.z[:, 0], tr.q[:, i]) < 8.0          # published: 7.2 rad
    # The filters' integrator on the true model stays on IDA's motion.
    exact = kalman.simulate(bench["true"], tr.t[:401])
    assert np.max(np.abs(exact.z[:, 0] - tr.q[:401, i])) < 1e-3


def test_force_the_bad_model_lacks_has_the_published_size(bench):
    assert 9.0 < np.sqrt(np.mean(bench["force"] ** 2)) < 10.0   # published: 9.6 N·m


@pytest.mark.parametrize("scene", ["fourbar.yaml", "fivebar.yaml"])
def test_reduced_jacobians_match_finite_differences(scene):
    ic = kalman.Independent(SCENES / scene)
    sensors = [kalman.Sensor("e", "encoder", ic.names[0], 0.01),
               kalman.Sensor("g", "gyroscope", ic.model.bodies[1]["name"], 0.01)]
    meas = kalman.Measurements(ic, sensors)
    rng = np.random.default_rng(3)
    z = ic.model.initial_q[ic.iz] + 0.3 * rng.standard_normal(ic.f)
    dz = rng.standard_normal(ic.f)
    q, dq = ic.state(z, dz, ic.model.initial_q)
    h, Hz, Hdz = meas.reduced(q, dq)
    eps = 1e-6
    for j in range(ic.f):
        e = np.zeros(ic.f)
        e[j] = eps
        hz = meas.values(*ic.state(z + e, dz, q))
        hdz = meas.values(*ic.state(z, dz + e, q))
        np.testing.assert_allclose((hz - h) / eps, Hz[:, j], atol=1e-4)
        np.testing.assert_allclose((hdz - h) / eps, Hdz[:, j], atol=1e-4)
    # The gyroscope reads the body's angular velocity (crank: the crank angle's rate).
    crank = kalman.Measurements(ic, [kalman.Sensor("w", "gyroscope", ic.model.bodies[0]["name"], 1)])
    if scene == "fourbar.yaml":
        assert crank.values(q, dq)[0] == pytest.approx(dz[0], rel=1e-12)


def test_readings_csv_round_trip(tmp_path):
    t = np.arange(5) * DT
    r = kalman.Readings(t, {"enc": np.array([0.1, np.nan, 0.3, np.nan, 0.5]),
                            "gyro": np.array([np.nan, 1.0, 2.0, 3.0, np.nan])})
    kalman.write_readings(tmp_path / "r.csv", r)
    assert (tmp_path / "r.csv").read_text().splitlines()[:3] == ["t,enc,gyro", "0.0,0.1,",
                                                                 "0.005,,1.0"]
    back = kalman.read_readings(tmp_path / "r.csv")
    np.testing.assert_array_equal(back.t, t)
    for k in r.columns:
        np.testing.assert_array_equal(back.columns[k], r.columns[k])


def check_tracking(bench, est, limit):
    tr, i = bench["truth"], bench["i"]
    err = est.z[:, 0] - tr.q[:, i]
    ol = 7.2
    assert rmse(est.z[:, 0], tr.q[:, i]) < limit < ol / 100
    # Converged: the last half is at the noise's level.
    assert np.sqrt(np.mean(err[len(err) // 2:] ** 2)) < limit
    # Honest σ: the truth within ±2σ at most steps.
    assert np.mean(np.abs(err) <= 2 * est.sz[:, 0]) >= 0.85
    assert rmse(est.dz[:, 0], tr.dq[:, i]) < 0.3
    return err


def test_error_ekf_with_a_crank_encoder_tracks_theta(bench):
    est = kalman.ErrorEKF(bench["bad"], [ENCODER]).run(bench["readings"])   # reads `enc` only
    check_tracking(bench, est, 2e-2)                                         # published 5.1e-3
    assert est.force is None and est.filter == "errorEKF"


def test_ukf_with_a_crank_encoder_tracks_theta(bench):
    est = kalman.UKF(bench["bad"], [ENCODER]).run(bench["readings"])
    check_tracking(bench, est, 2e-2)                                         # published 5.2e-3


def test_error_ekf_fe_with_a_coupler_gyroscope_estimates_the_force(bench):
    est = kalman.ErrorEKF(bench["bad"], [GYRO], force_estimation=True).run(bench["readings"])
    force = bench["force"]
    f_rms, f_err = np.sqrt(np.mean(force ** 2)), rmse(est.force[:, 0], force)
    assert f_err < 0.5 * f_rms                                               # published 2.6 vs 9.6
    assert np.mean(np.abs(est.force[:, 0] - force) <= 2 * est.sforce[:, 0]) >= 0.85
    tr, i = bench["truth"], bench["i"]
    assert rmse(est.z[:, 0], tr.q[:, i]) < 5e-2                              # published 6.8e-3
    assert rmse(est.dz[:, 0], tr.dq[:, i]) < 5e-2                            # published 4.8e-3


def test_missing_readings_only_predict(bench):
    """Encoder every fourth row (50 Hz): the filter still converges."""
    r = bench["readings"]
    rows = 801
    enc = r.columns["enc"][:rows].copy()
    enc[np.arange(rows) % 4 != 0] = np.nan
    est = kalman.ErrorEKF(bench["bad"], [ENCODER]).run(kalman.Readings(r.t[:rows], {"enc": enc}))
    tr, i = bench["truth"], bench["i"]
    assert np.sqrt(np.mean((est.z[400:, 0] - tr.q[400:rows, i]) ** 2)) < 2e-2


def test_sensor_from_mapping_and_errors(bench):
    s = kalman.Sensor.from_mapping({"name": "g", "type": "gyroscope", "body": "rocker",
                                    "sigma": 0.01})
    assert s == kalman.Sensor("g", "gyroscope", "rocker", 0.01)
    with pytest.raises(ValueError, match="unknown type"):
        kalman.Measurements(bench["bad"], [kalman.Sensor("a", "accelerometer", "P1", 1)])
    with pytest.raises(ValueError, match="no readings for enc"):
        kalman.ErrorEKF(bench["bad"], [ENCODER]).run(kalman.Readings(np.arange(3) * DT, {}))
