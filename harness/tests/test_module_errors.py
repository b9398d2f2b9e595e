"""The mbfg Python module under bad calls (issue 16): every failure is an ordinary
exception of a documented class with a one-line message, a panic never escapes as
pyo3's PanicException, Ctrl-C stops a run promptly, and a failed or interrupted run
hands back the steps it solved (docs/python.md, "Errors")."""
import json
import math
import pathlib
import signal
import subprocess
import sys
import textwrap
import time

import numpy as np
import pytest

import mbfg

ROOT = pathlib.Path(__file__).resolve().parents[2]
FOURBAR = ROOT / "scenes" / "fourbar.yaml"
THETA = ROOT / "scenes" / "fourbar-theta.yaml"
THETA_CSV = ROOT / "scenes" / "trajectories" / "fourbar-theta.csv"
NFOURBAR = ROOT / "scenes" / "benchmarks" / "n-fourbar-1.yaml"


def test_exception_classes():
    assert issubclass(mbfg.InvalidArgument, ValueError)
    assert issubclass(mbfg.SceneError, ValueError)
    assert issubclass(mbfg.SolveError, RuntimeError)
    assert issubclass(mbfg.InternalError, RuntimeError)
    for e in (mbfg.InvalidArgument, mbfg.SceneError, mbfg.SolveError, mbfg.InternalError):
        assert e.__module__ == "mbfg" and getattr(mbfg, e.__name__) is e
    # Every SolveError has `.result`, None unless a run attached one.
    assert mbfg.SolveError("x").result is None
    assert mbfg.SolveError("x").failure is None


def _short(t=0.01, **kw):
    return lambda: mbfg.simulate(FOURBAR, t_end=t, **kw)


MODEL = mbfg.load(FOURBAR)
Q = MODEL.initial_q
DRIVEN = mbfg.load(ROOT / "scenes" / "driven" / "crank-rocker-ramp.yaml")
TORQUE = next(i for i, e in enumerate(DRIVEN.effects) if e["type"] in ("torque", "force"))

