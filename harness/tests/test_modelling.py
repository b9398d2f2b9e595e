"""The Python modelling API: scenes from dicts, YAML text and `mbfg.Scene` built in
code (the four-bar bit for bit as its file), the round trip to YAML for the suite's
scenes, joint-space quantities (M(z), Q_z, c, R, point Jacobians) checked against
their definitions and finite differences, gravity compensation that holds a robot
still, `columns=` as the CLI's, and the module's public surface."""

import csv
import inspect
import pathlib
import subprocess

import numpy as np
import pytest

import mbfg

ROOT = pathlib.Path(__file__).resolve().parents[2]
SCENES = ROOT / "scenes"
MBFG = ROOT / "target/release/mbfg"


def fourbar_in_code() -> mbfg.Scene:
    s = mbfg.Scene("fourbar")
    s.point("A", 0, 0, fixed=True).point("P1", 1, 0).point("P2", 1, 2).point("B", 4, 0, fixed=True)
    s.body("crank", ["A", "P1"], mass=1)
    s.body("coupler", ["P1", "P2"], mass=2)
    s.body("rocker", ["P2", "B"], mass=4, length="sqrt(13)")
    return s.gravity(0, -9.81)


def test_the_fourbar_built_in_code_runs_as_its_file_bit_for_bit():
    built = mbfg.simulate(fourbar_in_code(), dt=1e-3, t_end=5.0)
    filed = mbfg.simulate(str(SCENES / "fourbar.yaml"), dt=1e-3, t_end=5.0)
    assert built.columns == filed.columns
    assert built.data.shape == filed.data.shape == (5001, 13)
    assert np.array_equal(built.data, filed.data)
    # A model of it too, with parameters overridden as for a file.
    m = fourbar_in_code().parameter("g", 9.81).model(params={"g": 1.0})
    assert m.n == 4 and m.dof == 1


def test_load_takes_a_path_a_dict_yaml_text_and_a_scene():
    path = SCENES / "fourbar-theta.yaml"
    text = path.read_text()
    scene = mbfg.Scene.from_yaml(text)
    models = [mbfg.load(path), mbfg.load(text), mbfg.load(scene.to_dict()), mbfg.load(scene)]
    for m in models[1:]:
        assert m.names == models[0].names
        assert np.array_equal(m.mass_matrix(), models[0].mass_matrix())
        assert np.array_equal(m.initial_q, models[0].initial_q)
        assert m.effects == models[0].effects and m.independent == models[0].independent
    # Parameters of a scene given as text are overridden as a file's.
    pendulum = "parameters: {L: 1}\npoints:\n  - {name: O, x: 0, y: 0, fixed: true}\n" \
               "  - {name: T, x: L, y: 0}\nbodies:\n  - {name: bar, points: [O, T], mass: 1}\n"
    assert mbfg.load(pendulum, params={"L": 2}).initial_q[0] == 2.0
    long = mbfg.load(mbfg.load(pendulum), params={"L": 3})
    assert long.initial_q[0] == 3.0


def test_errors_in_built_scenes_name_their_line_and_suggest_names():
    s = fourbar_in_code().independent("thetta").coordinate("theta", "angle", points=["A", "P1"])
    with pytest.raises(mbfg.SceneError, match=r"<Scene>:\d+: independent: unknown coordinate "
                                              r"'thetta'.*did you mean 'theta'\?"):
        s.model()
    with pytest.raises(mbfg.SceneError, match="the file is empty"):
        mbfg.load("\n")
    model = fourbar_in_code().model()
    with pytest.raises(mbfg.InvalidArgument, match=r"no coordinate named 'P1.z'; did you mean 'P1.y' or 'P1.x'"):
        model.index("P1.z")
    with pytest.raises(mbfg.InvalidArgument, match=r"no body named 'rocer'; did you mean 'rocker'"):
        model.body_point_position(model.initial_q, "rocer")


SUITE = sorted(p for p in SCENES.rglob("*.yaml")
               if "trajectories" not in p.parts and "mbse" not in p.parts)


