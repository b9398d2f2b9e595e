"""The integrator choice from Python: Hermite–Simpson is fourth order where the
trapezoidal rule is second, and an unknown name is refused with the choices."""

import pathlib

import pytest

import mbfg
from harness import pages

ROOT = pathlib.Path(__file__).resolve().parents[2]


def error(integrator, dt, coords="dc", scene="fourbar"):
    truth, _ = pages.load_reference(scene)
    r = mbfg.simulate(pages.scene_path(scene), coords=coords, dt=dt, t_end=1.0,
                      integrator=integrator)
    return pages.errors(mbfg.load(pages.scene_path(scene)), r.t, r.q, truth)[0]


@pytest.mark.parametrize("coords, scene", [("dc", "fourbar"), ("ic", "fourbar-theta")])
def test_hermite_simpson_is_fourth_order_and_the_trapezoidal_rule_second(coords, scene):
    hs = error("hermite-simpson", 4e-3, coords, scene) / error("hermite-simpson", 2e-3, coords, scene)
    tr = error("trapezoidal", 4e-3, coords, scene) / error("trapezoidal", 2e-3, coords, scene)
    assert 14 <= hs <= 18, hs
    assert 3.5 <= tr <= 4.5, tr
    assert error("hermite-simpson", 1e-3, coords, scene) <= 1e-9


def test_an_unknown_integrator_names_the_choices():
    with pytest.raises(mbfg.InvalidArgument, match="hermite-simpson"):
        mbfg.simulate(ROOT / "scenes/fourbar.yaml", dt=1e-3, t_end=0.01, integrator="rk4")
