"""Output-error identification: the classical peer of `mbfg estimate`'s parameters.

The parameters θ are fitted by scipy.optimize.least_squares to the readings y_k:

    min_θ  Σ_k Σ_s ((h_s(x(t_k; θ), t_k) − y_{s,k}) / σ_s)²

where each evaluation of the residual is a whole forward simulation of the model with
the parameters θ (`mbfg.simulate(scene, params=θ)`, or SUNDIALS IDA through
harness/ida.py, the classical integrator), and h_s the model's sensors
(`mbfg.Model.sensor_value`, noise free; an encoder's reading is its coordinate). The
state's start is the scene's; a scene parameter that sets it (an initial angle) can be
fitted beside the physical ones. The σ of the estimates is the classical one,
(JᵀJ)⁻¹ s², J the Jacobian of the whitened residuals at the optimum and s² their
mean square per degree of freedom.

    python -m harness.output_error SCENE READINGS.csv g=9 th0=1.24   # one fit, printed
"""
from __future__ import annotations

import argparse
import dataclasses
import math
import sys
import time
from typing import Mapping, Sequence

import numpy as np
from scipy import optimize

import mbfg

# A simulation that fails for some θ (a negative mass, a motion too fast for the step)
# gives every residual this value (whitened): far worse than any fit, so the trust
# region shrinks away from it.
FAILED_RESIDUAL = 1e3


# IDA's tolerance where `integrator="ida"` gives none: its error then sits far below the
# readings' noise, and far below the finite-difference steps' effect (DIFF_STEP).
IDA_RTOL = 1e-10
# The relative step of the Jacobian's finite differences: well above the simulations'
# own noise in θ, well below θ's σ. IDA's adaptive steps change with θ: at a step of
# 1e-6 its cost's differences are half noise (the crank-mass four-bar), at 1e-4 they
# agree with mbfg's fixed-step simulation to 0.3 %.
DIFF_STEP = 1e-6
DIFF_STEP_IDA = 1e-4


class Simulation:
    """An IDA run as the peer reads it: t, q, q̇, q̈, column(), and the model with θ."""

    def __init__(self, traj, model: mbfg.Model):
        self.t, self.q, self.dq, self.ddq = traj.t, traj.q, traj.dq, traj.ddq
        self.names, self.scene = list(traj.names), model

    def column(self, name: str) -> np.ndarray:
        group, _, c = name.partition(":")
        return {"q": self.q, "dq": self.dq, "ddq": self.ddq}[group][:, self.names.index(c)]


@dataclasses.dataclass
class Fit:
    """One output-error fit: per parameter its estimate and σ, and how the fit went."""
    names: list[str]
    estimate: dict[str, float]
    sigma: dict[str, float]
    start: dict[str, float]
    cost: float                 # ½ Σ r² of the whitened residuals at the optimum
    s2: float                   # Σ r² / (m − p)
    readings: int               # m, the residuals
    evaluations: int            # simulations run (the Jacobian's included)
    wall_s: float
    success: bool
    message: str
    failed_simulations: int = 0


