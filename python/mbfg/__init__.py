"""mbfg: planar multibody dynamics as factor graphs (the Rust library, through PyO3).

    model = mbfg.load("scenes/fourbar.yaml")
    run = mbfg.simulate("scenes/fourbar.yaml", coords="dc", dt=1e-3, t_end=5.0)

The native module checks the arguments and hands over numpy arrays (float64 arrays
are read in place, results own their buffers) and a run's table as a float64 buffer;
this layer gives the defaults and shapes the table, also the partial result an
interrupted or failed run attaches to its exception (`.result`). API: docs/python.md.
"""
from __future__ import annotations

import os
import warnings
from typing import Callable, Mapping, Sequence

import numpy as np

from . import _native, joint_space as _joint_space
from ._native import InternalError, InvalidArgument, SceneError, SolveError, __version__
from .scene import Scene

__all__ = ["InternalError", "InvalidArgument", "Model", "PlausibilityWarning", "Result", "Scene",
           "SceneError", "SolveError", "Estimator", "COLUMN_GROUPS", "animate", "estimate",
           "inverse", "load", "measure", "simulate"]

# The optional column groups of `simulate(columns=...)`, as `mbfg simulate --columns`.
COLUMN_GROUPS = ("bodies", "energy", "joints")


def __dir__():
    return sorted(__all__ + ["__version__"])


