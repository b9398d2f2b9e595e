"""The identification page's pieces: the scenes of scenes/identification/ (true and bad
differ only where their comments say), the output-error peer (harness/output_error.py),
the parsing of `--parameters-out`, the page's verdicts, and the page end to end on a
short record."""

import numpy as np
import pytest
import yaml

import mbfg
from harness import identification as ident
from harness import output_error

SCENES = ident.SCENES


def spec(name: str) -> dict:
    return yaml.safe_load((SCENES / name).read_text())


# ---------------------------------------------------------------- the scenes

# What each bad scene may change of its true scene's: parameter values, and where the
# start is off the free points' placement (initial guesses of the assembly).
CHANGED = {"gravity": ({"g", "th0"}, True), "mass": ({"m_crank", "th0"}, True),
           "spring": ({"k", "c"}, False), "arm": ({"m1", "m2", "I1", "I2"}, False),
           "arm-laws": ({"m1", "m2", "I1", "I2"}, False), "friction": ({"b", "mu"}, False)}


@pytest.mark.parametrize("key", list(ident.TEST))
def test_true_and_bad_scenes_differ_only_where_said(key):
    test = ident.TEST[key]
    true, bad = spec(test.true_scene), spec(test.bad_scene)
    names, moved = CHANGED[key]
    # The true scene holds the truth the page scores against.
    for p, v in test.truth.items():
        assert ident.eval_parameter(SCENES / test.true_scene, p) == pytest.approx(v, rel=1e-12)
    shared = set(true["parameters"]) & set(bad["parameters"])
    differ = {p for p in shared
              if ident.eval_parameter(SCENES / test.true_scene, p)
              != ident.eval_parameter(SCENES / test.bad_scene, p)}
    assert differ == names
    # Only the true arm's controllers have gains; the bad arm has no controllers.
    assert set(true["parameters"]) - shared == ({"kp1", "kd1", "kp2", "kd2"} if key == "arm" else set())
    assert set(bad["parameters"]) == shared
    # The unknowns: every parameter the page identifies, each with a prior σ.
    unknown = bad["estimation"]["parameters"]
    assert [u["name"] for u in unknown] == list(test.truth)
    assert all(u["sigma"] > 0 for u in unknown)
    for k in ("bodies", "coordinates", "independent", "initial"):
        assert true.get(k) == bad.get(k), k
    # The bad scene reads what the true one does, but the columns mbfg is not given.
    assert bad["sensors"] == [s for s in true["sensors"] if s["name"] not in test.readings_dropped]
    if moved:
        assert [p for p in true["points"] if p.get("fixed")] == [p for p in bad["points"] if p.get("fixed")]
    else:
        assert true["points"] == bad["points"]
    if key == "arm":
        # The bad model has no controllers: their torques are the unknown inputs the
        # torque sensors read.
        assert [e["type"] for e in true["effects"]] == ["torque", "torque"]
        assert "effects" not in bad
        assert {i["coordinate"] for i in bad["estimation"]["inputs"]} == {"q1", "q2"}
        assert {s["coordinate"] for s in bad["sensors"] if s["type"] == "input"} == {"q1", "q2"}
    else:
        assert true["effects"] == bad["effects"]


@pytest.mark.parametrize("key", list(ident.TEST))
def test_scenes_load(key):
    test = ident.TEST[key]
    for name in (test.true_scene, test.bad_scene):
        model = mbfg.load(str(SCENES / name))
        assert model.dof == len(model.independent)


def test_four_bar_tests_start_off_as_the_benchmark_does():
    for key in ("gravity", "mass"):
        test = ident.TEST[key]
        th_true = ident.eval_parameter(SCENES / test.true_scene, "th0")
        th_bad = ident.eval_parameter(SCENES / test.bad_scene, "th0")
        assert th_bad - th_true == pytest.approx(np.pi / 16)


# ---------------------------------------------------------------- the peer

def exact_readings(scene, t_end, dt=5e-3, params=None):
    """The encoder's exact readings along an accurate simulation (1 ms, Hermite–Simpson)."""
    r = mbfg.simulate(str(scene), dt=1e-3, t_end=t_end, integrator="hermite-simpson",
                      params=params)
    rows = np.arange(0, len(r.t), int(round(dt / 1e-3)))
    return {"t": r.t[rows], "enc": r.column("q:theta")[rows]}


def test_peer_recovers_stiffness_and_damping_on_an_exact_record():
    scene = SCENES / "spring-damper.yaml"
    readings = exact_readings(scene, 3.0)
    fit = output_error.fit(scene, readings, {"k": 15.0, "c": 0.1},
                           bounds={"k": (0, np.inf), "c": (0, np.inf)})
    assert fit.success, fit.message
    assert fit.estimate["k"] == pytest.approx(20.0, rel=1e-4)
    assert fit.estimate["c"] == pytest.approx(0.2, rel=1e-3)
    assert fit.evaluations > 3 and fit.wall_s > 0


