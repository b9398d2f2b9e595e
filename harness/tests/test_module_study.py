"""Parameter studies from Python without writing a file: parameter and initial-state
overrides, a loaded Model as the scene, and a sweep of 100 runs."""

import pathlib

import numpy as np
import pytest

import mbfg

ROOT = pathlib.Path(__file__).resolve().parents[2]
SPRING = ROOT / "scenes/spring-damper.yaml"
PENDULUM = ROOT / "scenes/pendulum.yaml"


def test_a_sweep_of_100_runs_over_a_parameter():
    angles = np.linspace(-1.2, 1.2, 100)
    ends = []
    for a in angles:
        r = mbfg.simulate(SPRING, dt=0.01, t_end=0.2, params={"th0": float(a)})
        assert r.summary["complete"]
        ends.append(r.q[0])
    # The parameter reached the placement: each run starts where its th0 puts the tip.
    th = np.array([np.arctan2(q[1], q[0]) for q in ends])
    assert np.allclose(th, angles, atol=1e-9)


def test_overridden_parameters_equal_an_edited_file(tmp_path):
    text = SPRING.read_text().replace("th0: -pi/2 + 0.5", "th0: -pi/2 + 0.3")
    edited = tmp_path / "spring-damper.yaml"
    edited.write_text(text)
    a = mbfg.simulate(SPRING, dt=0.01, t_end=0.5, params={"th0": -np.pi / 2 + 0.3})
    b = mbfg.simulate(edited, dt=0.01, t_end=0.5)
    assert np.array_equal(a.data, b.data)


def test_initial_state_overrides_equal_an_edited_file(tmp_path):
    text = PENDULUM.read_text() + "initial:\n  positions: {theta: -0.7}\n  velocities: {theta: 2.5}\n"
    edited = tmp_path / "pendulum.yaml"
    edited.write_text(text)
    a = mbfg.simulate(PENDULUM, dt=0.01, t_end=0.5, q0={"theta": -0.7}, dq0={"theta": 2.5})
    b = mbfg.simulate(edited, dt=0.01, t_end=0.5)
    assert np.array_equal(a.data, b.data)


def test_a_loaded_model_is_a_scene():
    model = mbfg.load(SPRING, params={"th0": -1.0})
    a = mbfg.simulate(model, dt=0.01, t_end=0.3)
    b = mbfg.simulate(SPRING, dt=0.01, t_end=0.3, params={"th0": -1.0})
    assert np.array_equal(a.data, b.data)
    # Overrides on top of a loaded model re-read its file.
    c = mbfg.simulate(model, dt=0.01, t_end=0.3, params={"th0": -1.1})
    assert not np.array_equal(a.data, c.data)


@pytest.mark.parametrize("kw, exc, words", [
    ({"params": {"no_such": 1.0}}, mbfg.SceneError, "no parameter 'no_such' to override"),
    ({"params": {"th0": float("nan")}}, mbfg.InvalidArgument, "finite"),
    ({"params": [("th0", 1.0)]}, mbfg.InvalidArgument, "params must be a dict"),
    ({"q0": {"nope": 1.0}}, mbfg.InvalidArgument, "no coordinate 'nope'"),
    ({"dq0": {"P.x": 1.0}}, mbfg.InvalidArgument, "not an independent coordinate"),
])
def test_bad_overrides_are_named(kw, exc, words):
    with pytest.raises(exc, match=words):
        mbfg.simulate(SPRING, dt=0.01, t_end=0.1, **kw)