class Model:
    """An assembled model: coordinate names, points, bodies, constraints, effects and
    the functions M, Φ, Φq, Q of the natural coordinates q."""

    def __init__(self, native: _native.Model):
        self._m = native
        # Static descriptions, read once.
        self.file: str = native.file
        self.names: list[str] = native.names
        self.n: int = native.n
        self.m: int = native.m
        self.dof: int = native.dof
        self.points: list[dict] = native.points
        self.bodies: list[dict] = native.bodies
        self.coordinates: list[dict] = native.coordinates
        self.constraints: list[dict] = native.constraints
        self.equations: list[str] = native.equations
        self.redundant: list[str] = native.redundant
        self.effects: list[dict] = native.effects
        self.independent: list[str] = native.independent
        self.is_conservative: bool = native.is_conservative
        self.initial_q = np.asarray(native.initial_q)
        self.initial_dq = np.asarray(native.initial_dq)

    def __repr__(self) -> str:
        return repr(self._m)

    def index(self, name: str) -> int:
        """Position of a coordinate in q."""
        try:
            return self.names.index(name)
        except ValueError:
            raise InvalidArgument(_clip(f"no coordinate named {name!r:.60}{_did_you_mean(name, self.names)} "
                                        f"(coordinates: {', '.join(self.names)})")) from None

    def mass_matrix(self) -> np.ndarray:
        """M (n × n), constant in natural coordinates: the bodies' masses and inertias
        on their points, and the point masses."""
        return np.asarray(self._m.mass_matrix()).reshape(self.n, self.n)

    # The native methods check q, dq and t (1-D, n finite numbers): passed as given.
    def phi(self, q) -> np.ndarray:
        """Φ(q), the m constraint residuals (m² for distance constraints, m for
        sliders, rad-free for angles); 0 on a consistent configuration."""
        return np.asarray(self._m.phi(q))

    def phi_q(self, q) -> np.ndarray:
        """Φ_q(q) = ∂Φ/∂q (m × n)."""
        return np.asarray(self._m.phi_q(q)).reshape(self.m, self.n)

    def phi_q_dot(self, q, dq) -> np.ndarray:
        """dΦ_q/dt = Σ ∂Φ_q/∂q_i q̇_i (m × n): what the acceleration problem needs."""
        return np.asarray(self._m.phi_q_dot(q, dq)).reshape(self.m, self.n)

    def generalized_forces(self, q, dq, t: float) -> np.ndarray:
        """Q(q, q̇, t), the n generalized forces of every effect (gravity, springs,
        dampers, torques, forces) at that state and time."""
        return np.asarray(self._m.generalized_forces(q, dq, t))

    def force_jacobians(self, q, dq, t: float) -> tuple[np.ndarray, np.ndarray]:
        """(∂Q/∂q, ∂Q/∂q̇), each n × n, at that state and time: closed form for the
        scene's effects (symbolic derivatives of expression values), forward
        differences for Python effects. What the dynamics factor linearizes."""
        kq, kv = self._m.force_jacobians(q, dq, t)
        n = len(self.names)
        return np.asarray(kq).reshape(n, n), np.asarray(kv).reshape(n, n)

    def accelerations(self, q, dq, t: float) -> np.ndarray:
        """q̈ from the augmented (KKT) system [M Φ_qᵀ; Φ_q 0] at a consistent state:
        the classical forward dynamics at one instant."""
        return np.asarray(self._m.accelerations(q, dq, t))

    def effect_value(self, i: int, t: float):
        """The value of effect i (in `effects` order) at time t: a torque in N·m, a
        force as (Fx, Fy) in N; other effects (gravity, springs) raise InvalidArgument."""
        return self._m.effect_value(i, t)

    def joint_forces(self, q, dq, ddq, t: float) -> dict[tuple[str, str], np.ndarray]:
        """The force the rest of the mechanism exerts on each body at each of its points,
        N, global axes, at a consistent state (a row of a result): {(body, point):
        array([fx, fy])}. At a pin the forces on the bodies that meet there balance the
        pin's own load; at a fixed point, minus their sum is the ground's reaction."""
        return {(b, p): np.array([fx, fy]) for b, p, fx, fy in self._m.joint_forces(q, dq, ddq, t)}

    def constraint_forces(self, q, dq, ddq, t: float) -> dict[str, float]:
        """The force each of the scene's `constraints` carries at a consistent state (a
        row of a result), by name: a distance's tension (N, positive pulling its points
        together), a slider's normal force (N, along the guide's left normal), as the
        CLI's `--columns constraints` writes them (`R:<name>`)."""
        return dict(self._m.constraint_forces(q, dq, ddq, t))

    def point_position(self, q, name: str) -> tuple[float, float]:
        """(x, y) of a named point at q, in m (fixed points included)."""
        return self._m.point_position(q, name)

    def point_velocity(self, dq, name: str) -> tuple[float, float]:
        """(ẋ, ẏ) of a named point for the velocities q̇, in m/s."""
        return self._m.point_velocity(dq, name)

    def kinetic_energy(self, dq) -> float:
        """½ q̇ᵀ M q̇, in J."""
        return self._m.kinetic_energy(dq)

    def potential_energy(self, q) -> float:
        """Potential energy of gravity and the springs at q, in J (0 without them)."""
        return self._m.potential_energy(q)

    def sensors(self) -> list[dict]:
        """The scene's sensors, one dict each: name, type, columns (the reading's
        columns in a measurement file), sigma, rate (None: every sample), resolution
        (counts per turn or None), effective_sigma (√(σ² + quantum²/12)) and reads
        ([q, q̇, q̈]: which the reading depends on)."""
        return self._m.sensors()

    # Joint space: the independent coordinates z (the scene's `independent`, or any
    # other f coordinates of q passed as `independent=[...]`).
    def velocity_map(self, q, independent: Sequence[str] | None = None) -> np.ndarray:
        """R = ∂q/∂z (n × f) at a consistent q: q̇ = R ż. Raises InvalidArgument where
        the independent coordinates do not determine the others."""
        return _joint_space.velocity_map(self, q, independent)

    def reduced_mass_matrix(self, q, independent: Sequence[str] | None = None) -> np.ndarray:
        """M(z) = RᵀMR (f × f), the mass matrix in the independent coordinates at q."""
        r = self.velocity_map(q, independent)
        return r.T @ self.mass_matrix() @ r

    def reduced_forces(self, q, dq, t: float = 0.0,
                       independent: Sequence[str] | None = None) -> np.ndarray:
        """Q_z = RᵀQ(q, q̇, t) (f): every effect's generalized force in the independent
        coordinates (N·m on an angle, N on a length)."""
        return self.velocity_map(q, independent).T @ self.generalized_forces(q, dq, t)

    def reduced_gravity(self, q, independent: Sequence[str] | None = None) -> np.ndarray:
        """RᵀQ_g (f): the scene's gravity alone in the independent coordinates. A motor
        torque τ = −RᵀQ_g on them holds the mechanism still against gravity."""
        return self.velocity_map(q, independent).T @ _joint_space.gravity_forces(self, q)

    def gravity_forces(self, q) -> np.ndarray:
        """Q_g (n): the scene's gravity alone in the natural coordinates."""
        return _joint_space.gravity_forces(self, q)

    def bias_forces(self, q, dq, independent: Sequence[str] | None = None) -> np.ndarray:
        """c(z, ż) = RᵀM q̈₀ (f): the velocity terms of M(z) z̈ + c = Q_z, with q̈₀ the
        accelerations at z̈ = 0 (Φ_q q̈₀ = −Φ̇_q q̇). Zero at rest."""
        r = self.velocity_map(q, independent)
        return r.T @ self.mass_matrix() @ _joint_space.bias_accelerations(self, q, dq, independent)

    def point_jacobian(self, q=None, point: str | None = None, body: str | None = None,
                       local=None) -> np.ndarray:
        """∂r/∂q (2 × n) of a named point (`point=`), or of the point at `local` = (x,
        y) in `body`'s frame (origin at its first point, x axis towards its second).
        Constant in natural coordinates (q is accepted for symmetry and not needed);
        the velocity is J q̇, and J R its Jacobian in the independent coordinates."""
        if (point is None) == (body is None):
            raise self._invalid("point_jacobian: give point=NAME, or body=NAME and local=(x, y)")
        if point is not None:
            return _joint_space.point_jacobian(self, point)
        return _joint_space.body_point_jacobian(self, body, (0.0, 0.0) if local is None else local)

    def body_point_position(self, q, body: str, local=(0.0, 0.0)) -> np.ndarray:
        """(x, y) in m of the point at `local` in `body`'s frame, at q."""
        return _joint_space.body_point_position(self, q, body, local)

    def body_point_velocity(self, q, dq, body: str, local=(0.0, 0.0)) -> np.ndarray:
        """(ẋ, ẏ) in m/s of the point at `local` in `body`'s frame, for q̇."""
        return _joint_space.body_point_jacobian(self, body, local) @ np.asarray(dq, dtype=float)

    def _invalid(self, message: str) -> InvalidArgument:
        return InvalidArgument(_clip(message))

    def sensor_value(self, name: str, q, dq, ddq, t: float = 0.0):
        """The reading h(q, q̇, q̈, t) of sensor `name`, without noise, and its
        Jacobians: (h, ∂h/∂q, ∂h/∂q̇, ∂h/∂q̈), h of 1 or 2 entries, each Jacobian
        dim × n."""
        return self._m.sensor_value(name, q, dq, ddq, t)


