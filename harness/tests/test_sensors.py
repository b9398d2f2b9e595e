"""Sensors from Python: their descriptions, readings with Jacobians against finite
differences, and `mbfg.measure` (seeded, at each sensor's rate, the same readings as
`mbfg measure`)."""

import pathlib
import subprocess

import numpy as np
import pytest

import mbfg

ROOT = pathlib.Path(__file__).resolve().parents[2]
SCENE = ROOT / "scenes/sensors/fourbar-sensors.yaml"
TRUTH = ROOT / "scenes/sensors/fourbar-truth.csv"
MBFG = ROOT / "target/release/mbfg"


def test_sensors_are_described():
    m = mbfg.load(SCENE)
    sensors = {s["name"]: s for s in m.sensors()}
    assert list(sensors) == ["enc", "gyro", "acc", "cam", "gap"]
    assert sensors["acc"]["columns"] == ["acc.x", "acc.y"]
    assert sensors["enc"]["type"] == "encoder"
    assert sensors["enc"]["resolution"] == 4096 and sensors["enc"]["rate"] == 200.0
    assert sensors["gyro"]["rate"] is None and sensors["gyro"]["reads"] == [True, True, False]
    assert mbfg.load(ROOT / "scenes/fourbar-theta.yaml").sensors() == []


def test_sensor_jacobians_match_finite_differences():
    m = mbfg.load(SCENE)
    rng = np.random.default_rng(1)
    x = [m.initial_q + 0.1 * rng.standard_normal(m.n), rng.standard_normal(m.n),
         rng.standard_normal(m.n)]
    for s in m.sensors():
        h, *jac = m.sensor_value(s["name"], *x, t=0.2)
        assert h.shape == (len(s["columns"]),)
        for k in range(3):
            assert jac[k].shape == (len(h), m.n)
            for j in range(m.n):
                up = [v.copy() for v in x]
                dn = [v.copy() for v in x]
                up[k][j] += 1e-6
                dn[k][j] -= 1e-6
                fd = (m.sensor_value(s["name"], *up, t=0.2)[0]
                      - m.sensor_value(s["name"], *dn, t=0.2)[0]) / 2e-6
                assert np.allclose(jac[k][:, j], fd, atol=1e-6), (s["name"], k, j)
    with pytest.raises(mbfg.InvalidArgument, match="no sensor named 'lidar'"):
        m.sensor_value("lidar", *x)


def test_measure_matches_the_cli(tmp_path):
    a = mbfg.measure(SCENE, TRUTH, seed=3)
    b = mbfg.measure(mbfg.load(SCENE), TRUTH, seed=3)
    c = mbfg.measure(SCENE, TRUTH, seed=4)
    assert list(a) == ["t", "enc", "gyro", "acc.x", "acc.y", "cam.x", "cam.y", "gap"]
    for k in a:
        assert np.array_equal(a[k], b[k], equal_nan=True)
    assert not np.array_equal(a["gyro"], c["gyro"])
    # enc at 200 Hz and cam at 50 Hz on a 5 ms trajectory: every row, every fourth.
    assert np.isfinite(a["enc"]).all()
    assert np.isfinite(a["cam.x"][::4]).all() and np.isnan(a["cam.x"][1::4]).all()
    out = tmp_path / "m.csv"
    r = subprocess.run([str(MBFG), "measure", str(SCENE), "--trajectory", str(TRUTH), "--seed", "3",
                        "--out", str(out)], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    lines = out.read_text().splitlines()
    assert lines[0].split(",") == list(a)
    for i, line in enumerate(lines[1:]):
        cells = [float(v) if v else np.nan for v in line.split(",")]
        assert np.array_equal(cells, [a[k][i] for k in a], equal_nan=True)
    # A simulated Result serves as the truth too.
    result = mbfg.simulate(SCENE, dt=0.005, t_end=0.1)
    d = mbfg.measure(SCENE, result, seed=3, rate=100)
    assert len(d["t"]) == 21 and np.isnan(d["gyro"][1]) and np.isfinite(d["gyro"][2])
    with pytest.raises(mbfg.InvalidArgument, match="has no sensors"):
        mbfg.measure(ROOT / "scenes/fourbar-theta.yaml", TRUTH, seed=1)
