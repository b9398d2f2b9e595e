"""The harness's own reading of a scene file (harness/scene_file.py): it agrees with
mbfg's on every scene of the repository, and a quantity mbfg reads differently refuses
the scene, named."""
from __future__ import annotations

import pathlib

import numpy as np
import pytest

import mbfg
from harness import coverage
from harness.scene_file import Mismatch, SceneFile

ROOT = pathlib.Path(__file__).resolve().parents[2]


@pytest.mark.parametrize("path", coverage.scenes(), ids=lambda p: str(p.relative_to(ROOT)))
def test_every_scene_reads_as_mbfg_reads_it(path):
    SceneFile(path).check(mbfg.load(str(path)))


class Misread:
    """An mbfg model with one quantity read wrongly."""

    def __init__(self, model, **override):
        self._model, self._override = model, override

    def __getattr__(self, name):
        return self._override.get(name, getattr(self._model, name))


def altered(items, k, **changes):
    out = [dict(d) for d in items]
    out[k].update(changes)
    return out


@pytest.mark.parametrize("scene, what, field, change, message", [
    ("slider-crank.yaml", "bodies", 1, {"inertia_cog": 0.0501}, "body rod inertia about its centre of mass"),
    ("fourbar.yaml", "bodies", 0, {"cog": (0.5, 0.001)}, "body crank centre of mass"),
    ("slider-crank.yaml", "points", 3, {"mass": 0.6}, "point S mass"),
    ("hard/redundant-fourbar.yaml", "constraints", 0, {"length": 2.001}, "constraint coupler-again length"),
    ("spring-damper.yaml", "effects", 1, {"stiffness": 20.2}, "stiffness"),
])
def test_a_quantity_mbfg_reads_differently_is_named(scene, what, field, change, message):
    path = ROOT / "scenes" / scene
    model = mbfg.load(str(path))
    wrong = Misread(model, **{what: altered(getattr(model, what), field, **change)})
    with pytest.raises(Mismatch, match=message):
        SceneFile(path).check(wrong)


def test_an_initial_state_off_the_files_geometry_is_named():
    path = ROOT / "scenes" / "slider-crank.yaml"
    model = mbfg.load(str(path))
    q0 = np.array(model.initial_q)
    q0[model.names.index("S.y")] += 1e-4        # the block off its guide
    with pytest.raises(Mismatch, match="slider guide: S is .* off its line"):
        SceneFile(path).check(Misread(model, initial_q=q0))
    dq0 = np.array(model.initial_dq)
    dq0[model.names.index("theta")] += 0.01
    with pytest.raises(Mismatch, match="initial velocity of theta"):
        SceneFile(path).check(Misread(model, initial_dq=dq0))


def test_a_time_load_mbfg_evaluates_differently_is_named():
    path = ROOT / "scenes" / "driven" / "slider-crank-docs.yaml"
    model = mbfg.load(str(path))
    k = next(i for i, e in enumerate(model.effects) if e["type"] == "torque")

    def value(i, t):
        v = model.effect_value(i, t)
        return v * (1 - 1e-6) if i == k else v
    with pytest.raises(Mismatch, match="value at t"):
        SceneFile(path).check(Misread(model, effect_value=value))


def test_coverage_page_names_each_scene_and_its_peers(tmp_path):
    paths = [ROOT / "scenes" / "pendulum.yaml", ROOT / "scenes" / "pick-and-place.yaml"]
    rows = coverage.write(tmp_path, t_end=0.05, dt=1e-3, paths=paths)
    page = (tmp_path / "coverage.md").read_text()
    assert "**2 of 2 scenes** are checked by an independent simulator." in page
    assert rows[0]["verdict"] == "checked by exudyn, pinocchio"
    # exudyn refuses the robot's redundant rigid-body equations; Pinocchio checks it.
    assert rows[1]["exudyn_status"] == "refused" and rows[1]["pinocchio_status"] == "agrees"
    assert "| scenes/pick-and-place.yaml |" in page and "refused: redundant" in page