class PlausibilityWarning(UserWarning):
    """A run converged, but its step is too coarse for the scene's stiffest spring or
    damper, or a conservative scene's energy drifted beyond 1 % of its largest kinetic
    energy."""


class Result:
    """A run's trajectory in the CSV contract (plus `Q` for inverse dynamics). A partial
    one (on an exception's `.result`) has `summary["complete"]` False.

    Fields:
      t         times (rows,), s
      q, dq, ddq  positions, velocities, accelerations (rows × n), in `names` order
      Q         generalized forces (rows × n) of an inverse run, else None
      names     the coordinates of q (`Model.names`)
      columns   every column's name: t, q:<c>, dq:<c>, ddq:<c> [, Q:<c>], then the
                optional groups asked with `columns=` (`mbfg simulate --columns`)
      data      the whole table (rows × columns), float64
      summary   the run's summary line as a dict: steps, requested_steps, wall_time (s),
                mean_iterations, max_iterations, mean_factorizations, worst_phi,
                worst_velocity_constraint, energy_drift (J, conservative scenes),
                plan (what ran: schedule, window, integrator, dc_integrators, …),
                refinement, reselections, converged, complete, warnings (what
                converged but may not be right), …
      failures  the steps that did not converge (dicts), when continued past
      scene     the scene it was run on (for `animate`)
    `column(name)` is one column by name."""

    def __init__(self, raw: dict):
        # The scene (path or Model) it was run on, for `animate`; set by `simulate`.
        self.scene = None
        self.columns: list[str] = list(raw["columns"])
        # Row-major float64s in native byte order, in a bytearray: wrapped, not copied.
        self.data = np.frombuffer(raw["data"], dtype=float).reshape(raw["rows"], len(self.columns))
        if raw.get("extra_columns"):
            extra = np.asarray(raw["extra"]).reshape(raw["rows"], len(raw["extra_columns"]))
            self.data = np.hstack([self.data, extra])
            self.columns += list(raw["extra_columns"])
        self.summary: dict = raw["summary"]
        self.failures: list[dict] = raw["failures"]
        self.names = [c[2:] for c in self.columns if c.startswith("q:")]
        n = len(self.names)
        self.t = self.data[:, 0]
        self.q = self.data[:, 1:1 + n]
        self.dq = self.data[:, 1 + n:1 + 2 * n]
        self.ddq = self.data[:, 1 + 2 * n:1 + 3 * n]
        self.Q = self.data[:, 1 + 3 * n:1 + 4 * n] if len(self.columns) > 1 + 3 * n else None

    def column(self, name: str) -> np.ndarray:
        try:
            return self.data[:, self.columns.index(name)]
        except ValueError:
            raise InvalidArgument(_clip(f"no column {name!r:.60}")) from None

    def __repr__(self) -> str:
        return f"<mbfg.Result: {len(self.t)} rows, {len(self.columns)} columns, summary {self.summary}>"