def test_peer_sigma_covers_its_error_on_noisy_readings():
    scene = SCENES / "spring-damper.yaml"
    truth = mbfg.simulate(str(scene), dt=1e-3, t_end=3.0, integrator="hermite-simpson")
    rows = np.arange(0, len(truth.t), 5)
    readings = mbfg.measure(str(scene), {c: truth.column(c)[rows] for c in truth.columns}, seed=3)
    fit = output_error.fit(scene, readings, {"k": 15.0}, bounds={"k": (0, np.inf)})
    err = fit.estimate["k"] - 20.0
    # σ from (JᵀJ)⁻¹ s²: of the order of the error, and s² near 1 for readings with
    # the σ the scene says.
    assert 0 < fit.sigma["k"] < 0.05
    assert abs(err) < 4 * fit.sigma["k"]
    assert 0.8 < fit.s2 < 1.2


def test_peer_stages_escape_the_wrong_minimum_of_a_long_record():
    scene = SCENES / "fourbar-gravity.yaml"
    readings = exact_readings(scene, 4.0)
    start = {"g": 9.0, "th0": np.pi / 3 + np.pi / 16}
    staged = output_error.fit(scene, readings, start, bounds={"g": (0, np.inf)},
                              horizons=(1.0,))
    assert staged.estimate["g"] == pytest.approx(10.0, rel=1e-4)
    assert staged.estimate["th0"] == pytest.approx(np.pi / 3, abs=1e-5)


def test_peer_refuses_what_it_cannot_fit():
    scene = SCENES / "spring-damper.yaml"
    readings = exact_readings(scene, 0.5)
    with pytest.raises(ValueError, match="no scene parameter stiffness"):
        output_error.fit(scene, readings, {"stiffness": 15.0})
    with pytest.raises(ValueError, match="evenly spaced"):
        output_error.fit(scene, {"t": np.array([0, 0.1, 0.3]), "enc": np.zeros(3)}, {"k": 15.0})
    with pytest.raises(ValueError, match="none of its sensors"):
        output_error.fit(scene, {"t": readings["t"], "gyro": readings["enc"]}, {"k": 15.0})


def test_peer_reads_a_measurement_file(tmp_path):
    path = tmp_path / "m.csv"
    path.write_text("t,enc,gyro\n0,1.5,\n0.005,1.25,0.5\n")
    r = output_error.read_readings(path)
    assert r["enc"].tolist() == [1.5, 1.25]
    assert np.isnan(r["gyro"][0]) and r["gyro"][1] == 0.5


# ---------------------------------------------------------------- the page's pieces

def test_parameters_out_is_read_as_the_contract_says(tmp_path):
    path = tmp_path / "p.csv"
    path.write_text("name,estimate,sigma,prior,prior_sigma,identifiable,reason,corr:m1,corr:I1\n"
                    "m1,2.6,0.98,2.5,1,no,\"posterior σ 0.98 of prior σ 1; moves with I1 (ρ = -0.999)\",1,-0.999\n"
                    "I1,0.05,0.019,0.03,0.02,no,moves with m1,-0.999,1\n")
    p = ident.read_parameters(path)
    assert list(p) == ["m1", "I1"]
    assert p["m1"]["identifiable"] is False and "moves with I1" in p["m1"]["reason"]
    assert p["m1"]["corr"] == {"m1": 1.0, "I1": -0.999}
    assert p["I1"]["prior_sigma"] == 0.02


def row(test, seed, est, **kw):
    return {"test": test, "seed": seed, "estimator": est, "status": "ok", **kw}


def test_verdicts_count_a_named_parameter_and_miss_a_wrong_one():
    rows = []
    for seed in (1, 2):
        rows.append(row("arm", seed, "mbfg batch", **{
            "relerr:m1": 0.3, "identifiable:m1": False,          # named: met
            "relerr:I1": 0.3, "identifiable:I1": True,           # wrong and confident: missed
            "relerr:m2": 0.005, "identifiable:m2": True,
            "relerr:I2": 0.01, "identifiable:I2": True, "process_s": 1.0}))
        rows.append(row("arm", seed, "output-error", **{
            "relerr:m2": 0.004, "relerr:I2": 0.02, "relerr:I1": 0.001, "wall_s": 20.0}))
    res = {"rows": rows, "tests": ["arm"], "seeds": [1, 2]}
    title = ident.TEST["arm"].title + ": "
    v = {k.removeprefix(title): m for k, m in ident.verdicts(res)}
    line = {k.split(" ")[0]: m for k, m in v.items() if "or named" in k}
    assert line == {"m1": True, "I1": False, "m2": True, "I2": True}
    speed = [m for k, m in v.items() if "faster" in k]
    assert speed == [True]  # 20 s against 1 s
    acc = {k.split(",")[0]: m for k, m in v.items() if "as accurate" in k}
    assert acc == {"I1": False, "m2": False, "I2": True}  # m1 named: not compared


