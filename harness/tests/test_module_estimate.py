"""mbfg.estimate from Python: the summary names the coordinates the readings leave
undetermined (a freely spinning bar read by a gyroscope alone, without gravity),
and none where the dynamics carry the angle into the reading (the same bar under
gravity)."""

import pathlib

import numpy as np
import pytest

mbfg = pytest.importorskip("mbfg")

SPIN = ((pathlib.Path(__file__).resolve().parents[2] / "tests" / "data" / "spinning-bar.yaml").read_text()
        + "initial:\n  positions: {th: 0}\n  velocities: {th: 1}\n"
        + "sensors:\n  - {name: gyro, type: gyroscope, body: bar, sigma: 1e-3}\n")


def _summary(tmp_path, gravity):
    text = SPIN + ("effects:\n  - {type: gravity, vector: [0, -9.81]}\n" if gravity else "")
    scene = tmp_path / "spin.yaml"
    scene.write_text(text)
    run = mbfg.simulate(str(scene), dt=0.01, t_end=3.0)
    # The gyroscope reads the bar's rate, with its σ of noise (seeded).
    rng = np.random.default_rng(1)
    rate = run.column("dq:th")
    readings = {"t": list(run.column("t")), "gyro": list(rate + 1e-3 * rng.standard_normal(len(rate)))}
    return mbfg.estimate(str(scene), readings)["summary"]


def test_an_angle_no_sensor_observes_is_named(tmp_path):
    assert _summary(tmp_path, gravity=False)["undetermined"] == ["th"]


def test_gravity_carries_the_angle_into_the_gyroscope(tmp_path):
    assert _summary(tmp_path, gravity=True)["undetermined"] == []


def test_the_summary_says_how_far_the_window_grew(tmp_path):
    s = _summary(tmp_path, gravity=True)
    assert s["window"] == 20
    assert s["window_longest"] >= 20 and s["window_longest"] <= 80
    assert 1 <= s["window_mean"] <= s["window_longest"]


def test_the_summary_counts_the_starts_solved_again(tmp_path):
    # A pendulum's start its gyroscope fits at once: no window holding it is far
    # from a fit, and none is solved again from the filter's path.
    s = _summary(tmp_path, gravity=True)
    assert s["start_refits"] == 0


def test_an_estimate_that_left_the_motion_raises_with_its_failure():
    # The five-bar read by its crank encoders and coupler gyroscopes, a noise draw
    # whose start two motions fit: a window of 5 follows the wrong one until the
    # readings disagree beyond any σ, and the run stops there (docs/estimation.md).
    import pathlib
    scenes = pathlib.Path(__file__).resolve().parents[2] / "scenes" / "estimation"
    truth = mbfg.simulate(str(scenes / "fivebar.yaml"), dt=1e-3, t_end=2.0)
    readings = mbfg.measure(str(scenes / "fivebar.yaml"), truth, seed=9, rate=200)
    with pytest.raises(mbfg.SolveError) as caught:
        mbfg.estimate(str(scenes / "fivebar-bad.yaml"), readings, window=5)
    failure = caught.value.failure
    assert failure["kind"] == "diverged" and failure["step"] >= 99
    assert 0 < len(caught.value.result["t"]) <= failure["step"]