def load(scene: "str | os.PathLike | Mapping | Scene | Model",
         params: Mapping[str, float] | None = None) -> Model:
    """Reads and assembles a scene: a scene (or MBSE mechanism) file's path, the text
    of one (a string with a newline or a `key:`), a dict with the file's sections, or
    an `mbfg.Scene`. `params` gives some of the scene's `parameters` other values
    (every expression using them sees the new ones); naming a parameter the scene
    does not have raises SceneError. Errors in text, dicts and Scenes name the line of
    their YAML (`Scene.to_yaml()` shows it)."""
    params = None if params is None else dict(params)
    text = _scene_text(scene)
    if text is not None:
        return Model(_native.load(text[0], params, text[1]))
    return Model(_native.load(scene._m if isinstance(scene, Model) else scene, params))


def _scene_text(scene) -> tuple[str, str] | None:
    """(name for messages, YAML text) of a scene given as text, dict or Scene; None for
    a path or a Model."""
    from .scene import to_yaml
    if isinstance(scene, Scene):
        return "<Scene>", scene.to_yaml()
    if isinstance(scene, Mapping):
        return "<dict>", to_yaml(scene)
    if isinstance(scene, str) and ("\n" in scene or (":" in scene and not os.path.exists(scene))):
        return "<string>", scene
    return None