@pytest.mark.parametrize("path", SUITE, ids=[str(p.relative_to(SCENES)) for p in SUITE])
def test_every_suite_scene_round_trips_through_the_builder(path, monkeypatch):
    text = path.read_text()
    scene = mbfg.Scene.from_yaml(text)
    again = mbfg.Scene.from_yaml(scene.to_yaml())
    assert again == scene
    # `mechanism:` files are found from the scene's folder.
    monkeypatch.chdir(path.parent)
    a, b = mbfg.load(path.name), mbfg.load(scene)
    assert a.names == b.names and a.effects == b.effects and a.independent == b.independent
    assert np.array_equal(a.mass_matrix(), b.mass_matrix())
    assert np.array_equal(a.initial_q, b.initial_q) and np.array_equal(a.initial_dq, b.initial_dq)


def consistent_states(scene, t_end=0.3):
    run = mbfg.simulate(str(SCENES / scene), dt=1e-3, t_end=t_end)
    return mbfg.load(SCENES / scene), run


def test_the_velocity_map_spans_the_constraints_free_motions():
    model, run = consistent_states("pick-and-place.yaml")
    q = run.q[-1]
    r = model.velocity_map(q)
    idx = [model.index(n) for n in model.independent]
    assert r.shape == (model.n, 2)
    assert np.abs(model.phi_q(q) @ r).max() < 1e-12
    assert np.allclose(r[idx], np.eye(2), atol=1e-13)
    # Kinetic energy in z: ½ żᵀ M(z) ż = ½ q̇ᵀ M q̇.
    dz = run.dq[-1][idx]
    assert np.isclose(0.5 * dz @ model.reduced_mass_matrix(q) @ dz, model.kinetic_energy(run.dq[-1]),
                      rtol=1e-10)
    with pytest.raises(mbfg.InvalidArgument, match="2 degree"):
        model.velocity_map(q, independent=["motor1"])


@pytest.mark.parametrize("scene", ["fourbar-theta.yaml", "pick-and-place.yaml", "slider-crank.yaml"])
def test_the_equations_of_motion_hold_in_the_independent_coordinates(scene):
    """M(z) z̈ + c(z, ż) = Q_z on the states of a run (each a consistent q, q̇, q̈)."""
    model, run = consistent_states(scene)
    names = model.independent or None
    if names is None:
        pytest.skip("no independent coordinates")
    idx = [model.index(n) for n in names]
    for k in (50, 150, 300):
        q, dq, ddq, t = run.q[k], run.dq[k], run.ddq[k], run.t[k]
        lhs = model.reduced_mass_matrix(q) @ ddq[idx] + model.bias_forces(q, dq)
        rhs = model.reduced_forces(q, dq, t)
        assert np.allclose(lhs, rhs, rtol=1e-7, atol=1e-7 * np.abs(rhs).max()), (k, lhs, rhs)


def test_gravity_in_independent_coordinates_is_the_forces_of_a_gravity_only_scene():
    model, run = consistent_states("pick-and-place.yaml")
    q = run.q[-1]
    assert np.allclose(model.reduced_gravity(q), model.reduced_forces(q, np.zeros(model.n), 0.0),
                       rtol=1e-12, atol=1e-12)


def test_point_jacobians_match_finite_differences():
    model, run = consistent_states("pick-and-place.yaml")
    q, dq = run.q[-1], run.dq[-1]
    for body, local in [("plate", (0.75, -0.25)), ("elbow1", (0.1, 0.3)), ("arm1a", (0.5, 0))]:
        j = model.point_jacobian(body=body, local=local)
        h = 1e-6
        fd = np.column_stack([
            (model.body_point_position(q + h * e, body, local)
             - model.body_point_position(q - h * e, body, local)) / (2 * h)
            for e in np.eye(model.n)])
        assert np.allclose(j, fd, atol=1e-8), body
        assert np.allclose(model.body_point_velocity(q, dq, body, local), j @ dq)
    # The frame's points themselves are the scene's points.
    plate = next(b for b in model.bodies if b["name"] == "plate")
    p0, p1 = plate["points"][:2]
    assert np.allclose(model.body_point_position(q, "plate", (0, 0)), model.point_position(q, p0))
    assert np.allclose(model.body_point_position(q, "plate", (plate["length"], 0)),
                       model.point_position(q, p1), atol=1e-12)
    assert np.allclose(model.point_jacobian(point=p0) @ dq, model.point_velocity(dq, p0))


