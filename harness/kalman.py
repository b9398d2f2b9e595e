"""Peer state estimators for the three-simulation benchmark of Sanjurjo et al.
(Nonlinear Dynamics, 2017): the bad model corrected by noisy readings of the true one.

The filters run a (possibly wrong) scene's model in its independent coordinates z, the
scene's `independent:` list, corrected by sensor readings:

- `ErrorEKF`: the indirect (error-state) EKF. Its state is the error (Δz, Δż, Δz̈) of a
  simulation that runs alongside; each update's estimate is added to the simulation,
  which is brought back onto the constraints, and the error is reset to zero.
- `ErrorEKF(force_estimation=True)` (errorEKF-FE): the estimated acceleration error is
  turned into a generalized force ΔQ = M̄ Δz̈ (M̄ = Rᵀ M R, R = ∂q/∂z) that accumulates
  into the model's input on z: the unknown force is a random walk.
- `UKF`: filterpy's unscented Kalman filter over (z, ż), sigma points through the model.

The model steps with the trapezoidal rule on z at the readings' step dt:
z₊ = z + dt ż + dt²/4 (z̈ + z̈₊), ż₊ = ż + dt/2 (z̈ + z̈₊), z̈₊ = f(z₊, ż₊) by fixed-point
iteration, where f(z, ż) solves the position and velocity problems for q, q̇ and takes
z̈ from the constrained forward dynamics (`Model.accelerations`) plus the extra force.

Readings come as a CSV (`read_readings`): a column `t`, then one column per sensor named
by the sensor; an empty cell is no reading. `Sensor` says what a column measures:
an `encoder` reads a coordinate of q, a `gyroscope` the angular velocity of a body (from
its first two points). Every `run` returns an `Estimate`: z, ż, z̈ and their σ at every
row (and the force on z with its σ for errorEKF-FE).

Tunings (one per filter, the same for every case; SI units, dt the readings' step):
- errorEKF: Δz̈ is a random walk of intensity 10 (rad/s²)²/s (per-step variance 10 dt);
  initial σ 0.2 rad, 0.5 rad/s, 1 rad/s² on (Δz, Δż, Δz̈).
- errorEKF-FE: the force on z is a random walk of intensity 100 (N·m)²/s (mapped to Δz̈
  through M̄⁻¹ at each step), initial σ 10 N·m; σ of z, ż as errorEKF.
- UKF: white acceleration noise of intensity 1 (rad/s²)²/s on (z, ż)
  (Q = q [[dt³/3, dt²/2], [dt²/2, dt]]); initial σ 0.2 rad, 0.5 rad/s; Merwe sigma
  points alpha = 1, beta = 2, kappa = 0.
The initial σ cover the benchmark's bad start (θ0 off by π/16 ≈ 0.2 rad). The
intensities are decades: for the force, 10 N·m changing by its own size in a second;
for the accelerations, the smallest decade whose reported σ held the truth (≥ 85 % of
the steps within 2σ) on both the four-bar and the five-bar with crank encoders, on a
noise draw no test uses. z̈'s σ is propagated from (z, ż) through the linearized
dynamics (plus Δz̈ for errorEKF); the UKF's leaves out its white acceleration noise.
"""
from __future__ import annotations

import csv
import dataclasses
import math
import os
import time

import numpy as np

import mbfg

# Tunings (see the module docstring).
EKF_ACCEL_INTENSITY = 10.0
EKF_SIGMA0 = (0.2, 0.5, 1.0)
FE_FORCE_INTENSITY = 100.0
FE_FORCE_SIGMA0 = 10.0
UKF_ACCEL_INTENSITY = 1.0
UKF_SIGMA0 = (0.2, 0.5)
UKF_POINTS = dict(alpha=1.0, beta=2.0, kappa=0.0)


# ---------------------------------------------------------------- independent coordinates