def simulate(scene: str | os.PathLike | Model, coords: str = "dc", dt: float = 1e-3,
             t_end: float = 5.0, window: int = 1, batch: bool = False, max_iterations: int = 50,
             integrator: str = "trapezoidal", noise: str = "default",
             continue_on_failure: bool = False, past: str = "adaptive",
             dc_integrators: str = "auto", params: Mapping[str, float] | None = None, q0: Mapping[str, float] | None = None,
             dq0: Mapping[str, float] | None = None, refine: bool = True,
             effects: Mapping[str, Callable] | None = None,
             square_steps: bool = True, columns: Sequence[str] | None = None,
             until: str | None = None, rtol: float | None = None,
             atol: float | None = None, tolerance_scope: str = "run") -> Result:
    """Forward dynamics, as `mbfg simulate` runs it, of a scene (a path, text, dict or
    `mbfg.Scene`, as `load` takes) or a loaded Model, from t = 0 to `t_end` in steps of
    `dt` (s; a t_end off the step grid ends at the nearest step, and
    `summary["warnings"]` says so). Returns a `Result`.

    `coords` is "dc" (dependent, natural coordinates: every configuration) or "ic"
    (the scene's `independent` coordinates). `window` is the fixed-lag smoother's
    number of steps N_w and `batch=True` solves the whole horizon at once; where every
    step holds all its equations (IC, tangent DC) both give N_w = 1's solution and the
    steps are taken one at a time (`summary["plan"]` says what ran). `max_iterations`
    bounds the solves per window. `noise` is "default" or "paper" (the paper's Table 2
    noise models); `past` what a step leaving the window leaves behind: "adaptive"
    (the Gaussian marginal until a solve fails, then conditioning), "conditioned" or
    "marginalized". `continue_on_failure=True` goes on past a step that does not
    converge (listed in `failures`). `columns` adds the optional column groups of
    `mbfg simulate --columns`: "bodies" (angle, centre of mass position and velocity
    of every body), "energy" (kinetic, potential, work of every non-conservative
    effect, energy_balance), "joints" (the force on each body at each of its points).
    `until` ends the run where an expression of the time and the state crosses zero
    ("x(ram) - 0.3", "theta - 1.5"; names as in effects' values), as `mbfg simulate
    --until`: the rows end with the step after it, and `summary["until"]` gives the
    time `t` of the zero, located within that step, and the `step`.

    `rtol` (and `atol`, by default `rtol`) asks for error-controlled steps, as
    `mbfg simulate --rtol`: each step's size is chosen so that its estimated local
    error stays within atol + rtol·|x| per coordinate and per second simulated, and
    the rows are interpolated onto the grid of `dt`. One step at a time only
    (`window=1`); "hermite-simpson" takes the fewest. With `tolerance_scope="run"` (the
    default) the rows are checked against a run at a coarser tolerance, and the run made
    again at a tighter one where their estimated error exceeds the tolerance;
    "steps" bounds each step's error only (one run, its rows unchecked).
    `summary["error_control"]` gives the tolerance, the steps `accepted` and `rejected`,
    the `failed_solves` taken again smaller, the `smallest_step` and `largest_step` (s),
    the rows' `estimated_error` in units of the tolerance (None where `unchecked` says
    why), and the `step_rtols` of the runs made (the last one's rows returned).

    For studies without writing files: `params` overrides the scene's parameters (as
    `load` does), `q0` the initial values of coordinates of q by name (the position
    problem keeps those of independent coordinates and closes the others), `dq0` the
    initial velocities of independent coordinates. `integrator` is "trapezoidal" (the
    paper's, second order), "euler" or "hermite-simpson" (fourth order: the four-bar at
    dt = 1 ms to 2e-11 m instead of 3e-5 m). `dc_integrators` chooses the integrator
    factors of dependent coordinates: "auto", "full" (the paper's) or "tangent" (see
    `mbfg simulate --help`). Where a step is too coarse for the motion (a body turns
    over half a radian a step), the run is integrated again at dt/K (K ≤ 1024) and every
    K-th state returned, on the grid of `dt`: `summary["refinement"]` then gives K, the
    finer step and the failure that asked for it; `refine=False` fails there instead.
    `square_steps=False` sends every step through the general solver where the default
    takes an IC step, or a DC step with tangent integrators and the trapezoidal rule or
    Euler, as the sparse square system it is (the same solution to the step tolerance;
    windows and the batch then solve their graphs rather than the N_w = 1 answer).
    Ctrl-C stops the run within ~0.1 s
    with KeyboardInterrupt; that and SolveError carry the steps solved as `.result`.

    `effects` adds loads computed in Python, {name: f}: f(t, q, dq) gets the time and
    q, q̇ as 1-D float arrays in `Model.names` order and returns the generalized forces
    Q (one per coordinate of q; a torque on an angle coordinate is its entry, a force
    at a point its `P.x`, `P.y` entries). Their Jacobians are taken by forward
    differences: 2n + 1 calls per linearization, about 1 µs of Python each, so a
    controller costs far more than the same law written as a scene expression. The
    first exception f raises is raised again, carrying the steps solved as `.result`."""
    if _scene_text(scene) is not None:
        scene = load(scene)
    native = scene._m if isinstance(scene, Model) else scene
    if isinstance(columns, str):
        columns = columns.split(",")
    elif columns is not None and not isinstance(columns, (list, tuple)):
        raise InvalidArgument(_clip(f"columns must be a list of {', '.join(COLUMN_GROUPS)}, "
                                    f"got {columns!r:.60}"))
    try:
        result = _run(_native.simulate, native, coords, dt, t_end, window, batch,
                      max_iterations, integrator, noise, continue_on_failure, past,
                      dc_integrators, refine, _dict(params), _dict(q0), _dict(dq0),
                      _effects(effects), square_steps,
                      None if columns is None else [str(c).strip() for c in columns], until,
                      rtol, atol, tolerance_scope)
    except BaseException as e:
        if isinstance(getattr(e, "result", None), Result):
            e.result.scene = scene
        raise
    # What `animate` draws it with (the overridden parameters' geometry, if any).
    result.scene = scene if params is None else load(scene, params)
    return result