def test_verdicts_of_the_four_bar_hold_every_seed_to_one_percent():
    rows = [row("gravity", s, "mbfg batch", **{"relerr:g": e, "covered:g": c, "wall_s": 0.5,
                                                "process_s": 0.6, "steps": 2001,
                                                "rmse_z:theta": 2e-3, "rmse_dz:theta": 0.01,
                                                "rmse_ddz:theta": 0.1})
            for s, (e, c) in enumerate([(0.001, True)] * 9 + [(0.02, False)], start=1)]
    # The batch's time is the timing pass's (one run at a time), not the main pass's.
    timing = [row("gravity", 1, "mbfg batch", wall_s=2.5, process_s=2.6, steps=2001)]
    res = {"rows": rows, "tests": ["gravity"], "seeds": list(range(1, 11)), "timing": timing}
    v = ident.verdicts(res)
    within = next(m for k, m in v if "within 1%" in k)
    covers = next(m for k, m in v if "1σ covers" in k)
    batch = next(k for k, m in v if "the batch of 2001 steps" in k)
    assert (within, covers) == (False, True)
    assert "median 2.50 s over 1 seeds" in batch and not dict(v)[batch]


def test_page_end_to_end_on_a_short_record(tmp_path):
    pytest.importorskip("sksundae")
    res = ident.write(tmp_path, seeds=[1], t_end=2.0, tests=["gravity"], inverse=False,
                      ida_seeds=0)
    text = (tmp_path / "identification.md").read_text()
    assert "## (a) four-bar, gravity" in text and "output-error" in text
    batch = ident.ok(res["rows"], "gravity", "mbfg batch")
    peer = ident.ok(res["rows"], "gravity", "output-error")
    assert batch and peer, res["rows"]
    # Two seconds of a 1° encoder still put g within a few percent, with a σ that says so.
    assert batch[0]["relerr:g"] < 0.05 and batch[0]["z:g"] < 4
    assert peer[0]["relerr:g"] < 0.05
    assert (tmp_path / "identification" / "gravity.png").exists()


def test_peer_over_ida_simulates_what_mbfg_does():
    pytest.importorskip("sksundae")
    scene = SCENES / "spring-damper.yaml"
    readings = exact_readings(scene, 0.5)
    hs = output_error.Problem(scene, readings, ["k"])
    ida = output_error.Problem(scene, readings, ["k"], integrator="ida")
    a, b = hs.simulate([18.0]), ida.simulate([18.0])
    assert np.max(np.abs(a.column("q:theta") - b.column("q:theta"))) < 1e-6
    assert ida.residuals([20.0]) == pytest.approx(np.zeros(len(readings["t"])), abs=1e-5)
    with pytest.raises(ValueError, match="unknown integrator 'rk4'"):
        output_error.Problem(scene, readings, ["k"], integrator="rk4")


# The numbers on seed 1 of each test, the page's own runs (10 s, IDA truth):
# the batch's estimates within the tolerance, or named not identifiable with a reason.
# (Its time is the page's to measure, not a test's.)
# Link 1 only turns about its base: m1 and I1 move together.
NAMED = {"arm": {"m1", "I1"}, "arm-laws": {"m1", "I1"}}


@pytest.mark.parametrize("key", list(ident.TEST))
def test_batch_identifies_on_seed_1(key):
    pytest.importorskip("sksundae")
    test = ident.TEST[key]
    exe = str(ident.est.snapshot())
    tpath = str(ident.truth_path(test))
    r = ident.mbfg_row(test, 1, ident.T_END, str(ident.readings_path(test, 1, exe=exe)), tpath,
                       exe, "batch")
    assert r["status"] == "ok", r["status"]
    for p in test.truth:
        if p in NAMED.get(key, ()):
            assert r[f"identifiable:{p}"] is False and r[f"reason:{p}"], p
        else:
            assert r[f"identifiable:{p}"] is True, (p, r[f"reason:{p}"])
            assert r[f"relerr:{p}"] <= test.tolerance, (p, r[f"est:{p}"])
            assert r[f"z:{p}"] < 4, (p, r[f"est:{p}"], r[f"sd:{p}"])
    if test.state_targets:
        z, dz, ddz = ident.STATE_TARGETS["batch"]
        assert r["rmse_z:theta"] <= z and r["rmse_dz:theta"] <= dz and r["rmse_ddz:theta"] <= ddz
