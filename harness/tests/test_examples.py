"""The scripts in examples/python run as printed and write what they say."""

import pathlib
import subprocess
import sys

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[2]
EXPECTED = {
    "parameter_sweep.py": ["sweep.png"],
    "joint_forces.py": ["pins.png"],
    "energy_and_animation.py": ["energy.png", "swing.gif"],
    "controller.py": ["controller.png"],
}


def test_every_example_is_tested():
    assert {p.name for p in (ROOT / "examples/python").glob("*.py")} == set(EXPECTED)


@pytest.mark.parametrize("script", sorted(EXPECTED))
def test_example_runs(script, tmp_path):
    r = subprocess.run([sys.executable, ROOT / "examples/python" / script, tmp_path],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr[-2000:]
    for name in EXPECTED[script]:
        assert (tmp_path / name).stat().st_size > 1000, name
