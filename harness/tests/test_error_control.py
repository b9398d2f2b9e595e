"""Error-controlled steps from Python (`rtol=`, `atol=`): a tolerance gives its
accuracy on the double pendulum, the rows stay on the grid of dt, the summary says
what the control did, and bad values are refused by name."""

import numpy as np
import pytest

import mbfg
from harness import pages


@pytest.mark.parametrize("rtol", [1e-4, 1e-8])
def test_a_tolerance_gives_its_accuracy_on_the_double_pendulum(rtol):
    truth, _ = pages.load_reference("double-pendulum")
    scene = pages.scene_path("double-pendulum")
    r = mbfg.simulate(scene, dt=1e-3, t_end=5.0, integrator="hermite-simpson", rtol=rtol)
    rmse = pages.errors(mbfg.load(scene), r.t, r.q, truth)[0]
    assert rtol / 10 <= rmse <= 10 * rtol, (rtol, rmse)
    c = r.summary["error_control"]
    assert c["rtol"] == rtol and c["atol"] == rtol
    assert c["accepted"] > 0 and c["smallest_step"] <= c["largest_step"]
    # The rows checked (the default scope): their estimated error, and the runs made.
    assert c["estimated_error"] is not None and c["estimated_error"] <= 1.0
    assert c["step_rtols"][0] == rtol and c["unchecked"] is None
    assert r.summary["complete"]
    assert len(r.t) == 5001
    np.testing.assert_allclose(r.t, np.arange(5001) * 1e-3, atol=1e-12)


def test_a_tolerance_on_the_steps_is_one_run_unchecked():
    r = mbfg.simulate(pages.scene_path("double-pendulum"), dt=1e-3, t_end=1.0,
                      integrator="hermite-simpson", rtol=1e-6, tolerance_scope="steps")
    c = r.summary["error_control"]
    assert c["estimated_error"] is None and c["step_rtols"] is None


def test_without_rtol_there_is_no_error_control():
    r = mbfg.simulate(pages.scene_path("fourbar"), dt=1e-2, t_end=0.1)
    assert r.summary["error_control"] is None


@pytest.mark.parametrize("kwargs, name", [
    ({"rtol": 0.0}, "rtol"),
    ({"rtol": -1e-6}, "rtol"),
    ({"rtol": float("nan")}, "rtol"),
    ({"rtol": "tight"}, "rtol"),
    ({"rtol": 1e-6, "atol": 0.0}, "atol"),
    ({"atol": 1e-6}, "atol"),
    ({"rtol": 1e-6, "window": 5}, "window"),
    ({"rtol": 1e-6, "batch": True}, "batch"),
    ({"rtol": 1e-6, "tolerance_scope": "rows"}, "tolerance_scope"),
    ({"rtol": 1e-6, "tolerance_scope": 3}, "tolerance_scope"),
])
def test_bad_tolerances_are_refused_by_name(kwargs, name):
    with pytest.raises(mbfg.InvalidArgument, match=name):
        mbfg.simulate(pages.scene_path("fourbar"), dt=1e-3, t_end=0.1, **kwargs)