def test_the_integrator_is_chosen_named_and_checked():
    # The trapezoidal rule by default for a state, Hermite–Simpson for a scene that
    # identifies parameters; either on request; any other name refused by name; the
    # online estimator takes the same choice.
    import pathlib
    root = pathlib.Path(__file__).resolve().parents[2] / "scenes"
    truth = mbfg.simulate(str(root / "estimation" / "fourbar.yaml"), dt=1e-3, t_end=0.5)
    readings = mbfg.measure(str(root / "estimation" / "fourbar.yaml"), truth, seed=1, rate=200)
    state = str(root / "estimation" / "fourbar-bad.yaml")
    assert mbfg.estimate(state, readings)["summary"]["integrator"] == "trapezoidal"
    hs = mbfg.estimate(state, readings, integrator="hermite-simpson")
    assert hs["summary"]["integrator"] == "hermite-simpson"
    assert np.all(np.isfinite(hs["q:theta"]))
    identify = str(root / "identification" / "fourbar-mass-bad.yaml")
    truth = mbfg.simulate(str(root / "identification" / "fourbar-mass.yaml"), dt=1e-3, t_end=0.5)
    readings = mbfg.measure(str(root / "identification" / "fourbar-mass.yaml"), truth, seed=1)
    out = mbfg.estimate(identify, readings, batch=True)
    assert out["summary"]["integrator"] == "hermite-simpson"
    assert mbfg.estimate(identify, readings, batch=True,
                         integrator="trapezoidal")["summary"]["integrator"] == "trapezoidal"
    with pytest.raises(mbfg.InvalidArgument, match="integrator"):
        mbfg.estimate(state, readings, integrator="euler")
    truth = mbfg.simulate(str(root / "estimation" / "fourbar.yaml"), dt=1e-3, t_end=0.5)
    readings = mbfg.measure(str(root / "estimation" / "fourbar.yaml"), truth, seed=1, rate=200)
    online = mbfg.Estimator(state, 0.005, integrator="hermite-simpson")
    for t, enc in zip(readings["t"][:20], readings["enc"][:20]):
        step = online.update(float(t), {"enc": float(enc)})
    assert np.all(np.isfinite(step["q"])) and np.all(np.isfinite(step["sd_q"]))
    with pytest.raises(mbfg.InvalidArgument, match="integrator"):
        mbfg.Estimator(state, 0.005, integrator="rk4")


def test_readings_between_steps_are_taken_at_their_own_times():
    # A logger whose 5 ms readings jitter by up to 1.5 ms: estimate() takes each at
    # its nearest step and says so in the summary; the online estimator does the
    # same, and an update nearest a step already updated is refused by name.
    import pathlib
    root = pathlib.Path(__file__).resolve().parents[2] / "scenes" / "estimation"
    truth = mbfg.simulate(str(root / "fourbar.yaml"), dt=5e-4, t_end=1.0)
    every = mbfg.measure(str(root / "fourbar.yaml"), truth, seed=2)
    jitter = [0, 3, 1, -2, -3, 2, -1, 0, 2, -3]
    rows = [10 * k + (jitter[k % 10] if 0 < k < 100 else 0) for k in range(101)]
    readings = {c: [float(every[c][i]) for i in rows] for c in ("t", "enc", "gyro")}
    out = mbfg.estimate(str(root / "fourbar-bad.yaml"), readings)
    s = out["summary"]
    assert abs(s["dt"] - 0.005) < 1e-12
    assert s["readings_between_steps"] > 0 and abs(s["largest_offset"] - 1.5e-3) < 1e-9
    assert np.all(np.isfinite(out["q:theta"]))
    on_grid = {c: [float(every[c][10 * k]) for k in range(101)] for c in ("t", "enc", "gyro")}
    assert mbfg.estimate(str(root / "fourbar-bad.yaml"), on_grid)["summary"]["readings_between_steps"] == 0
    online = mbfg.Estimator(str(root / "fourbar-bad.yaml"), 0.005)
    for t, enc, gyro in zip(readings["t"][:30], readings["enc"][:30], readings["gyro"][:30]):
        step = online.update(t, {"enc": enc, "gyro": gyro})
    assert np.all(np.isfinite(step["q"]))
    with pytest.raises(mbfg.InvalidArgument, match="already holds"):
        online.update(readings["t"][29] + 1e-3, {"enc": readings["enc"][29]})


