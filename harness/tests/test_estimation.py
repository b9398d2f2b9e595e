"""The estimation page (harness/estimation.py) end to end on a short horizon: the IDA
truth, `mbfg measure`, `mbfg estimate` on the bad four-bar, the scores and the page."""
import numpy as np
import pytest

pytest.importorskip("sksundae")
pytest.importorskip("filterpy")

from harness import estimation  # noqa: E402

if not estimation.binary().exists():
    pytest.skip(f"no mbfg binary at {estimation.binary()} (`make build`, or set MBFG)",
                allow_module_level=True)

T_END, SEED = 2.0, 1


@pytest.fixture(scope="module")
def encoder_run():
    case = estimation.CASE["encoder"]
    rpath = str(estimation.readings_path(case, SEED, T_END))
    tpath = str(estimation.truth_path(case.true_scene, T_END))
    row = estimation.run_task(("encoder", SEED, "mbfg N_w=20", T_END, rpath, tpath, True))
    ic = estimation.run_task(("encoder", SEED, "mbfg IC N_w=20", T_END, rpath, tpath, False))
    return case, row, estimation.open_loop(case, tpath), ic


def test_summary_line_is_parsed():
    s = estimation.parse_summary(
        "2001 steps (dt = 0.005 s, DC, window 50) from 2001 readings in 2.546 s (1272 µs a "
        "step); linear solves per step: mean 3.86; mean NIS 1.405 against 1.000 expected, 95 % "
        "bounds [0.939, 1.063]: NOT consistent; process σ 1 (the scene's)")
    assert s["steps"] == 2001 and s["wall_s"] == 2.546 and s["us_per_step"] == 1272
    assert (s["coords"], s["window"]) == ("DC", 50)
    assert s["nis"] == 1.405 and s["nis_expected"] == 1.0
    assert (s["nis_lo"], s["nis_hi"]) == (0.939, 1.063)
    assert s["nis_ok"] is False
    assert s["process_sigma"] == 1 and s["process_sigma_how"] == "the scene's"
    s = estimation.parse_summary(
        "2001 steps (dt = 0.005 s, IC, batch) from 2001 readings in 1.254 s (627 µs a step); "
        "linear solves per step: mean 4.78; mean NIS 1.048 against 1.000 expected, 95 % bounds "
        "[0.939, 1.063]: consistent; process σ 3 (the default)")
    assert s["steps"] == 2001 and s["us_per_step"] == 627
    assert (s["coords"], s["window"]) == ("IC", "batch")
    assert s["nis"] == 1.048 and s["nis_ok"] is True
    assert s["process_sigma"] == 3 and s["process_sigma_how"] == "the default"


def test_failure_is_short():
    status = ("mbfg estimate failed (1): error: the estimate at step 1 (t = 0.005 s) did not "
              "converge: iteration limit, cost 1.833e-1 after 203 iterations; nothing was written")
    assert (estimation.short_failure(status)
            == "step 1 (t = 0.005 s) did not converge (iteration limit)")
    assert estimation.short_failure("mbfg estimate failed (2): error: no such file") == "no such file"


def test_estimator_names():
    assert estimation.mbfg_est(50) == "mbfg N_w=50"
    assert estimation.mbfg_est("batch", "ic") == "mbfg IC batch"
    assert estimation.label("mbfg IC N_w=50") == "mbfg IC fixed-lag N_w = 50"
    assert estimation.label("mbfg N_w=20") == "mbfg fixed-lag N_w = 20 (default)"
    assert "mbfg IC N_w=50" in estimation.estimators(estimation.CASE["encoder"])


def test_readings_keep_the_case_columns():
    case = estimation.CASE["encoder"]
    path = estimation.readings_path(case, SEED, T_END)
    header = path.read_text().splitlines()[0]
    assert header == "t,enc"
    assert len(path.read_text().splitlines()) == round(T_END / estimation.DT) + 2


def test_mbfg_estimate_tracks_the_truth_from_the_bad_model(encoder_run):
    _, row, loop, _ = encoder_run
    assert row["status"] == "ok", row["status"]
    assert (row["coords"], row["window"]) == ("DC", 20)
    # Far below the bad model alone, and at the encoder's noise level or better.
    assert loop["rmse_z:theta"] > 0.1
    assert row["rmse_z:theta"] < min(1e-2, loop["rmse_z:theta"] / 50)
    assert row["rmse_dz:theta"] < loop["rmse_dz:theta"] / 10
    # Honest σ: the truth within ±2σ at most steps.
    assert row["within_2sd"] >= 0.85
    assert row["us_per_step"] > 0 and row["nis"] > 0


def test_mbfg_estimate_in_independent_coordinates(encoder_run):
    _, _, loop, ic = encoder_run
    assert ic["status"] == "ok", ic["status"]
    assert (ic["coords"], ic["window"]) == ("IC", 20)
    assert ic["rmse_z:theta"] < min(1e-2, loop["rmse_z:theta"] / 50)


def test_page_has_its_tables(encoder_run, tmp_path):
    case, row, loop, ic = encoder_run
    failed = {"case": "encoder", "seed": SEED, "estimator": "mbfg IC batch", "status":
              "mbfg estimate failed (1): error: the estimate at step 1 (t = 0.005 s) did not "
              "converge: iteration limit, cost 1.833e-1 after 203 iterations; nothing was written"}
    res = {"rows": [row, ic, failed], "open_loop": [loop], "seeds": [SEED], "sweep_seeds": [SEED],
           "sweep_windows": [20, "batch"], "sweep_windows_ic": [20, "batch"], "t_end": T_END,
           "cases": ["encoder"], "seconds": 1.0}
    estimation.plot(res, tmp_path)
    text = estimation.write_page(res, tmp_path)
    assert (tmp_path / "estimation.md").read_text() == text
    assert text.startswith("# State estimation: the three-simulation benchmark")
    assert "| estimator | z (rad) | ż (rad/s) | z̈ (rad/s²) | within ±2σ | mean NIS (in bounds) |" in text
    assert ("| N_w | DC z (rad) | DC ż (rad/s) | DC z̈ (rad/s²) | DC µs/step | IC z (rad) "
            "| IC ż (rad/s) | IC z̈ (rad/s²) | IC µs/step |") in text
    assert "not available" not in text and "no estimator yet" not in text
    assert "| failed: step 1 (t = 0.005 s) did not converge (iteration limit) |" in text
    assert f"| 20 | {estimation.g(row['rmse_z:theta'])} |" in text
    assert f"| {estimation.g(ic['rmse_z:theta'])} |" in text
    assert "| mbfg fixed-lag N_w = 20 (default) |" in text
    assert "| mbfg IC fixed-lag N_w = 50 | not run |" in text
    assert "| open loop (bad model alone) |" in text
    assert "5.1e-3 / 0.056 / 0.38" in text          # the published errorEKF beside ours
    assert "| errorEKF | not run |" in text          # the peers, left out here
    assert "(the default)" in text or "(the scene's)" in text   # the process σ's origin
    assert (tmp_path / "estimation" / "encoder-estimate.png").exists()
    assert (tmp_path / "estimation" / "encoder-error.png").exists()
    assert (tmp_path / "estimation" / "runs.csv").read_text().startswith("case,seed,estimator")
