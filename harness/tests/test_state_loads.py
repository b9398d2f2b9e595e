"""Loads that depend on the state, from Python: scene expressions (`rate(theta)`,
`vx(P2)`, …) that IDA follows, and controllers written as Python callables (`effects=`).
exudyn and Pinocchio on such scenes: test_peers.py."""

import json
import pathlib
import subprocess
import sys

import numpy as np
import pytest

import mbfg

ROOT = pathlib.Path(__file__).resolve().parents[2]
CONTROLLED = ROOT / "scenes/driven/controlled-crank-rocker.yaml"
COMPRESSOR = ROOT / "scenes/driven/compressor-slider-crank.yaml"


def compare(tmp_path, scene, dt, tools="mbfg,mbfg-ic,ida"):
    out = tmp_path / f"{scene.stem}-{dt:g}"
    r = subprocess.run([sys.executable, "-m", "harness.compare", str(scene), "--tools", tools,
                        "--t-end", "2", "--dt", str(dt), "--out", str(out)],
                       cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    return {t["tool"]: t for t in json.loads((out / "compare.json").read_text())["tools"]}


@pytest.mark.parametrize("scene", [CONTROLLED, COMPRESSOR], ids=lambda p: p.stem)
def test_state_dependent_scenes_match_ida_at_second_order(tmp_path, scene):
    fine = compare(tmp_path, scene, 1e-4)
    coarse = compare(tmp_path, scene, 1e-3, tools="mbfg,mbfg-ic,ida")
    for tool in ("mbfg", "mbfg-ic"):
        assert fine[tool]["status"] == "ok", fine[tool]
        assert fine[tool]["rmse_m"] <= 5e-6, fine[tool]
        assert fine[tool]["max_abs_phi"] <= 1e-9
        ratio = coarse[tool]["rmse_m"] / fine[tool]["rmse_m"]
        assert 50 <= ratio <= 200, (tool, ratio)


def test_effects_say_which_depend_on_the_state():
    model = mbfg.load(CONTROLLED)
    kinds = {e.get("name"): e.get("state_dependent") for e in model.effects}
    assert kinds == {None: None, "controller": True, "drag": True}
    with pytest.raises(mbfg.InvalidArgument, match="depends on the state"):
        model.effect_value(1, 0.0)
    plain = mbfg.load(ROOT / "scenes/driven/slider-crank-docs.yaml")
    assert all(not e.get("state_dependent") for e in plain.effects)


def test_force_jacobians_are_the_derivatives_of_the_forces():
    model = mbfg.load(COMPRESSOR)
    rng = np.random.default_rng(3)
    q = model.initial_q + 0.1 * rng.standard_normal(len(model.names))
    dq = rng.standard_normal(len(model.names))
    kq, kv = model.force_jacobians(q, dq, 0.2)
    h = 1e-6
    for j in range(len(q)):
        e = np.eye(len(q))[j]
        fq = (model.generalized_forces(q + h * e, dq, 0.2) - model.generalized_forces(q - h * e, dq, 0.2)) / (2 * h)
        fv = (model.generalized_forces(q, dq + h * e, 0.2) - model.generalized_forces(q, dq - h * e, 0.2)) / (2 * h)
        np.testing.assert_allclose(kq[:, j], fq, rtol=1e-6, atol=1e-6)
        np.testing.assert_allclose(kv[:, j], fv, rtol=1e-6, atol=1e-6)


def without_controller(tmp_path):
    text = CONTROLLED.read_text()
    lines = [l for l in text.splitlines() if "name: controller" not in l]
    assert len(lines) == len(text.splitlines()) - 1
    path = tmp_path / "uncontrolled.yaml"
    path.write_text("\n".join(lines) + "\n")
    return mbfg.load(path)


@pytest.mark.parametrize("coords", ["dc", "ic"])
def test_a_python_controller_is_the_scene_expression(tmp_path, coords):
    model = without_controller(tmp_path)
    i, n = model.index("theta"), len(model.names)
    kp, kd, w = 400.0, 40.0, 2 * np.pi
    calls = []

    def controller(t, q, dq):
        calls.append(t)
        assert isinstance(q, np.ndarray) and q.shape == (n,) and dq.shape == (n,)
        Q = np.zeros(n)
        Q[i] = kp * (w * t - q[i]) + kd * (w - dq[i])
        return Q

    run = mbfg.simulate(model, coords=coords, dt=1e-3, t_end=1.0,
                        effects={"controller": controller})
    written = mbfg.simulate(CONTROLLED, coords=coords, dt=1e-3, t_end=1.0)
    assert np.abs(run.q - written.q).max() <= 1e-10
    assert np.abs(run.dq - written.dq).max() <= 1e-9
    assert len(calls) > run.q.shape[0]


def test_a_python_controller_runs_in_inverse_dynamics(tmp_path):
    model = without_controller(tmp_path)
    i, n = model.index("theta"), len(model.names)
    t = np.linspace(0, 1, 201)
    motion = {"t": t, "theta": 2 * np.pi * t}
    plain = mbfg.inverse(model, motion)
    # A constant external torque of 5 N·m on theta: the actuator gives 5 N·m less.
    helped = mbfg.inverse(model, motion, effects={"help": lambda t, q, dq: 5.0 * np.eye(n)[i]})
    key = [c for c in plain.columns if c.startswith("Q:") and "theta" in c][0]
    diff = plain.column(key) - helped.column(key)
    np.testing.assert_allclose(diff, 5.0, atol=1e-8)


def test_a_controller_that_raises_stops_the_run_with_its_exception(tmp_path):
    model = without_controller(tmp_path)
    n = len(model.names)

    def lost(t, q, dq):
        if t > 0.25:
            raise ValueError("encoder lost")
        return np.zeros(n)

    with pytest.raises(ValueError, match="encoder lost") as info:
        mbfg.simulate(model, dt=1e-3, t_end=1.0, effects={"sensor": lost})
    partial = info.value.result
    assert partial is not None and 0.2 < partial.t[-1] <= 0.25 + 1e-12


@pytest.mark.parametrize("effects, message", [
    ({"short": lambda t, q, dq: [0.0]}, "returned 1 values"),
    ({"nan": lambda t, q, dq: [float("nan")] * 5}, r"returned NaN for coordinate 0 \(P1.x\)"),
    ({"drag": lambda t, q, dq: [0.0] * 5}, "already has an effect named 'drag'"),
    ({"x": 3}, "must be a callable"),
    ([1, 2], "must be a dict"),
])
def test_bad_effects_are_named(tmp_path, effects, message):
    model = without_controller(tmp_path)
    with pytest.raises((mbfg.InvalidArgument, mbfg.SolveError), match=message):
        mbfg.simulate(model, dt=1e-3, t_end=0.1, effects=effects)