# (call, the argument the message must name) — calls the module once coerced or
# accepted silently, and the neighbours of each.
BAD = {
    "window float": (_short(window=1.7), "window"),
    "window integral float": (_short(window=1.0), "window"),
    "window bool": (_short(window=True), "window"),
    "window zero": (_short(window=0), "window"),
    "window negative": (_short(window=-3), "window"),
    "window huge": (_short(window=10**30), "window"),
    "window str": (_short(window="2"), "window"),
    "batch str": (_short(batch="no"), "batch"),
    "batch int": (_short(batch=1), "batch"),
    "batch None": (_short(batch=None), "batch"),
    "continue_on_failure int": (_short(continue_on_failure=0), "continue_on_failure"),
    "square_steps int": (_short(square_steps=1), "square_steps"),
    "max_iterations float": (_short(max_iterations=2.5), "max_iterations"),
    "max_iterations zero": (_short(max_iterations=0), "max_iterations"),
    "dt nan": (lambda: mbfg.simulate(FOURBAR, dt=math.nan), "dt"),
    "dt inf": (lambda: mbfg.simulate(FOURBAR, dt=math.inf), "dt"),
    "dt str": (lambda: mbfg.simulate(FOURBAR, dt="1e-3"), "dt"),
    "dt bool": (lambda: mbfg.simulate(FOURBAR, dt=True), "dt"),
    "dt array": (lambda: mbfg.simulate(FOURBAR, dt=np.array([1e-3])), "dt"),
    "dt negative": (lambda: mbfg.simulate(FOURBAR, dt=-1.0), "dt"),
    "t_end nan": (lambda: mbfg.simulate(FOURBAR, t_end=math.nan), "t_end"),
    "t_end below dt": (lambda: mbfg.simulate(FOURBAR, t_end=0.0), "t_end"),
    "coords int": (_short(coords=5), "coords"),
    "coords long": (_short(coords="x" * 10_000), "coords"),
    "integrator None": (_short(integrator=None), "integrator"),
    "noise unknown": (_short(noise="loud"), "noise"),
    "past unknown": (_short(past="forgotten"), "past"),
    "scene int": (lambda: mbfg.simulate(5), "scene"),
    "load None": (lambda: mbfg.load(None), "scene"),
    "q 2-D": (lambda: MODEL.phi(np.ones((2, 2))), "q"),
    "q column": (lambda: MODEL.phi(Q.reshape(-1, 1)), "q"),
    "q nested list": (lambda: MODEL.phi([[1.0], [2.0], [3.0], [4.0]]), "q"),
    "q str": (lambda: MODEL.phi("abcd"), "q"),
    "q scalar": (lambda: MODEL.phi(1.0), "q"),
    "q bools": (lambda: MODEL.phi([True] * 4), "q"),
    "q short": (lambda: MODEL.phi([1.0, 2.0]), "q"),
    "q nan": (lambda: MODEL.phi([math.nan] * 4), "q"),
    "dq inf": (lambda: MODEL.kinetic_energy([math.inf] * 4), "dq"),
    "dq 2-D": (lambda: MODEL.phi_q_dot(Q, np.zeros((4, 4))), "dq"),
    "t nan": (lambda: MODEL.accelerations(Q, Q * 0, math.nan), "t"),
    "t str": (lambda: MODEL.generalized_forces(Q, Q * 0, "0"), "t"),
    "effect index float": (lambda: DRIVEN.effect_value(float(TORQUE), 0.0), "i"),
    "effect index out of range": (lambda: DRIVEN.effect_value(99, 0.0), "i"),
    "effect t inf": (lambda: DRIVEN.effect_value(TORQUE, math.inf), "t"),
    "point name int": (lambda: MODEL.point_position(Q, 5), "name"),
    "coordinate name": (lambda: MODEL.index("Z.x"), "coordinate"),
    "trajectory int": (lambda: mbfg.inverse(THETA, 5), "trajectory"),
    "trajectory missing file": (lambda: mbfg.inverse(THETA, ROOT / "nope.csv"), "trajectory"),
    "trajectory ragged": (lambda: mbfg.inverse(THETA, {"t": [0, 0.01, 0.02], "theta": [0, 1]}),
                          "trajectory"),
    "trajectory nan": (lambda: mbfg.inverse(THETA, {"t": [0, 0.01, 0.02, 0.03],
                                                    "theta": [0, 1, math.nan, 0]}), "theta"),
    "trajectory 2-D column": (lambda: mbfg.inverse(THETA, {"t": [0, 0.01], "theta": [[0], [1]]}),
                              "theta"),
    "trajectory key": (lambda: mbfg.inverse(THETA, {1: [0, 0.01], "theta": [0, 1]}), "trajectory"),
    "trajectory unknown column": (lambda: mbfg.inverse(THETA, {"t": [0, 0.01, 0.02],
                                                               "phi": [0, 0, 0]}), "phi"),
    "start unknown": (lambda: mbfg.inverse(THETA, THETA_CSV, start="x"), "start"),
    "inverse max_iterations float": (lambda: mbfg.inverse(THETA, THETA_CSV, max_iterations=3.0),
                                     "max_iterations"),
}


@pytest.mark.parametrize("case", list(BAD))
def test_bad_arguments_raise_invalid_argument(case):
    call, name = BAD[case]
    with pytest.raises(mbfg.InvalidArgument) as info:
        call()
    message = str(info.value)
    assert name in message
    assert "\n" not in message and len(message) <= 300


def test_good_arguments_of_other_types_are_accepted():
    # numpy scalars, paths, tuples and arrays are what users have at hand.
    r = mbfg.simulate(str(FOURBAR), dt=np.float64(1e-3), t_end=np.float32(0.01),
                      window=np.int64(2), batch=np.False_, max_iterations=np.int32(20))
    assert r.q.shape == (11, 4) and r.summary["complete"]
    assert mbfg.simulate(FOURBAR, t_end=1, dt=1e-2).q.shape == (101, 4)  # an int as a time
    np.testing.assert_allclose(MODEL.phi(tuple(Q)), MODEL.phi(Q))
    np.testing.assert_allclose(MODEL.phi(np.array([1, 0, 1, 2])), MODEL.phi([1.0, 0.0, 1.0, 2.0]))
    value = DRIVEN.effect_value(np.int64(TORQUE), 0)
    assert isinstance(value, (float, tuple))


