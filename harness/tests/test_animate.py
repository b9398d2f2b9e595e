"""The mechanism in motion: mbfg.animate and `mbfg animate` write a GIF with one frame
per 1/fps s of motion, and refuse a run that does not belong to the scene."""

import os
import pathlib
import subprocess
import sys

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


def test_animate_needs_a_model_or_a_simulated_result():
    with pytest.raises(mbfg.InvalidArgument, match="model"):
        mbfg.animate(object())