def animate(result: "Result", model: "Model | None" = None, out: str | os.PathLike = "mbfg.gif",
            fps: int = 25, speed: float = 1.0, trail: str | None = None,
            forces: bool = False) -> str:
    """Writes the mechanism's motion in `result` to a GIF (or an MP4 when `out` ends in
    .mp4; that needs ffmpeg): bodies as lines, fixed points as triangles, point masses
    as squares, the time in a corner. `model` (a Model or a scene path) defaults to the
    scene of a result from `simulate`. `fps` is the frames per second of the file, `speed` how much faster than
    real time it plays (2.0: twice), `trail` a point whose path is drawn behind it,
    `forces=True` the ground's reaction at every fixed point as an arrow. Slider guides
    and slots are drawn; the label gives the time and the independent angles (the speed
    of one that turns full turns).
    Returns the path written. Needs matplotlib (`pip install "mbfg[plot]"`)."""
    from .animation import animate as draw
    return draw(result, model, out, fps=fps, speed=speed, trail=trail, forces=forces)


def _dict(values):
    """A mapping as a dict for the native call; anything else as given, for the
    native call to refuse by name."""
    return dict(values) if isinstance(values, Mapping) else values


def inverse(scene: str | os.PathLike, trajectory: str | os.PathLike | Mapping[str, Sequence[float]],
            coords: str = "dc", start: str = "kinematic", max_iterations: int = 50,
            effects: Mapping[str, Callable] | None = None,
            sample_sigma: "float | str | Mapping[str, float] | None" = None) -> Result:
    """Inverse dynamics, as `mbfg inverse` runs it. `trajectory` is a CSV path or a
    mapping {"t": times, "<coordinate>": values, ...}. One batch solve: Ctrl-C takes
    effect when it returns. A SolveError carries the last iterate as `.result`.
    `coords` is "dc" or "ic" (as `mbfg inverse --coords`), `start` how the batch solve
    starts ("kinematic": the classical kinematic solution; "staged": the paper's four
    stages from the scene's configuration), `max_iterations` the solver's bound. `effects` adds loads computed in
    Python, as in `simulate`. The result's `Q` holds the generalized forces.
    `sample_sigma` (as `mbfg inverse --sample-sigma`) treats the samples as
    measurements with noise σ: a number for every column, a mapping {coordinate: σ},
    or "auto" (σ from the data); the result then has the columns sd:q:<c>, sd:dq:<c>,
    sd:ddq:<c>, sd:Q:<c> and `summary["smoothing"]`, one dict per prescribed column."""
    if isinstance(scene, Model):
        scene = scene._m
    loads = _effects(effects)
    if isinstance(trajectory, Mapping):
        columns, values = _table(trajectory)
        return _run(_native.inverse, scene, None, columns, values, coords, start, max_iterations,
                    loads, _dict(sample_sigma))
    if not isinstance(trajectory, (str, os.PathLike)):
        raise InvalidArgument(_clip("trajectory must be a CSV path or a mapping "
                                    f"{{column: values}}, got {trajectory!r:.60} "
                                    f"({type(trajectory).__name__})"))
    return _run(_native.inverse, scene, trajectory, None, None, coords, start, max_iterations,
                loads, _dict(sample_sigma))