def test_a_start_far_from_the_first_reading(tmp_path):
    # The friction pendulum drawn at 3 rad while its record starts at 0.37, the start
    # left to the default priors: the first solve begins at the first reading, in the
    # batch estimate and in the online estimator's first update.
    import math
    import pathlib
    root = pathlib.Path(__file__).resolve().parents[2] / "scenes" / "identification"
    text = (root / "pendulum-friction-bad.yaml").read_text()
    text = text.replace("{name: P, x: 0.9320390859672263, y: 0.36235775447667357}",
                        f"{{name: P, x: {math.cos(3.0)!r}, y: {math.sin(3.0)!r}}}")
    text = text.replace("  initial_sigma: {theta: 1e-6}\n", "")
    text = text.replace("  initial_velocity_sigma: {theta: 1e-6}\n", "")
    far = tmp_path / "far.yaml"
    far.write_text(text)
    truth = mbfg.simulate(str(root / "pendulum-friction.yaml"), dt=1e-3, t_end=2.0)
    readings = mbfg.measure(str(root / "pendulum-friction.yaml"), truth, seed=1)
    out = mbfg.estimate(str(far), readings, window=10)
    assert abs(out["q:theta"][0] - readings["enc"][0]) < 0.01
    online = mbfg.Estimator(str(far), 0.005, window=10)
    first = online.update(float(readings["t"][0]), {"enc": float(readings["enc"][0])})
    assert abs(first["q"][list(online.names).index("theta")] - readings["enc"][0]) < 0.01


def test_a_motion_too_fast_for_the_readings_period(tmp_path):
    # A 1 cm link whipped by a stiff spring, read at 200 Hz: at the readings' period the
    # estimate fails and says to step finer; at the step it suggests, it holds.
    import pathlib
    root = pathlib.Path(__file__).resolve().parents[2] / "scenes"
    text = (root / "hard" / "mixed-scale-pendulum.yaml").read_text() + "sensors:\n" + "".join(
        f"  - {{name: enc{c}, type: encoder, coordinate: {c}, sigma: 0.001, rate: 200}}\n"
        for c in ("a1", "a2", "a3"))
    scene = tmp_path / "whip.yaml"
    scene.write_text(text)
    truth = mbfg.simulate(str(scene), dt=1e-3, t_end=1.0)
    readings = mbfg.measure(str(scene), truth, seed=1)
    with pytest.raises(mbfg.SolveError, match=r"too fast for steps of the readings' period"):
        mbfg.estimate(str(scene), readings)
    out = mbfg.estimate(str(scene), readings, dt=0.001)
    assert np.all(np.isfinite(out["q:a3"]))


def test_a_batch_beyond_the_memory_is_refused_naming_the_window(tmp_path, monkeypatch):
    text = SPIN + "effects:\n  - {type: gravity, vector: [0, -9.81]}\n"
    scene = tmp_path / "spin.yaml"
    scene.write_text(text)
    run = mbfg.simulate(str(scene), dt=0.01, t_end=3.0)
    readings = {"t": list(run.column("t")), "gyro": list(run.column("dq:th"))}
    monkeypatch.setenv("MBFG_MEMORY_LIMIT", "1e5")
    with pytest.raises(mbfg.InvalidArgument, match=r"a batch estimate of 301 steps .* window=N in Python"):
        mbfg.estimate(str(scene), readings, batch=True)
    # The fixed-lag estimate the error names runs in that memory.
    assert mbfg.estimate(str(scene), readings)["summary"]["steps"] == 301


def test_the_online_estimator_finds_the_motion_again_after_a_long_gap():
    # The benchmark four-bar's crank encoder read for 0.25 s, then for nothing over
    # 100 s, then again: the online estimator crosses the gap (its priors keep a floor
    # of information) and its first update after it begins at the readings.
    import math
    import pathlib
    scene = pathlib.Path(__file__).resolve().parents[2] / "scenes" / "estimation" / "fourbar.yaml"
    truth = mbfg.simulate(str(scene), dt=1e-3, t_end=100.75)
    readings = mbfg.measure(str(scene), truth, seed=1, rate=200)
    online = mbfg.Estimator(str(scene), 0.005)
    theta = list(online.names).index("theta")
    last = None
    for t, enc in zip(readings["t"], readings["enc"]):
        if 0.25 <= t <= 100.25:
            continue
        last = online.update(float(t), {"enc": float(enc)})
    true_theta = truth.column("q:theta")[-1]
    off = math.remainder(last["q"][theta] - true_theta, 2 * math.pi)
    assert abs(off) < math.radians(1), off