def test_extreme_values_never_escape_as_a_panic():
    """Whatever the inputs, a call returns or raises an Exception (a panic would come
    as mbfg.InternalError, never as pyo3's PanicException, a BaseException)."""
    robot = mbfg.load(ROOT / "scenes" / "pick-and-place.yaml")
    calls = []
    for m in (MODEL, robot, DRIVEN):
        for v in (1e308, -1e308, 1e154, 5e-324, 0.0):
            x = [v] * m.n
            calls += [lambda m=m, x=x: m.phi_q(x), lambda m=m, x=x: m.accelerations(x, x, 1e308),
                      lambda m=m, x=x: m.generalized_forces(x, x, -1e308),
                      lambda m=m, x=x: m.potential_energy(x),
                      lambda m=m, x=x: m.accelerations(m.initial_q, x, 0.0)]
    calls += [lambda: mbfg.simulate(FOURBAR, dt=5e-324, t_end=1.0),
              lambda: mbfg.simulate(FOURBAR, dt=1e-3, t_end=1e300),
              lambda: mbfg.simulate(FOURBAR, dt=1e300, t_end=1e308),
              lambda: mbfg.inverse(THETA, {"t": np.arange(5) * 1e-300, "theta": np.ones(5)}),
              lambda: mbfg.inverse(THETA, {"t": np.arange(5) * 0.01, "theta": np.ones(5) * 1e300})]
    for call in calls:
        try:
            call()
        except Exception:
            pass


def test_a_failed_run_carries_its_steps():
    # A run that stops at a singular configuration: the steps before it come back.
    with pytest.raises(mbfg.SolveError, match="singular configuration") as info:
        mbfg.simulate(NFOURBAR, coords="ic", dt=1e-2, t_end=2.0)
    r = info.value.result
    assert isinstance(r, mbfg.Result)
    s = r.summary
    assert 10 < len(r.t) < 201 and r.q.shape == (len(r.t), len(r.names))
    assert s["steps"] == len(r.t) and s["requested_steps"] == 201
    assert s["complete"] is False and s["converged"] is False and s["interrupted"] is None
    assert r.failures[-1]["reason"] == "singular configuration"
    np.testing.assert_allclose(np.diff(r.t), 1e-2)
    assert s["worst_phi"] < 1e-8
    # Why, as data: the stop's step and time and the configuration ahead.
    f = info.value.failure
    assert f["kind"] == "singular-configuration"
    assert f["step"] == len(r.t) and f["t"] == pytest.approx(len(r.t) * 1e-2)
    assert f["located_t"] >= f["t"] and f["rank"] < f["full_rank"]
    assert f["independent"] and f["dependent"] and 0 < f["distance"] < 1
    assert f["message"] == str(info.value)


def test_a_step_that_does_not_converge_ends_the_result_before_it():
    # One integrator choice: under "auto" the failure reported is the second run's (the
    # paper's factors, whose adaptive past retries the step conditioned: 2 iterations).
    with pytest.raises(mbfg.SolveError, match="did not converge") as info:
        mbfg.simulate(FOURBAR, dt=1e-3, t_end=0.05, max_iterations=1, dc_integrators="tangent")
    r = info.value.result
    step = r.failures[0]["step"]
    assert len(r.t) == step and not r.summary["complete"]
    f = info.value.failure
    assert f["kind"] == "not-converged" and f["step"] == step
    assert f["termination"] == "iteration limit" and f["iterations"] == 1
    assert f["cause"] is None and f["batch"] is False


def test_continuing_past_failures_is_marked_incomplete():
    r = mbfg.simulate(FOURBAR, dt=1e-3, t_end=0.05, max_iterations=1, continue_on_failure=True)
    assert len(r.t) == 51 and r.failures
    assert r.summary["converged"] is False and r.summary["complete"] is False
    ok = mbfg.simulate(FOURBAR, dt=1e-3, t_end=0.05)
    assert ok.summary["converged"] and ok.summary["complete"] and ok.summary["interrupted"] is None