class Independent:
    """A model in its independent coordinates z (the scene's `independent:` list).

    `force` arguments are generalized forces on z added to the model's own loads."""

    def __init__(self, model: mbfg.Model | str | os.PathLike):
        if not isinstance(model, mbfg.Model):
            model = mbfg.load(str(model))
        if not model.independent:
            raise ValueError("the scene declares no independent coordinates (`independent:`)")
        self.model = model
        self.names = list(model.independent)
        self.iz = np.array([model.index(c) for c in self.names], dtype=int)
        self.id = np.array([i for i in range(model.n) if i not in set(self.iz)], dtype=int)
        redundant = set(model.redundant)
        self.rows = np.array([i for i, e in enumerate(model.equations) if e not in redundant],
                             dtype=int)
        self.square = len(self.rows) == len(self.id)
        if len(self.rows) == model.m:
            self.rows = slice(None)
        self._rd = (self.rows, self.id) if isinstance(self.rows, slice) else np.ix_(self.rows, self.id)
        self.f = len(self.iz)
        self.M = model.mass_matrix()

    def _solve(self, A, b):
        return np.linalg.solve(A, b) if self.square else np.linalg.lstsq(A, b, rcond=None)[0]

    def position(self, z, guess, tol=1e-11, iterations=30) -> np.ndarray:
        """q with q[z] = z on Φ(q) = 0, Newton on the dependent coordinates from `guess`."""
        q = np.array(guess, dtype=float)
        q[self.iz] = z
        m = self.model
        for _ in range(iterations):
            phi = m.phi(q)[self.rows]
            if np.max(np.abs(phi)) < tol:
                return q
            q[self.id] -= self._solve(m.phi_q(q)[self._rd], phi)
        if np.max(np.abs(m.phi(q)[self.rows])) > 1e-8:
            raise RuntimeError(f"position problem did not converge at z = {z}")
        return q

    def R(self, q) -> np.ndarray:
        """∂q/∂z (n × f) at a consistent q."""
        A = self.model.phi_q(q)[self.rows]
        R = np.zeros((self.model.n, self.f))
        R[self.iz] = np.eye(self.f)
        R[self.id] = -self._solve(A[:, self.id], A[:, self.iz])
        return R

    def velocity(self, q, dz) -> np.ndarray:
        """q̇ with q̇[z] = ż on Φ_q q̇ = 0."""
        return self.R(q) @ np.asarray(dz, float)

    def dR(self, q, dq, R=None) -> np.ndarray:
        """∂q̇/∂z at constant ż (n × f): Φ_q S + Φ̇_q R = 0, S[z] = 0."""
        R = self.R(q) if R is None else R
        A = self.model.phi_q(q)[self.rows]
        S = np.zeros_like(R)
        S[self.id] = -self._solve(A[:, self.id], self.model.phi_q_dot(q, dq)[self.rows] @ R)
        return S

    def reduced_mass(self, q, R=None) -> np.ndarray:
        """M̄ = Rᵀ M R (f × f)."""
        R = self.R(q) if R is None else R
        return R.T @ self.M @ R

    def accelerations(self, q, dq, t, force=None) -> np.ndarray:
        """z̈ of the constrained dynamics at (q, q̇), with an extra generalized force on z
        (M̄ z̈ = Rᵀ(Q − M Ṙ ż) + force)."""
        ddz = self.model.accelerations(q, dq, t)[self.iz]
        if force is not None and np.any(force):
            ddz = ddz + np.linalg.solve(self.reduced_mass(q), force)
        return ddz

    def state(self, z, dz, guess):
        """(q, q̇) for (z, ż), q found from `guess`."""
        q = self.position(z, guess)
        return q, self.velocity(q, dz)

    def step(self, q, dq, ddz, t, dt, force=None, tol=1e-10, iterations=50):
        """One trapezoidal step from (q, q̇, z̈) at t to t + dt: (q₊, q̇₊, z̈₊)."""
        z, dz = q[self.iz], dq[self.iz]
        a = np.array(ddz, float)
        for _ in range(iterations):
            qn = self.position(z + dt * dz + dt * dt / 4 * (ddz + a), q)
            dqn = self.velocity(qn, dz + dt / 2 * (ddz + a))
            an = self.accelerations(qn, dqn, t + dt, force)
            done = np.max(np.abs(an - a)) <= tol * (1 + np.max(np.abs(an)))
            a = an
            if done:
                break
        return qn, dqn, a

    def linearization(self, q, dq, t, force=None, eps=1e-6):
        """(∂z̈/∂z, ∂z̈/∂ż) by forward differences through the position and velocity
        problems."""
        z, dz = q[self.iz], dq[self.iz]
        a0 = self.accelerations(q, dq, t, force)
        Az, Adz = np.empty((self.f, self.f)), np.empty((self.f, self.f))
        for j in range(self.f):
            e = np.zeros(self.f)
            e[j] = eps
            qj, dqj = self.state(z + e, dz, q)
            Az[:, j] = (self.accelerations(qj, dqj, t, force) - a0) / eps
            Adz[:, j] = (self.accelerations(q, self.velocity(q, dz + e), t, force) - a0) / eps
        return Az, Adz


