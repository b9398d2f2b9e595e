"""mbfg.inverse(..., sample_sigma=...) on the paper's four-bar: 8-digit samples and
1e-4 rad noise against the classical torque of the exact motion (harness.inverse_measured),
the σ columns, and bad values refused."""
import numpy as np
import pytest

import mbfg
from harness import inverse_measured as im


@pytest.fixture(scope="module")
def case():
    model = mbfg.load(im.SCENE)
    t = np.arange(round(im.T_END / im.DT) + 1) * im.DT
    return t, im.crank(t)[0], im.classical_torque(model, t)


def test_eight_digit_samples(case):
    t, th, truth = case
    eight = np.array([float(f"{v:.8g}") for v in th])
    raw = im.stats(im.run(t, eight, truth, None))
    res = im.run(t, eight, truth, "auto")
    s = im.stats(res)
    assert raw["rms"] > 5e-3 and raw["lag1"] < -0.5          # today's differences
    assert s["rms"] <= 5e-4 and s["lag1"] > -0.2
    assert s["within"] >= 0.9
    fit = res["smoothing"][0]
    assert fit["from_data"] and fit["noise"] == "rounding" and fit["digits"] == 8


def test_noisy_samples_seed_1(case):
    t, th, truth = case
    y = th + im.NOISE * np.random.default_rng(1).standard_normal(len(t))
    assert im.stats(im.run(t, y, truth, None))["rms"] > 1.0
    for sigma in (im.NOISE, {"theta": im.NOISE}, "auto"):
        s = im.stats(im.run(t, y, truth, sigma))
        assert s["rms"] <= 0.05 and s["within"] >= 0.9, (sigma, s)


def test_without_sample_sigma_no_sd_columns_and_bad_values(case):
    t, th, _ = case
    r = mbfg.inverse(im.SCENE, {"t": t[:50], "theta": th[:50]})
    assert not any(c.startswith("sd:") for c in r.columns) and r.summary["smoothing"] is None
    r = mbfg.inverse(im.SCENE, {"t": t[:50], "theta": th[:50]}, sample_sigma=1e-6)
    assert r.columns[-1] == "sd:Q:theta" and (r.column("sd:Q:theta") > 0).all()
    for bad in ("x", {"phi": 1.0}, -1.0, True, {"theta": 0.0}):
        with pytest.raises(mbfg.InvalidArgument):
            mbfg.inverse(im.SCENE, {"t": t[:50], "theta": th[:50]}, sample_sigma=bad)


def test_samples_at_jittered_times(case):
    """Samples whose times jitter are smoothed at their own times (sample_sigma) and the
    torque read on the grid of their mean interval; without a σ they are refused."""
    t, _, truth = case
    rng = np.random.default_rng(3)
    tj = t + rng.uniform(-im.JITTER, im.JITTER, len(t))
    tj[0], tj[-1] = t[0], t[-1]
    y = im.crank(tj)[0] + im.NOISE * rng.standard_normal(len(t))
    with pytest.raises(mbfg.InvalidArgument, match="not uniformly spaced"):
        mbfg.inverse(im.SCENE, {"t": tj, "theta": y})
    r = mbfg.inverse(im.SCENE, {"t": tj, "theta": y}, sample_sigma="auto")
    assert np.allclose(r.t, t, atol=1e-12)
    lo, hi = r.summary["sample_intervals"]
    assert im.DT - 2 * im.JITTER <= lo < hi <= im.DT + 2 * im.JITTER
    err = r.column("Q:theta") - truth
    sd = r.column("sd:Q:theta")
    assert np.sqrt(np.mean(err ** 2)) <= 0.05
    assert np.mean(np.abs(err) <= 2 * sd) >= 0.9