def measure(scene: str | os.PathLike | Model,
            trajectory: "str | os.PathLike | Result | Mapping[str, Sequence[float]]",
            seed: int, rate: float | None = None) -> dict[str, np.ndarray]:
    """Noisy readings of the scene's sensors along a known motion, as `mbfg measure`
    makes them: `trajectory` is a trajectory CSV path, a `Result`, or a mapping
    {"t": times, "q:<c>": values, "dq:<c>": ..., "ddq:<c>": ...}. `seed` makes the
    noise reproducible (the same seed, the same readings, as `mbfg measure --seed`);
    `rate` (Hz) is the reading rate of the sensors without a `rate` of their own
    (default: one reading at every row). Returns {"t": times,
    "<column>": readings, ...}, NaN where a sensor does not read at that time."""
    if isinstance(scene, Model):
        scene = scene._m
    if isinstance(trajectory, Result):
        trajectory = {c: trajectory.column(c) for c in trajectory.columns}
    if isinstance(trajectory, Mapping):
        columns, values = _table(trajectory)
        raw = _native.measure(scene, None, columns, values, seed, rate)
    else:
        raw = _native.measure(scene, trajectory, None, None, seed, rate)
    out = {"t": np.asarray(raw["t"])}
    values = np.asarray(raw["values"])
    for j, c in enumerate(raw["columns"]):
        out[c] = values[:, j]
    return out


def estimate(scene: str | os.PathLike | Model,
             measurements: "str | os.PathLike | Mapping[str, Sequence[float]]",
             window: int | None = None, batch: bool = False, dt: float | None = None,
             max_iterations: int = 200, coords: str = "dc",
             integrator: str | None = None) -> dict:
    """State estimation, as `mbfg estimate` runs it: the motion from the scene's model
    and its sensors' readings. `measurements` is a CSV path (as `mbfg measure` writes
    it) or a mapping {"t": times, "<column>": readings, ...} with NaN where a sensor
    did not read. `window` is the fixed-lag smoother's (default 20); `batch=True`
    estimates every step at once. `dt` is the estimator's step (default: the readings'
    spacing), `max_iterations` the solver's bound per window, `coords` "dc" or "ic",
    `integrator` "trapezoidal" or "hermite-simpson" (default: Hermite–Simpson where the
    scene identifies parameters, the trapezoidal rule otherwise). Returns {"t": times, "q:<c>": ..., "dq:<c>": ...,
    "ddq:<c>": ..., "Q:<c>": (unknown inputs), "sd:q:<c>": σ, ..., "summary": {...}}:
    arrays of the final estimates and the run's summary (steps, window, readings, NIS
    mean, its expected value and 95 % bounds, whether it is consistent, process σ).
    With `estimation: parameters:` in the scene, "p:<name>" and "sd:p:<name>" are the
    parameters' estimates a step, and "parameters" maps each name to {"estimate",
    "sigma", "prior", "prior_sigma", "identifiable", "reason"} at the end of the
    record, "parameter_correlation" their correlation matrix in the order of
    "parameter_names"."""
    if isinstance(scene, Model):
        scene = scene._m
    def arrays(raw):
        values = np.asarray(raw["values"])
        return {c: values[:, j] for j, c in enumerate(raw["columns"])}

    try:
        if isinstance(measurements, Mapping):
            columns = list(measurements.keys())
            cols = [np.asarray(measurements[c], dtype=float) for c in columns]
            values = np.column_stack(cols).ravel().tolist() if cols else []
            raw = _native.estimate(scene, None, columns, values, window, batch, dt, max_iterations, coords,
                                   integrator)
        else:
            raw = _native.estimate(scene, measurements, None, None, window, batch, dt, max_iterations,
                                   coords, integrator)
    except SolveError as e:
        # The steps final before the failure.
        if isinstance(getattr(e, "result", None), dict):
            e.result = arrays(e.result)
        raise
    out = arrays(raw)
    out["summary"] = raw["summary"]
    for key in ("parameters", "parameter_names", "parameter_correlation"):
        out[key] = raw[key]
    return out


