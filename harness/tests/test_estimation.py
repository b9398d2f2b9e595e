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
    return case, row, estimation.open_loop(case, tpath)


def test_summary_line_is_parsed():
    s = estimation.parse_summary(
        "2001 steps (dt = 0.005 s, window 50) from 2001 readings in 2.546 s (1272 µs a step); "
        "linear solves per step: mean 3.86; mean NIS 1.405 against 1 expected, 95 % bounds "
        "[0.939, 1.063]: NOT consistent; process σ 1")
    assert s["steps"] == 2001 and s["wall_s"] == 2.546 and s["us_per_step"] == 1272
    assert s["nis"] == 1.405 and (s["nis_lo"], s["nis_hi"]) == (0.939, 1.063)
    assert s["nis_ok"] is False and s["process_sigma"] == 1


def test_readings_keep_the_case_columns():
    case = estimation.CASE["encoder"]
    path = estimation.readings_path(case, SEED, T_END)
    header = path.read_text().splitlines()[0]
    assert header == "t,enc"
    assert len(path.read_text().splitlines()) == round(T_END / estimation.DT) + 2


def test_mbfg_estimate_tracks_the_truth_from_the_bad_model(encoder_run):
    _, row, loop = encoder_run
    assert row["status"] == "ok", row["status"]
    # Far below the bad model alone, and at the encoder's noise level or better.
    assert loop["rmse_z:theta"] > 0.1
    assert row["rmse_z:theta"] < min(1e-2, loop["rmse_z:theta"] / 50)
    assert row["rmse_dz:theta"] < loop["rmse_dz:theta"] / 10
    # Honest σ: the truth within ±2σ at most steps.
    assert row["within_2sd"] >= 0.85
    assert row["us_per_step"] > 0 and row["nis"] > 0


def test_page_has_its_tables(encoder_run, tmp_path):
    case, row, loop = encoder_run
    res = {"rows": [row], "open_loop": [loop], "seeds": [SEED], "sweep_seeds": [SEED],
           "sweep_windows": [20, "batch"], "t_end": T_END, "cases": ["encoder"],
           "seconds": 1.0}
    estimation.plot(res, tmp_path)
    text = estimation.write_page(res, tmp_path)
    assert (tmp_path / "estimation.md").read_text() == text
    assert text.startswith("# State estimation: the three-simulation benchmark")
    assert "| estimator | z (rad) | ż (rad/s) | z̈ (rad/s²) | within ±2σ | mean NIS (in bounds) |" in text
    assert "| N_w | DC z (rad) | DC ż (rad/s) | DC z̈ (rad/s²) | DC µs/step | IC |" in text
    assert "not available: `--coords ic` is not supported by mbfg estimate yet" in text
    assert "| mbfg fixed-lag N_w = 20 (default) |" in text
    assert "| open loop (bad model alone) |" in text
    assert "5.1e-3 / 0.056 / 0.38" in text          # the published errorEKF beside ours
    assert "| errorEKF | not run |" in text          # the peers, left out here
    assert (tmp_path / "estimation" / "encoder-estimate.png").exists()
    assert (tmp_path / "estimation" / "encoder-error.png").exists()
    assert (tmp_path / "estimation" / "runs.csv").read_text().startswith("case,seed,estimator")
