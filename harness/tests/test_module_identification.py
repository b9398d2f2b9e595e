"""mbfg.estimate identifies scene parameters from Python: the spring and damper of
tests/data/identification/spring-damper-kc.yaml from the readings of its true scene
(scenes/spring-damper.yaml), with σ's, correlations and the identifiability verdict;
and the mass and inertia of a pendulum, which the readings cannot tell apart, named."""

import pathlib

import numpy as np
import pytest

mbfg = pytest.importorskip("mbfg")

ROOT = pathlib.Path(__file__).resolve().parents[2]
DATA = ROOT / "tests" / "data" / "identification"


def _readings(true_scene, t_end, sigma, seed):
    run = mbfg.simulate(str(true_scene), dt=0.005, t_end=t_end)
    rng = np.random.default_rng(seed)
    theta = run.column("q:theta")
    return {"t": list(run.column("t")), "enc": list(theta + sigma * rng.standard_normal(len(theta)))}


def test_stiffness_and_damping_come_out_with_their_sigmas():
    readings = _readings(ROOT / "scenes" / "spring-damper.yaml", 4.0, 1e-3, 1)
    out = mbfg.estimate(str(DATA / "spring-damper-kc.yaml"), readings, batch=True)
    assert out["parameter_names"] == ["k", "c"]
    for name, truth in [("k", 20.0), ("c", 0.5)]:
        p = out["parameters"][name]
        assert p["identifiable"] and p["reason"] == ""
        assert abs(p["estimate"] - truth) < 3 * p["sigma"], (name, p)
        assert p["sigma"] < 0.1 * p["prior_sigma"]
        # The per-step columns end where the summary's estimate is.
        assert out[f"p:{name}"][-1] == pytest.approx(p["estimate"], rel=1e-9)
    corr = out["parameter_correlation"]
    assert corr.shape == (2, 2) and np.allclose(np.diag(corr), 1.0)


def test_mass_and_inertia_about_a_pivot_are_named_together():
    readings = _readings(DATA / "pendulum-true.yaml", 3.0, 1e-3, 2)
    out = mbfg.estimate(str(DATA / "pendulum-mass-inertia.yaml"), readings, batch=True)
    for name, other in [("m", "i_rod"), ("i_rod", "m")]:
        p = out["parameters"][name]
        assert not p["identifiable"]
        assert "combination" in p["reason"] and other in p["reason"]


def test_the_online_estimator_gives_the_parameters_apart_from_the_inputs():
    # spring-damper.yaml identifies k and c and declares an unknown input on theta:
    # each update's Q holds the input only, p the two parameters.
    readings = _readings(ROOT / "scenes" / "spring-damper.yaml", 1.0, 1e-3, 3)
    est = mbfg.Estimator(str(DATA / "spring-damper.yaml"), dt=0.005, window=10)
    for t, enc in zip(readings["t"], readings["enc"]):
        out = est.update(t, {"enc": enc})
    assert len(out["Q"]) == 1 and len(out["sd_Q"]) == 1
    assert len(out["p"]) == 2 and len(out["sd_p"]) == 2
    # The parameters stay near their prior within a second of readings, with σ's.
    assert abs(out["p"][0] - 18.0) < 3 * 5.0 and out["sd_p"][0] > 0