# ---------------------------------------------------------------- sensors

@dataclasses.dataclass(frozen=True)
class Sensor:
    """A sensor: `kind` "encoder" reads the coordinate `target` of q (rad or m);
    "gyroscope" the angular velocity of the body `target` (rad/s). sigma: noise σ."""
    name: str
    kind: str
    target: str
    sigma: float

    @classmethod
    def from_mapping(cls, d: dict) -> "Sensor":
        """From a scene-like mapping: {name, type, coordinate | body, sigma}."""
        kind = d["type"]
        target = d.get("coordinate") if kind == "encoder" else d.get("body")
        if target is None:
            raise ValueError(f"sensor {d.get('name')!r}: an encoder needs `coordinate`, "
                             "a gyroscope `body`")
        return cls(d["name"], kind, target, float(d["sigma"]))


class Measurements:
    """The sensors' values h(q, q̇) and Jacobians on one model."""

    KINDS = ("encoder", "gyroscope")

    def __init__(self, ic: Independent, sensors):
        self.ic = ic
        self.sensors = list(sensors)
        m = ic.model
        points = {p["name"]: p for p in m.points}
        bodies = {b["name"]: b for b in m.bodies}
        self._spec = []
        for s in self.sensors:
            if s.kind == "encoder":
                self._spec.append(m.index(s.target))
            elif s.kind == "gyroscope":
                if s.target not in bodies:
                    raise ValueError(f"sensor {s.name!r}: no body named {s.target!r}")
                p0, p1 = (points[p] for p in bodies[s.target]["points"][:2])
                self._spec.append((p0, p1))
            else:
                raise ValueError(f"sensor {s.name!r}: unknown type {s.kind!r} "
                                 f"(one of {', '.join(self.KINDS)})")
        self.sigma = np.array([s.sigma for s in self.sensors])

    @staticmethod
    def _point(p, v, deriv=False):
        if p["fixed"]:
            return np.zeros(2) if deriv else np.array([p["x"], p["y"]])
        i = p["index"]
        return np.array([v[i], v[i + 1]])

    def values(self, q, dq, which=None) -> np.ndarray:
        """h(q, q̇) of the sensors `which` (indices; all by default)."""
        return self.evaluate(q, dq, which, jacobians=False)[0]

    def evaluate(self, q, dq, which=None, jacobians=True):
        """(h, ∂h/∂q, ∂h/∂q̇) of the sensors `which`."""
        which = range(len(self.sensors)) if which is None else which
        n = self.ic.model.n
        h = np.empty(len(which))
        Hq, Hv = (np.zeros((len(which), n)), np.zeros((len(which), n))) if jacobians else (None, None)
        for r, k in enumerate(which):
            spec = self._spec[k]
            if isinstance(spec, (int, np.integer)):
                h[r] = q[spec]
                if jacobians:
                    Hq[r, spec] = 1.0
                continue
            p0, p1 = spec
            d = self._point(p1, q) - self._point(p0, q)
            v = self._point(p1, dq, True) - self._point(p0, dq, True)
            L2 = d @ d
            w = (d[0] * v[1] - d[1] * v[0]) / L2
            h[r] = w
            if jacobians:
                gd = np.array([v[1] - 2 * d[0] * w, -v[0] - 2 * d[1] * w]) / L2
                gv = np.array([-d[1], d[0]]) / L2
                for p, sign in ((p0, -1.0), (p1, 1.0)):
                    if not p["fixed"]:
                        Hq[r, p["index"]:p["index"] + 2] += sign * gd
                        Hv[r, p["index"]:p["index"] + 2] += sign * gv
        return h, Hq, Hv

    def reduced(self, q, dq, which=None):
        """(h, ∂h/∂z, ∂h/∂ż) through R = ∂q/∂z and ∂q̇/∂z."""
        h, Hq, Hv = self.evaluate(q, dq, which)
        R = self.ic.R(q)
        S = self.ic.dR(q, dq, R)
        return h, Hq @ R + Hv @ S, Hv @ R