class Problem:
    """The residuals of one scene against one record of readings."""

    def __init__(self, scene, readings: Mapping[str, Sequence[float]], parameters: Sequence[str],
                 sensors: Sequence[str] | None = None, integrator: str = "hermite-simpson",
                 substeps: int = 1):
        self.scene = str(scene)
        self.names = list(parameters)
        if integrator != "ida" and not integrator.startswith("ida:") and integrator not in (
                "trapezoidal", "euler", "hermite-simpson"):
            raise ValueError(f"unknown integrator {integrator!r} (expected trapezoidal, euler, "
                             "hermite-simpson, ida or ida:<rtol>)")
        self.integrator = integrator
        t = np.asarray(readings["t"], dtype=float)
        if t.ndim != 1 or len(t) < 2 or not np.all(np.diff(t) > 0):
            raise ValueError("readings: column t must hold two or more increasing times")
        dt = float(np.median(np.diff(t)))
        if abs(t[0]) > 1e-9 * max(1.0, dt) or np.max(np.abs(np.diff(t) - dt)) > 1e-6 * dt:
            raise ValueError("readings: the times must start at 0 and be evenly spaced "
                             f"(got t0 = {t[0]:g}, spacing {np.min(np.diff(t)):g}…{np.max(np.diff(t)):g} s)")
        if substeps < 1:
            raise ValueError(f"substeps must be ≥ 1, got {substeps}")
        self.t, self.dt, self.substeps = t, dt, int(substeps)
        model = mbfg.load(self.scene)
        unknown = [p for p in self.names if p not in self.scene_parameters()]
        if unknown:
            raise ValueError(f"{self.scene}: no scene parameter {', '.join(unknown)} to fit")
        spec = {s["name"]: s for s in model.sensors()}
        wanted = list(sensors) if sensors is not None else [
            s for s in spec if all(c in readings for c in spec[s]["columns"])]
        missing = [s for s in wanted if s not in spec]
        if missing:
            raise ValueError(f"{self.scene}: no sensor {', '.join(missing)}")
        if not wanted:
            raise ValueError(f"{self.scene}: none of its sensors has a column in the readings")
        # Per sensor: its columns, the readings (NaN where it did not read) and its σ.
        self.sensors = []
        for name in wanted:
            s = spec[name]
            cols = s["columns"]
            absent = [c for c in cols if c not in readings]
            if absent:
                raise ValueError(f"readings: no column {', '.join(absent)} for sensor {name!r}")
            y = np.column_stack([np.asarray(readings[c], dtype=float) for c in cols])
            self.sensors.append((name, s["type"], y, float(s["effective_sigma"])))
        self.readings = int(sum(np.isfinite(y).sum() for _, _, y, _ in self.sensors))
        self.evaluations = 0
        self.failed = 0

    def scene_parameters(self) -> set[str]:
        import yaml
        with open(self.scene) as f:
            return set((yaml.safe_load(f) or {}).get("parameters") or {})

    def simulate(self, theta) -> "mbfg.Result | Simulation":
        params = dict(zip(self.names, map(float, theta)))
        if self.integrator.startswith("ida"):
            from harness import ida
            rtol = float(self.integrator.partition(":")[2] or IDA_RTOL)
            try:
                traj, _ = ida.generate(self.scene, float(self.t[-1]), self.dt / self.substeps,
                                       rtol=rtol, params=params)
            except RuntimeError as e:
                raise mbfg.SolveError(str(e)) from None
            return Simulation(traj, mbfg.load(self.scene, params))
        r = mbfg.simulate(self.scene, dt=self.dt / self.substeps, t_end=float(self.t[-1]),
                          integrator=self.integrator, params=params)
        if len(r.t) < (len(self.t) - 1) * self.substeps + 1:
            raise mbfg.SolveError(f"the simulation ended at t = {r.t[-1]:g} s")
        return r

    def predictions(self, theta) -> list[np.ndarray]:
        """The sensors' noise-free readings along the simulation with θ, at the
        readings' times: one (rows × columns) array per sensor."""
        r = self.simulate(theta)
        rows = np.arange(len(self.t)) * self.substeps
        model = r.scene  # the scene with θ (a sensor may use a parameter)
        q, dq, ddq, t = r.q[rows], r.dq[rows], r.ddq[rows], r.t[rows]
        out = []
        for name, kind, y, _ in self.sensors:
            if kind == "encoder":
                # An encoder reads one coordinate of q: h = H q with H its constant ∂h/∂q.
                H = np.atleast_2d(model.sensor_value(name, q[0], dq[0], ddq[0], t[0])[1])
                out.append(q @ H.T)
            else:
                out.append(np.array([np.atleast_1d(model.sensor_value(name, q[k], dq[k], ddq[k], t[k])[0])
                                     for k in range(len(t))]).reshape(len(t), y.shape[1]))
        return out

    def residuals(self, theta) -> np.ndarray:
        """Whitened residuals (h − y)/σ over every reading taken."""
        self.evaluations += 1
        try:
            pred = self.predictions(theta)
        except (mbfg.SolveError, mbfg.SceneError, mbfg.InvalidArgument) as e:
            self.failed += 1
            self.last_failure = str(e)
            return np.full(self.readings, FAILED_RESIDUAL)
        parts = []
        for h, (_, _, y, sigma) in zip(pred, self.sensors):
            taken = np.isfinite(y)
            parts.append(((h - y) / sigma)[taken])
        return np.concatenate(parts)


