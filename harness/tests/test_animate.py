"""The mechanism in motion: mbfg.animate and `mbfg animate` write a GIF with one frame
per 1/fps s of motion, and refuse a run that does not belong to the scene."""

import os
import pathlib
import subprocess
import sys
import types

import numpy as np
import pytest
from PIL import Image

import mbfg

ROOT = pathlib.Path(__file__).resolve().parents[2]
MBFG = ROOT / "target/release/mbfg"


def test_animate_a_result(tmp_path):
    r = mbfg.simulate(ROOT / "scenes/fourbar.yaml", dt=1e-3, t_end=1.0)
    out = mbfg.animate(r, out=tmp_path / "fourbar.gif", fps=20, trail="P2")
    with Image.open(out) as im:
        assert im.n_frames == 21
        assert im.size[0] > 100


def test_animate_from_the_command_line(tmp_path):
    csv = tmp_path / "run.csv"
    scene = ROOT / "scenes/slider-crank.yaml"
    subprocess.run([MBFG, "simulate", scene, "--dt", "0.002", "--t-end", "0.5", "--out", csv],
                   check=True, capture_output=True)
    env = {**os.environ, "MBFG_PYTHON": sys.executable}
    r = subprocess.run([MBFG, "animate", csv, "--scene", scene, "--fps", "10"], env=env,
                       capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    with Image.open(tmp_path / "run.gif") as im:
        assert im.n_frames == 6
    # A run of another scene: one error line, exit 2.
    r = subprocess.run([MBFG, "animate", csv, "--scene", ROOT / "scenes/fourbar.yaml"], env=env,
                       capture_output=True, text=True)
    assert r.returncode == 2 and r.stderr.startswith("error: ") and r.stderr.count("\n") == 1, r.stderr


@pytest.mark.parametrize("damage, says", [
    (None, "No such file"),
    ("nan", ":4: column `q:P.x`: nan is not finite"),
    ("abc", ":4: column `q:P.x`"),
])
def test_animate_names_a_bad_run_as_mbfg_does(tmp_path, damage, says):
    # A missing file, a row that is not a number: mbfg's own message (file, row,
    # column), one line, exit 2 — not Python's.
    scene = ROOT / "scenes/pendulum.yaml"
    csv = tmp_path / "run.csv"
    subprocess.run([MBFG, "simulate", scene, "--dt", "0.01", "--t-end", "0.05", "--out", csv],
                   check=True, capture_output=True)
    if damage is None:
        csv = tmp_path / "missing.csv"
    else:
        rows = csv.read_text().splitlines()
        cells = rows[3].split(",")
        cells[1] = damage
        rows[3] = ",".join(cells)
        csv.write_text("\n".join(rows) + "\n")
    env = {**os.environ, "MBFG_PYTHON": sys.executable}
    r = subprocess.run([MBFG, "animate", csv, "--scene", scene, "--out", tmp_path / "a.gif"],
                       env=env, capture_output=True, text=True)
    assert r.returncode == 2 and r.stderr.count("\n") == 1, r.stderr
    assert r.stderr.startswith("error: ") and says in r.stderr, r.stderr
    assert "Errno" not in r.stderr and "could not convert" not in r.stderr


def test_animate_needs_a_model_or_a_simulated_result():
    run = types.SimpleNamespace(t=[0.0], q=[[0.0]])
    with pytest.raises(mbfg.InvalidArgument, match="model"):
        mbfg.animate(run)
    with pytest.raises(mbfg.InvalidArgument, match="model: expected a Model or a scene path, got int"):
        mbfg.animate(run, 3)


def test_animate_names_arguments_given_in_the_wrong_place(tmp_path):
    scene = ROOT / "scenes/pendulum.yaml"
    with pytest.raises(mbfg.InvalidArgument, match="result: expected the Result of mbfg.simulate.*got str"):
        mbfg.animate(str(scene), mbfg.simulate(scene, dt=0.01, t_end=0.1))


def test_animate_takes_the_scene_as_a_path(tmp_path):
    scene = ROOT / "scenes/pendulum.yaml"
    r = mbfg.simulate(scene, dt=0.01, t_end=0.4)
    out = mbfg.animate(r, str(scene), tmp_path / "p.gif", fps=10)
    with Image.open(out) as im:
        assert im.n_frames == 5


def test_animate_draws_forces_guides_and_a_turning_crank(tmp_path):
    # A crank driven to speed: its speed is on the label; the ground reactions as arrows.
    r = mbfg.simulate(ROOT / "scenes/driven/dc-motor-crank-rocker.yaml", dt=1e-3, t_end=1.0)
    out = mbfg.animate(r, out=tmp_path / "motor.gif", fps=10, forces=True)
    with Image.open(out) as im:
        assert im.n_frames == 11
    # A slider's fixed guide runs across the whole view: grey in the frame's first
    # column of the axes at the guide's height, which no body reaches.
    r = mbfg.simulate(ROOT / "scenes/slider-crank.yaml", dt=1e-3, t_end=0.2)
    out = mbfg.animate(r, out=tmp_path / "slider.gif", fps=10)
    with Image.open(out) as im:
        frame = np.asarray(im.convert("RGB")).astype(int)
    grey = (np.abs(frame - frame[..., :1]).max(axis=2) < 8) & (frame[..., 0] > 150) & (frame[..., 0] < 240)
    # A horizontal band of grey, as wide as most of the axes.
    assert grey.sum(axis=1).max() > 0.5 * frame.shape[1]


def test_animate_forces_need_velocities_and_accelerations():
    r = mbfg.simulate(ROOT / "scenes/pendulum.yaml", dt=1e-2, t_end=0.1)

    class Positions:
        t, q = r.t, r.q
    with pytest.raises(mbfg.InvalidArgument, match="forces: the result needs dq and ddq"):
        mbfg.animate(Positions(), model=mbfg.load(ROOT / "scenes/pendulum.yaml"), forces=True)


def test_animate_forces_from_the_command_line(tmp_path):
    csv = tmp_path / "run.csv"
    scene = ROOT / "scenes/pendulum.yaml"
    subprocess.run([MBFG, "simulate", scene, "--dt", "0.01", "--t-end", "0.3", "--out", csv],
                   check=True, capture_output=True)
    env = {**os.environ, "MBFG_PYTHON": sys.executable}
    r = subprocess.run([MBFG, "animate", csv, "--scene", scene, "--fps", "10", "--forces"],
                       env=env, capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    with Image.open(tmp_path / "run.gif") as im:
        assert im.n_frames == 4