# ---------------------------------------------------------------- readings

@dataclasses.dataclass
class Readings:
    """Sensor readings: times t (rows,) and one column per sensor, NaN = no reading."""
    t: np.ndarray
    columns: dict

    def matrix(self, sensors) -> np.ndarray:
        """(rows, sensors) in the sensors' order."""
        missing = [s.name for s in sensors if s.name not in self.columns]
        if missing:
            raise ValueError(f"no readings for {', '.join(missing)} "
                             f"(columns: {', '.join(self.columns)})")
        return np.column_stack([self.columns[s.name] for s in sensors])


def read_readings(path) -> Readings:
    """Reads a readings CSV: a `t` column, then a column per sensor; empty = no reading."""
    with open(path, newline="") as f:
        rows = list(csv.reader(f))
    header = [h.strip() for h in rows[0]]
    if not header or header[0] != "t":
        raise ValueError(f"{path}: the first column must be `t`")
    data = np.array([[float(c) if c.strip() else np.nan for c in r] for r in rows[1:] if r],
                    dtype=float).reshape(-1, len(header))
    return Readings(data[:, 0], {h: data[:, i] for i, h in enumerate(header) if i})


def write_readings(path, readings: Readings) -> None:
    """Writes readings in the CSV format `read_readings` reads."""
    names = list(readings.columns)
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["t"] + names)
        for i, t in enumerate(readings.t):
            w.writerow([repr(float(t))] + ["" if math.isnan(v) else repr(float(v))
                                          for v in (readings.columns[c][i] for c in names)])


# ---------------------------------------------------------------- estimates

@dataclasses.dataclass
class Estimate:
    """A filter's output at every row of the readings. Arrays are (rows, f) in the order
    of `names` (the independent coordinates); force and sforce only with force
    estimation (generalized force on z, N·m or N)."""
    filter: str
    names: list
    t: np.ndarray
    z: np.ndarray
    dz: np.ndarray
    ddz: np.ndarray
    sz: np.ndarray
    sdz: np.ndarray
    sddz: np.ndarray
    force: np.ndarray | None = None
    sforce: np.ndarray | None = None
    wall_time_s: float = 0.0


def _grid(t):
    if len(t) < 2:
        raise ValueError("need at least two rows of readings")
    dt = float(t[1] - t[0])
    if dt <= 0 or np.max(np.abs(np.diff(t) - dt)) > 1e-6 * dt:
        raise ValueError("readings must be on a uniform time grid")
    return dt


class _Filter:
    def __init__(self, model, sensors):
        self.ic = model if isinstance(model, Independent) else Independent(model)
        self.meas = Measurements(self.ic, [s if isinstance(s, Sensor) else Sensor.from_mapping(s)
                                           for s in sensors])


