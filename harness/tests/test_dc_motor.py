"""A load that depends on the state: the DC motor (torque T_s (1 − ω/ω₀) as one
effect) spins the crank-rocker up from rest, and mbfg follows IDA's solution of the
same scene, second order in dt."""

import json
import pathlib
import subprocess
import sys

import pytest

import mbfg

ROOT = pathlib.Path(__file__).resolve().parents[2]
SCENE = ROOT / "scenes/driven/dc-motor-crank-rocker.yaml"


def compare(tmp_path, dt):
    out = tmp_path / f"dt{dt:g}"
    r = subprocess.run([sys.executable, "-m", "harness.compare", str(SCENE), "--tools",
                        "mbfg,mbfg-ic,ida", "--t-end", "2", "--dt", str(dt), "--out", str(out)],
                       cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    tools = json.loads((out / "compare.json").read_text())["tools"]
    return {t["tool"]: t for t in tools}


def test_the_motor_is_one_effect_whose_torque_falls_with_speed():
    model = mbfg.load(SCENE)
    motor = [e for e in model.effects if e["type"] == "dc_motor"]
    assert motor == [{"type": "dc_motor", "name": "motor", "coordinate": "theta",
                      "stall_torque": 60.0, "no_load_speed": 30.0}]
    i = model.index("theta")
    q, dq = model.initial_q, model.initial_dq.copy()
    # Gravity acts on the points: on theta, the motor's torque alone.
    for w in (0.0, 15.0, 30.0, 45.0):
        dq[i] = w
        assert model.generalized_forces(q, dq, 0.0)[i] == pytest.approx(60 * (1 - w / 30))


def test_the_driven_crank_rocker_matches_ida(tmp_path):
    fine, coarse = compare(tmp_path, 1e-4), compare(tmp_path, 1e-3)
    for tool in ("mbfg", "mbfg-ic"):
        assert fine[tool]["status"] == "ok"
        assert fine[tool]["rmse_m"] <= 5e-6, fine[tool]
        assert fine[tool]["max_abs_phi"] <= 1e-9
    # Second order: ten times the step, a hundred times the error (IC; DC falls faster).
    ratio = coarse["mbfg-ic"]["rmse_m"] / fine["mbfg-ic"]["rmse_m"]
    assert 60 <= ratio <= 160, ratio
    r = mbfg.simulate(SCENE, dt=1e-3, t_end=3.0)
    # Spun up from rest to near the speed where the motor's torque balances the losses.
    w = r.column("dq:theta")
    assert w[0] == 0.0 and 20 < w[-1] < 30