def test_gravity_compensation_holds_a_robot_still():
    """Computed torque on the two motors from M(z), c and Q_z: the robot released from
    rest stays where it is to 1e-9 m; without the motors it falls."""
    path = str(SCENES / "pick-and-place.yaml")
    model = mbfg.load(path)
    idx = [model.index(n) for n in model.independent]
    z0 = model.initial_q[idx]
    kp, kd = 100.0, 20.0

    def motors(t, q, dq):
        z, dz = q[idx], dq[idx]
        tau = (model.reduced_mass_matrix(q) @ (kp * (z0 - z) - kd * dz)
               + model.bias_forces(q, dq) - model.reduced_forces(q, dq, t))
        out = np.zeros(model.n)
        out[idx] = tau
        return out

    held = mbfg.simulate(path, dt=1e-2, t_end=0.5, effects={"motors": motors})
    drift = np.abs(held.q - model.initial_q).max()
    assert drift < 1e-9, drift
    fallen = mbfg.simulate(path, dt=1e-2, t_end=0.5)
    assert np.abs(fallen.q - model.initial_q).max() > 1e-2


def test_columns_are_the_cli_columns(tmp_path):
    scene = str(SCENES / "spring-damper.yaml")
    run = mbfg.simulate(scene, dt=1e-3, t_end=0.2, columns=["joints", "bodies", "energy"])
    out = tmp_path / "cli.csv"
    r = subprocess.run([str(MBFG), "simulate", scene, "--dt", "1e-3", "--t-end", "0.2",
                        "--columns", "bodies,energy,joints", "--out", str(out)],
                       capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    with open(out) as f:
        rows = list(csv.reader(f))
    assert run.columns == rows[0]
    assert np.array_equal(run.data, np.array(rows[1:], dtype=float))
    assert "energy_balance" in run.columns
    with pytest.raises(mbfg.InvalidArgument, match="unknown column group `power`.*bodies"):
        mbfg.simulate(scene, dt=1e-3, t_end=0.01, columns=["power"])


def test_a_refined_runs_columns_are_the_cli_columns(tmp_path):
    # Integrated at a finer step than the 10 ms rows: the work columns integrate over
    # every step taken, in Python as in the CLI, and the balance closes.
    scene = str(ROOT / "tests/data/fast-link-refined.yaml")
    run = mbfg.simulate(scene, coords="ic", dt=1e-2, t_end=0.3, columns=["energy"])
    out = tmp_path / "cli.csv"
    r = subprocess.run([str(MBFG), "simulate", scene, "--coords", "ic", "--dt", "0.01",
                        "--t-end", "0.3", "--columns", "energy", "--out", str(out)],
                       capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    assert "integrated at dt" in r.stdout
    with open(out) as f:
        rows = list(csv.reader(f))
    assert run.columns == rows[0]
    assert np.array_equal(run.data, np.array(rows[1:], dtype=float))
    peak = np.abs(run.column("kinetic")).max()
    assert np.abs(run.column("energy_balance")).max() < 0.01 * peak


def test_the_public_surface_is_listed_and_documented():
    assert not {"np", "os", "Mapping", "warnings"} & set(dir(mbfg))
    for name in mbfg.__all__:
        assert hasattr(mbfg, name), name
    for f in (mbfg.simulate, mbfg.load, mbfg.inverse, mbfg.measure, mbfg.estimate, mbfg.animate):
        doc = inspect.getdoc(f)
        for p in inspect.signature(f).parameters:
            assert p in doc, f"{f.__name__}: argument {p} is not explained"
    run = mbfg.simulate(str(SCENES / "pendulum.yaml"), dt=1e-2, t_end=0.1)
    doc = inspect.getdoc(mbfg.Result)
    for field in vars(run):
        assert field in doc, f"Result.{field} is not explained"


def test_until_ends_the_run_at_the_zero_as_the_cli_does():
    scene = str(ROOT / "examples/tutorial/swinging-bar.yaml")
    run = mbfg.simulate(scene, dt=1e-3, t_end=5.0, until="theta - 0.2")
    stop = run.summary["until"]
    assert run.summary["complete"] and len(run.t) == stop["step"] + 1 == 351
    theta = run.column("q:theta")
    assert theta[-2] < 0.2 <= theta[-1] and run.t[-2] < stop["t"] <= run.t[-1]
    r = subprocess.run([str(MBFG), "simulate", scene, "--dt", "1e-3", "--t-end", "5", "--until",
                        "theta - 0.2"], capture_output=True, text=True)
    assert f"at t = {round(stop['t'], 9)} s" in r.stderr, r.stderr
    with pytest.raises(mbfg.InvalidArgument, match="did you mean 'theta'"):
        mbfg.simulate(scene, dt=1e-3, t_end=1.0, until="thetta")