class ErrorEKF(_Filter):
    """The indirect (error-state) EKF over (Δz, Δż, Δz̈) of a simulation of `model` (an
    `mbfg.Model`, a scene path or an `Independent`), started at its initial state.
    force_estimation: errorEKF-FE (the acceleration error accumulates into a force on z).
    accel_intensity: random-walk intensity of Δz̈, (rad/s²)²/s; sigma0: initial σ of
    (Δz, Δż, Δz̈)."""

    def __init__(self, model, sensors, force_estimation=False,
                 accel_intensity=EKF_ACCEL_INTENSITY, sigma0=EKF_SIGMA0,
                 force_intensity=FE_FORCE_INTENSITY, force_sigma0=FE_FORCE_SIGMA0):
        super().__init__(model, sensors)
        self.force_estimation = force_estimation
        self.accel_intensity = float(accel_intensity)
        self.sigma0 = tuple(float(s) for s in sigma0)
        self.force_intensity = float(force_intensity)
        self.force_sigma0 = float(force_sigma0)

    def _plant(self, q, dt):
        """Covariance of the Δz̈ increment over one step (and M̄⁻¹ for -FE)."""
        f = self.ic.f
        if not self.force_estimation:
            return self.accel_intensity * dt * np.eye(f)
        Mi = np.linalg.inv(self.ic.reduced_mass(q))
        return Mi @ (self.force_intensity * dt * np.eye(f)) @ Mi.T

    @property
    def label(self):
        return "errorEKF-FE" if self.force_estimation else "errorEKF"

    def run(self, readings: Readings) -> Estimate:
        start = time.perf_counter()
        ic, f = self.ic, self.ic.f
        t = np.asarray(readings.t, float)
        dt = _grid(t)
        Y = readings.matrix(self.meas.sensors)
        var_r = self.meas.sigma ** 2
        m = ic.model
        q, dq = np.array(m.initial_q, float), np.array(m.initial_dq, float)
        force = np.zeros(f)
        I = np.eye(f)
        Z = np.zeros((f, f))
        P = np.diag(np.repeat(np.square(self.sigma0), f))
        if self.force_estimation:
            Mi = np.linalg.inv(ic.reduced_mass(q))
            P[2 * f:, 2 * f:] = self.force_sigma0 ** 2 * Mi @ Mi.T
        Qp = np.zeros((3 * f, 3 * f))
        ddz = ic.accelerations(q, dq, t[0], force)
        rows = len(t)
        out = {k: np.empty((rows, f)) for k in ("z", "dz", "ddz", "sz", "sdz", "sddz", "F", "sF")}
        for k in range(rows):
            if k > 0:
                # Az, Adz: the linearization at the previous row's corrected state.
                h2 = dt * dt / 2
                F = np.block([[I + h2 * Az, dt * I + h2 * Adz, h2 * I],
                              [dt * Az, I + dt * Adz, dt * I],
                              [Z, Z, I]])
                Qp[2 * f:, 2 * f:] = self._plant(q, dt)
                P = F @ P @ F.T + Qp
                q, dq, ddz = ic.step(q, dq, ddz, t[k - 1], dt, force)
            delta = np.zeros(3 * f)
            which = np.flatnonzero(~np.isnan(Y[k]))
            if len(which):
                h, Hz, Hdz = self.meas.reduced(q, dq, which)
                H = np.hstack([Hz, Hdz, np.zeros((len(which), f))])
                S = H @ P @ H.T + np.diag(var_r[which])
                K = np.linalg.solve(S, H @ P).T
                delta = K @ (Y[k, which] - h)
                IKH = np.eye(3 * f) - K @ H
                P = IKH @ P @ IKH.T + K @ np.diag(var_r[which]) @ K.T
                q = ic.position(q[ic.iz] + delta[:f], q)
                dq = ic.velocity(q, dq[ic.iz] + delta[f:2 * f])
                if self.force_estimation:
                    force = force + ic.reduced_mass(q) @ delta[2 * f:]
                ddz = ic.accelerations(q, dq, t[k], force)
            Az, Adz = ic.linearization(q, dq, t[k], force)
            G = np.hstack([Az, Adz, I])
            out["z"][k], out["dz"][k] = q[ic.iz], dq[ic.iz]
            out["ddz"][k] = ddz if self.force_estimation else ddz + delta[2 * f:]
            out["sz"][k] = np.sqrt(np.diag(P)[:f])
            out["sdz"][k] = np.sqrt(np.diag(P)[f:2 * f])
            out["sddz"][k] = np.sqrt(np.diag(G @ P @ G.T))
            Mb = ic.reduced_mass(q)
            out["F"][k] = force
            out["sF"][k] = np.sqrt(np.diag(Mb @ P[2 * f:, 2 * f:] @ Mb.T))
        return Estimate(self.label, ic.names, t, out["z"], out["dz"], out["ddz"], out["sz"],
                        out["sdz"], out["sddz"],
                        out["F"] if self.force_estimation else None,
                        out["sF"] if self.force_estimation else None,
                        time.perf_counter() - start)