Estimator = _native.Estimator


def _effects(effects):
    """Python effects for the native call, each f(t, q, dq) returning a float64 array
    (q and dq arrive as numpy arrays). Anything but a mapping of callables goes through
    as given, for the native call to refuse."""
    if not isinstance(effects, Mapping):
        return effects

    def adapt(name, f):
        if not callable(f):
            return f

        def call(t, q, dq):
            value = f(t, q, dq)
            if value is None:
                return value  # refused by the native call, naming the effect
            try:
                return np.asarray(value, dtype=float)
            except (TypeError, ValueError) as e:
                raise InvalidArgument(_clip(
                    f"effect {name!r:.60} must return one generalized force per coordinate "
                    f"as numbers; it returned {type(value).__name__} at t = {t} ({e})")) from None
        return call
    return {name: adapt(name, f) for name, f in effects.items()}


def _run(native, *args) -> Result:
    """A native run as a Result; the raw partial result an exception carries is shaped
    the same way (the exception is re-raised as it came)."""
    try:
        raw = native(*args)
    except BaseException as e:
        if isinstance(getattr(e, "result", None), dict):
            e.result = Result(e.result)
        raise
    result = Result(raw)
    # A converged run that may not be right: dt too coarse for the stiffest effect,
    # energy drift of a conservative scene (summary["warnings"] keeps them too).
    for w in result.summary.get("warnings", []):
        warnings.warn(w, PlausibilityWarning, stacklevel=3)
    return result


def _table(trajectory: Mapping) -> tuple[list[str], list[float]]:
    """A mapping {column: values} as its columns and row-major values."""
    columns, arrays = [], []
    for name, v in trajectory.items():
        if not isinstance(name, str):
            raise InvalidArgument(_clip(f"trajectory: column names must be strings, got {name!r:.60}"))
        try:
            a = np.asarray(v)
        except Exception:  # ragged or odd objects: say which column
            a = None
        if a is None or a.ndim != 1 or a.dtype.kind not in "iuf":
            what = "an unreadable value" if a is None else f"shape {a.shape}, dtype {a.dtype}"
            raise InvalidArgument(_clip(f"trajectory: column {name!r:.60} must be a 1-D sequence "
                                        f"of numbers, got {what}"))
        columns.append(name)
        arrays.append(a.astype(float))
    if not arrays:
        raise InvalidArgument("trajectory: the mapping has no columns")
    lengths = {len(a) for a in arrays}
    if len(lengths) > 1:
        counts = ", ".join(f"{c}: {len(a)}" for c, a in zip(columns, arrays))
        raise InvalidArgument(_clip(f"trajectory: the columns differ in length ({counts})"))
    return columns, np.column_stack(arrays).ravel().tolist()


def _did_you_mean(name, known) -> str:
    """`; did you mean 'psi'?` for a name close to a known one, else empty."""
    import difflib
    near = difflib.get_close_matches(str(name), list(known), n=3, cutoff=0.6)
    return "; did you mean " + " or ".join(repr(k) for k in near) + "?" if near else ""


def _clip(message: str, limit: int = 300) -> str:
    """One line of at most `limit` characters, as the native module's messages."""
    flat = " ".join(message.split())
    return flat if len(flat) <= limit else flat[:limit - 1] + "…"
