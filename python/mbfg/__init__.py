"""mbfg: planar multibody dynamics as factor graphs (the Rust library, through PyO3).

    model = mbfg.load("scenes/fourbar.yaml")
    run = mbfg.simulate("scenes/fourbar.yaml", coords="dc", dt=1e-3, t_end=5.0)

The native module hands over flat lists; this layer shapes them into numpy arrays.
API reference: docs/python.md.
"""
from __future__ import annotations

import os
from typing import Mapping, Sequence

import numpy as np

from . import _native
from ._native import SceneError, SolveError, __version__

__all__ = ["Model", "Result", "SceneError", "SolveError", "inverse", "load", "simulate"]


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
            raise ValueError(f"no coordinate named '{name}' (coordinates: {', '.join(self.names)})") from None

    def mass_matrix(self) -> np.ndarray:
        return np.asarray(self._m.mass_matrix()).reshape(self.n, self.n)

    def phi(self, q) -> np.ndarray:
        return np.asarray(self._m.phi(_vec(q)))

    def phi_q(self, q) -> np.ndarray:
        return np.asarray(self._m.phi_q(_vec(q))).reshape(self.m, self.n)

    def phi_q_dot(self, q, dq) -> np.ndarray:
        return np.asarray(self._m.phi_q_dot(_vec(q), _vec(dq))).reshape(self.m, self.n)

    def generalized_forces(self, q, dq, t: float) -> np.ndarray:
        return np.asarray(self._m.generalized_forces(_vec(q), _vec(dq), float(t)))

    def accelerations(self, q, dq, t: float) -> np.ndarray:
        return np.asarray(self._m.accelerations(_vec(q), _vec(dq), float(t)))

    def effect_value(self, i: int, t: float):
        return self._m.effect_value(int(i), float(t))

    def point_position(self, q, name: str) -> tuple[float, float]:
        return self._m.point_position(_vec(q), name)

    def point_velocity(self, dq, name: str) -> tuple[float, float]:
        return self._m.point_velocity(_vec(dq), name)

    def kinetic_energy(self, dq) -> float:
        return self._m.kinetic_energy(_vec(dq))

    def potential_energy(self, q) -> float:
        return self._m.potential_energy(_vec(q))


class Result:
    """A run's trajectory in the CSV contract (plus `Q` for inverse dynamics)."""

    def __init__(self, raw: dict):
        self.columns: list[str] = raw["columns"]
        self.data = np.asarray(raw["data"], dtype=float).reshape(raw["rows"], len(self.columns))
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
            raise ValueError(f"no column '{name}'") from None

    def __repr__(self) -> str:
        return f"<mbfg.Result: {len(self.t)} rows, {len(self.columns)} columns, summary {self.summary}>"


def load(scene: str | os.PathLike) -> Model:
    """Reads and assembles a scene (or MBSE mechanism) file."""
    return Model(_native.load(os.fspath(scene)))


def simulate(scene: str | os.PathLike, coords: str = "dc", dt: float = 1e-3, t_end: float = 5.0,
             window: int = 1, batch: bool = False, max_iterations: int = 50,
             integrator: str = "trapezoidal", noise: str = "default",
             continue_on_failure: bool = False) -> Result:
    """Forward dynamics, as `mbfg simulate` runs it."""
    return Result(_native.simulate(os.fspath(scene), coords, float(dt), float(t_end), int(window),
                                   bool(batch), int(max_iterations), integrator, noise,
                                   bool(continue_on_failure)))


def inverse(scene: str | os.PathLike, trajectory: str | os.PathLike | Mapping[str, Sequence[float]],
            coords: str = "dc", start: str = "kinematic", max_iterations: int = 50) -> Result:
    """Inverse dynamics, as `mbfg inverse` runs it. `trajectory` is a CSV path or a
    mapping {"t": times, "<coordinate>": values, ...}."""
    if isinstance(trajectory, Mapping):
        columns = list(trajectory.keys())
        table = np.column_stack([np.asarray(trajectory[c], dtype=float) for c in columns])
        raw = _native.inverse(os.fspath(scene), None, columns, table.ravel().tolist(), coords,
                              start, int(max_iterations))
    else:
        raw = _native.inverse(os.fspath(scene), os.fspath(trajectory), None, None, coords, start,
                              int(max_iterations))
    return Result(raw)


def _vec(x) -> list[float]:
    return np.asarray(x, dtype=float).ravel().tolist()