def test_a_diverged_run_raises_even_when_continuing():
    # A diverged solve ends the run short: never a short trajectory that looks complete.
    # Andrews' squeezer at 50 ms: its bodies turn hundreds of radians a step (by default
    # the run would be refined to a finer step).
    scene = ROOT / "scenes" / "benchmarks" / "andrews-squeezer.yaml"
    with pytest.raises(mbfg.SolveError, match="diverged") as info:
        mbfg.simulate(scene, dt=0.05, t_end=1.0, continue_on_failure=True, refine=False)
    r = info.value.result
    assert 0 < len(r.t) < 21 and not r.summary["complete"]


def test_a_failed_inverse_solve_raises_and_one_iteration_solves_a_full_prescription():
    # The staged start fails in its first stage: nothing was solved, so no result.
    with pytest.raises(mbfg.SolveError, match=r"staged start \(stage 1\) did not converge") as info:
        mbfg.inverse(THETA, THETA_CSV, start="staged")
    assert info.value.result is None
    f = info.value.failure
    assert f["kind"] == "not-converged" and f["termination"] in ("diverged", "iteration limit")
    assert f["iterations"] >= 1
    # The default start is the solution of a fully prescribed problem: the batch
    # confirms it in its first iteration.
    good = mbfg.inverse(THETA, THETA_CSV, max_iterations=1)
    assert good.Q.shape == (2001, 5)
    assert good.summary["converged"] and good.summary["complete"]
    assert good.summary["iterations"] == 1


# A child that runs until interrupted, then prints what the KeyboardInterrupt carried.
# It takes Python's own Ctrl-C handler: started from a shell's background job, it
# would inherit SIGINT ignored, and Python then installs none.
CHILD = textwrap.dedent("""
    import json, signal, sys, time
    signal.signal(signal.SIGINT, signal.default_int_handler)
    import mbfg
    print("ready", flush=True)
    try:
        {call}
        print(json.dumps({{"finished": True}}), flush=True)
    except KeyboardInterrupt as e:
        caught = time.time()
        r = e.result
        print(json.dumps({{"caught": caught, "rows": int(r.data.shape[0]),
                          "shape_ok": r.q.shape == (len(r.t), len(r.names)),
                          "summary": {{k: r.summary[k] for k in
                                      ("steps", "requested_steps", "interrupted",
                                       "complete", "converged")}},
                          "t_last": float(r.t[-1]) if len(r.t) else None,
                          "Q": None if r.Q is None else list(r.Q.shape)}}), flush=True)
""")


def _interrupt(call: str, after: float) -> tuple[dict, float, float]:
    """(what the child printed, seconds from SIGINT to the exception, to its exit)."""
    p = subprocess.Popen([sys.executable, "-c", CHILD.format(call=call)], cwd=ROOT,
                         stdout=subprocess.PIPE, text=True)
    try:
        assert p.stdout.readline().strip() == "ready"
        time.sleep(after)
        sent = time.time()
        p.send_signal(signal.SIGINT)
        out, _ = p.communicate(timeout=10)
        exited = time.time()
    finally:
        if p.poll() is None:
            p.kill()
    report = json.loads(out.strip().splitlines()[-1])
    return report, report.get("caught", math.inf) - sent, exited - sent


def test_ctrl_c_stops_a_run_and_keeps_its_steps():
    # 10⁶ steps: minutes of work, interrupted after a second.
    report, caught, exited = _interrupt(
        "mbfg.simulate('scenes/fourbar.yaml', dt=1e-4, t_end=100.0)", after=1.0)
    assert "caught" in report, report
    assert caught < 0.5 and exited < 1.5, (caught, exited)
    s = report["summary"]
    assert report["rows"] > 0 and report["shape_ok"]
    assert s["steps"] == report["rows"] and s["requested_steps"] == 1_000_001
    assert s["interrupted"] == report["rows"] - 1 and s["complete"] is False
    assert report["t_last"] == pytest.approx(1e-4 * (report["rows"] - 1))