class UKF(_Filter):
    """filterpy's UnscentedKalmanFilter over (z, ż) of `model` (an `mbfg.Model`, a scene
    path or an `Independent`), started at its initial state; one trapezoidal model step
    per sigma point. accel_intensity: white acceleration noise, (rad/s²)²/s; sigma0:
    initial σ of (z, ż); points: MerweScaledSigmaPoints' alpha, beta, kappa."""

    label = "UKF"

    def __init__(self, model, sensors, accel_intensity=UKF_ACCEL_INTENSITY, sigma0=UKF_SIGMA0,
                 points=None):
        super().__init__(model, sensors)
        self.accel_intensity = float(accel_intensity)
        self.sigma0 = tuple(float(s) for s in sigma0)
        self.points = dict(UKF_POINTS, **(points or {}))

    def run(self, readings: Readings) -> Estimate:
        from filterpy.kalman import MerweScaledSigmaPoints, UnscentedKalmanFilter
        start = time.perf_counter()
        ic, f = self.ic, self.ic.f
        t = np.asarray(readings.t, float)
        dt = _grid(t)
        Y = readings.matrix(self.meas.sensors)
        var_r = self.meas.sigma ** 2
        m = ic.model
        ref = {"q": np.array(m.initial_q, float), "t": t[0]}

        def fx(x, dt):
            q, dq = ic.state(x[:f], x[f:], ref["q"])
            ddz = ic.accelerations(q, dq, ref["t"])
            qn, dqn, _ = ic.step(q, dq, ddz, ref["t"], dt)
            return np.concatenate([qn[ic.iz], dqn[ic.iz]])

        def hx(x, which):
            q, dq = ic.state(x[:f], x[f:], ref["q"])
            return self.meas.values(q, dq, which)

        pts = MerweScaledSigmaPoints(2 * f, **self.points)
        ukf = UnscentedKalmanFilter(dim_x=2 * f, dim_z=len(self.meas.sensors), dt=dt,
                                    hx=hx, fx=fx, points=pts)
        q0, dq0 = ref["q"], np.array(m.initial_dq, float)
        ukf.x = np.concatenate([q0[ic.iz], dq0[ic.iz]])
        ukf.P = np.diag(np.repeat(np.square(self.sigma0), f))
        qc = self.accel_intensity
        ukf.Q = np.kron(np.array([[dt ** 3 / 3, dt ** 2 / 2], [dt ** 2 / 2, dt]]) * qc, np.eye(f))
        ukf.sigmas_f = pts.sigma_points(ukf.x, ukf.P)
        rows = len(t)
        out = {k: np.empty((rows, f)) for k in ("z", "dz", "ddz", "sz", "sdz", "sddz")}
        for k in range(rows):
            if k > 0:
                ref["t"] = t[k - 1]
                ukf.predict()
                ref["q"] = ic.position(ukf.x[:f], ref["q"])
            which = np.flatnonzero(~np.isnan(Y[k]))
            if len(which):
                ukf.update(Y[k, which], R=np.diag(var_r[which]), which=which)
                ref["q"] = ic.position(ukf.x[:f], ref["q"])
            q, dq = ic.state(ukf.x[:f], ukf.x[f:], ref["q"])
            ddz = ic.accelerations(q, dq, t[k])
            Az, Adz = ic.linearization(q, dq, t[k])
            G = np.hstack([Az, Adz])
            out["z"][k], out["dz"][k], out["ddz"][k] = ukf.x[:f], ukf.x[f:], ddz
            out["sz"][k] = np.sqrt(np.diag(ukf.P)[:f])
            out["sdz"][k] = np.sqrt(np.diag(ukf.P)[f:])
            out["sddz"][k] = np.sqrt(np.diag(G @ ukf.P @ G.T))
        return Estimate(self.label, ic.names, t, out["z"], out["dz"], out["ddz"], out["sz"],
                        out["sdz"], out["sddz"], wall_time_s=time.perf_counter() - start)


def simulate(model, t, force=None) -> Estimate:
    """The model alone (open loop, σ = 0) on the times t, with the filters' integrator."""
    start = time.perf_counter()
    ic = model if isinstance(model, Independent) else Independent(model)
    t = np.asarray(t, float)
    dt = _grid(t)
    q, dq = np.array(ic.model.initial_q, float), np.array(ic.model.initial_dq, float)
    ddz = ic.accelerations(q, dq, t[0], force)
    z, dz, a = (np.empty((len(t), ic.f)) for _ in range(3))
    for k in range(len(t)):
        if k:
            q, dq, ddz = ic.step(q, dq, ddz, t[k - 1], dt, force)
        z[k], dz[k], a[k] = q[ic.iz], dq[ic.iz], ddz
    zero = np.zeros_like(z)
    return Estimate("open loop", ic.names, t, z, dz, a, zero, zero, zero,
                    wall_time_s=time.perf_counter() - start)