def fit(scene, readings, start: Mapping[str, float], sensors: Sequence[str] | None = None,
        bounds: Mapping[str, tuple[float, float]] | None = None,
        integrator: str = "hermite-simpson", substeps: int = 1, max_evaluations: int = 200,
        horizons: Sequence[float] = ()) -> Fit:
    """Fits the scene parameters named in `start` (their starting values) to the
    readings (a CSV path as `mbfg measure` writes it, or {"t": …, "<column>": …} with
    NaN where a sensor did not read) by least squares over whole simulations. `sensors`
    chooses the scene's sensors compared (default: every one with its columns in the
    readings); `bounds` {name: (low, high)} keeps parameters physical (a mass > 0);
    each simulation runs `integrator` (mbfg's trapezoidal, euler or hermite-simpson at
    the readings' spacing / `substeps`; "ida" or "ida:<rtol>" for SUNDIALS IDA, sampled
    there).

    `horizons` (s) fits the first seconds of the record first, each fit starting from
    the last, then the whole record: the classical remedy for the local minima of a
    long record, whose predicted motion drifts out of phase with the readings when
    the start is far off. Every stage's simulations count in the wall time."""
    if not isinstance(readings, Mapping):
        readings = read_readings(readings)
    names = list(start)
    t = np.asarray(readings["t"], dtype=float)
    stages = [h for h in sorted(horizons) if h < t[-1]] + [None]
    x0 = np.array([float(start[n]) for n in names])
    lo = np.array([(bounds or {}).get(n, (-np.inf, np.inf))[0] for n in names], dtype=float)
    hi = np.array([(bounds or {}).get(n, (-np.inf, np.inf))[1] for n in names], dtype=float)
    # Relative finite-difference steps at each parameter's own scale.
    scale = np.maximum(np.abs(x0), 1e-3)
    began = time.perf_counter()
    x, evaluations, failed = x0, 0, 0
    for h in stages:
        part = readings if h is None else {c: np.asarray(v)[t <= h + 1e-9] for c, v in readings.items()}
        prob = Problem(scene, part, names, sensors, integrator, substeps)
        res = optimize.least_squares(prob.residuals, x, bounds=(lo, hi), x_scale=scale,
                                     method="trf", jac="2-point",
                                     diff_step=DIFF_STEP_IDA if integrator.startswith("ida") else DIFF_STEP,
                                     max_nfev=max_evaluations)
        x, evaluations, failed = res.x, evaluations + prob.evaluations, failed + prob.failed
    wall = time.perf_counter() - began
    m, p = len(res.fun), len(names)
    s2 = float(res.fun @ res.fun / max(m - p, 1))
    try:
        cov = np.linalg.inv(res.jac.T @ res.jac) * s2
        sd = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    except np.linalg.LinAlgError:
        sd = np.full(p, np.inf)
    return Fit(names=names, estimate=dict(zip(names, map(float, res.x))),
               sigma=dict(zip(names, map(float, sd))), start=dict(zip(names, map(float, x0))),
               cost=float(res.cost), s2=s2, readings=m, evaluations=evaluations,
               wall_s=wall, success=bool(res.success) and prob.failed < prob.evaluations,
               message=str(res.message), failed_simulations=failed)


def read_readings(path) -> dict[str, np.ndarray]:
    """A measurement CSV (`mbfg measure`'s) as {column: array}; empty cells are NaN."""
    with open(path) as f:
        header = f.readline().strip().split(",")
        rows = [line.rstrip("\n").split(",") for line in f if line.strip()]
    data = np.array([[float(v) if v not in ("", "nan", "NaN") else math.nan for v in r]
                     for r in rows])
    return {h: data[:, i] for i, h in enumerate(header)}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m harness.output_error",
                                 description=__doc__.split("\n\n")[0])
    ap.add_argument("scene")
    ap.add_argument("readings")
    ap.add_argument("start", nargs="+", help="name=value: a parameter to fit and its start")
    ap.add_argument("--integrator", default="hermite-simpson")
    ap.add_argument("--substeps", type=int, default=1)
    args = ap.parse_args(argv)
    start = {}
    for item in args.start:
        name, _, value = item.partition("=")
        if not value:
            ap.error(f"expected name=value, got {item!r}")
        start[name] = float(value)
    f = fit(args.scene, args.readings, start, integrator=args.integrator, substeps=args.substeps)
    for n in f.names:
        print(f"{n}: {f.estimate[n]:.6g} ± {f.sigma[n]:.3g} (start {f.start[n]:g})")
    print(f"{f.evaluations} simulations in {f.wall_s:.2f} s; s² = {f.s2:.3g} over {f.readings} "
          f"readings; {f.message}")
    return 0 if f.success else 1


if __name__ == "__main__":
    sys.exit(main())