def test_ctrl_c_during_an_inverse_solve_is_raised_with_its_result():
    # The batch solve runs to its end (~0.3 s); the interrupt is raised then, with it.
    report, caught, _ = _interrupt(
        "mbfg.inverse('scenes/pick-and-place.yaml', 'scenes/trajectories/pick-and-place.csv')",
        after=0.05)
    if "finished" in report:
        pytest.skip("the solve ended before the signal arrived")
    assert report["Q"] == [1001, 22] and report["summary"]["converged"] is True


def test_a_step_too_coarse_for_the_stiffest_spring_warns_with_its_numbers():
    scene = pathlib.Path(__file__).resolve().parents[2] / "scenes/hard/stiff-spring.yaml"
    with pytest.warns(mbfg.PlausibilityWarning) as record:
        r = mbfg.simulate(scene, dt=0.1, t_end=2.0)
    assert any("too coarse for spring" in str(w.message) for w in record)
    assert any("period is 9.935e-2 s" in w for w in r.summary["warnings"])
    assert any("energy of this conservative scene drifted" in w for w in r.summary["warnings"])
    import warnings
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        r = mbfg.simulate(scene, dt=0.01, t_end=0.5)
    assert r.summary["warnings"] == []


def test_a_mechanism_nothing_moves_warns():
    scene = pathlib.Path(__file__).resolve().parents[2] / "scenes/mbse/pick-and-place.yaml"
    with pytest.warns(mbfg.PlausibilityWarning, match="nothing moves the mechanism"):
        r = mbfg.simulate(scene, dt=0.01, t_end=0.05)
    assert r.summary["complete"]


def test_ctrl_c_stops_a_run_with_python_effects_and_keeps_its_steps():
    # The effect's call runs Python's Ctrl-C handler itself: the run must stop on it.
    call = ("import numpy as np; "
            "mbfg.simulate('scenes/fourbar.yaml', dt=1e-3, t_end=1000.0, "
            "effects={'zero': lambda t, q, dq: np.zeros(len(q))})")
    report, caught, exited = _interrupt(call, after=1.0)
    assert "caught" in report, report
    assert caught < 1.0 and exited < 2.0, (caught, exited)
    s = report["summary"]
    assert report["rows"] > 0 and s["steps"] == report["rows"] and s["complete"] is False


def test_a_run_beyond_the_address_space_limit_raises_rather_than_aborts():
    code = textwrap.dedent("""
        import resource, mbfg
        resource.setrlimit(resource.RLIMIT_AS, (2_000_000_000, 2_000_000_000))
        try:
            mbfg.simulate('scenes/fourbar.yaml', dt=1e-3, t_end=400.0, batch=True,
                          dc_integrators='full')
        except mbfg.InvalidArgument as e:
            print(e)
        # The rows of 10⁸ stepwise steps, held for the result, do not fit either.
        try:
            mbfg.simulate('scenes/fourbar.yaml', dt=1e-4, t_end=1e4)
        except mbfg.InvalidArgument as e:
            print(e)
    """)
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True,
                         text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    lines = out.stdout.strip().splitlines()
    assert len(lines) == 2, out.stdout
    for line in lines:
        assert "needs about" in line and "GB available" in line, line


@pytest.mark.parametrize("value, expected", [
    ("abc", "returned str"),
    (None, "got None"),
    (np.array(["a", "b", "c", "d"], dtype=object), "returned ndarray"),
])
def test_an_effect_returning_the_wrong_type_is_named(value, expected):
    with pytest.raises(mbfg.InvalidArgument) as e:
        mbfg.simulate(FOURBAR, dt=1e-2, t_end=0.1, effects={"pusher": lambda t, q, dq: value})
    assert "effect 'pusher'" in str(e.value) and expected in str(e.value), str(e.value)


def test_an_effect_that_raises_keeps_its_exception_with_a_note_naming_it():
    def bad(t, q, dq):
        return q + "x"
    with pytest.raises(TypeError) as e:
        mbfg.simulate(FOURBAR, dt=1e-2, t_end=0.1, effects={"pusher": bad})
    assert any("effect 'pusher'" in n for n in getattr(e.value, "__notes__", [])), e.value
