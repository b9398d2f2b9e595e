"""Quantities in the independent coordinates z (joint space) and at body-fixed points,
from a Model's natural-coordinate ones, in closed form.

With E selecting z from q, the velocities q̇ = R ż where [Φ_q; E] R = [0; I] (R is
n × f, f the degrees of freedom). The equations of motion in z are then

    M(z) z̈ + c(z, ż) = Q_z,    M(z) = RᵀMR,  Q_z = RᵀQ,  c = RᵀM q̈₀,

where q̈₀ solves Φ_q q̈₀ = −Φ̇_q q̇, E q̈₀ = 0 (the accelerations the velocities alone
cause). Redundant constraints are consistent rows of [Φ_q; E]: the systems are
solved by least squares, exact where the independent coordinates determine the
others, and refused where they do not.

A body's frame has its origin at its first point P₀ and its x axis towards the second
P₁, so a point at (ξ, η) in it is r = P₀ + (ξ e + η e⊥), e = (P₁ − P₀)/L, with L the
body's length: linear in q, its Jacobian constant."""
from __future__ import annotations

import numpy as np

# Rotation by +90°: e⊥ = S e.
_S = np.array([[0.0, -1.0], [1.0, 0.0]])


def independent_indices(model, independent) -> list[int]:
    names = model.independent if independent is None else list(independent)
    if not names:
        raise model._invalid("the scene declares no independent coordinates: pass "
                             "independent=[...] (as many as the degrees of freedom, "
                             f"{model.dof})")
    if len(names) != model.dof:
        raise model._invalid(f"independent names {len(names)} coordinate(s) "
                             f"[{', '.join(names)}], the mechanism has {model.dof} degree(s) "
                             "of freedom")
    return [model.index(n) for n in names]


def _selector(model, idx) -> np.ndarray:
    e = np.zeros((len(idx), model.n))
    e[np.arange(len(idx)), idx] = 1.0
    return e


def _solve(model, q, idx, rhs_top, rhs_bottom) -> np.ndarray:
    """x with [Φ_q; E] x = [rhs_top; rhs_bottom], refused where [Φ_q; E] loses rank."""
    a = np.vstack([model.phi_q(q), _selector(model, idx)])
    b = np.vstack([rhs_top, rhs_bottom])
    x, _, rank, sv = np.linalg.lstsq(a, b, rcond=None)
    if rank < model.n or sv[-1] <= 1e-12 * sv[0]:
        names = ", ".join(model.names[i] for i in idx)
        raise model._invalid(f"the independent coordinates [{names}] do not determine the "
                             "others at this configuration (a singular one: choose others)")
    return x


def velocity_map(model, q, independent=None) -> np.ndarray:
    """R = ∂q/∂z (n × f): q̇ = R ż on the constraints."""
    idx = independent_indices(model, independent)
    f = len(idx)
    return _solve(model, q, idx, np.zeros((model.m, f)), np.eye(f))


def bias_accelerations(model, q, dq, independent=None) -> np.ndarray:
    """q̈₀: the accelerations of the natural coordinates with z̈ = 0."""
    idx = independent_indices(model, independent)
    top = -(model.phi_q_dot(q, dq) @ np.asarray(dq, dtype=float))
    return _solve(model, q, idx, top[:, None], np.zeros((len(idx), 1)))[:, 0]


def gravity_forces(model, q) -> np.ndarray:
    """Q of the scene's gravity alone (n): m Jᵀg at every body's centre of mass (J its
    point Jacobian, constant) and m g on every point mass."""
    g = np.zeros(2)
    for e in model.effects:
        if e.get("type") == "gravity":
            g += np.asarray(e["vector"], dtype=float)
    out = np.zeros(model.n)
    for b in model.bodies:
        out += b["mass"] * (body_point_jacobian(model, b["name"], b["cog"]).T @ g)
    for p in model.points:
        if p["index"] is not None and p["mass"]:
            out[p["index"]:p["index"] + 2] += p["mass"] * g
    return out


def body_frame(model, body: str):
    """(index of P₀ or None, P₀ fixed position, index of P₁ or None, its fixed
    position, L) of a body by name."""
    bodies = {b["name"]: b for b in model.bodies}
    if body not in bodies:
        from . import _did_you_mean
        raise model._invalid(f"no body named {body!r:.60}{_did_you_mean(body, bodies)} "
                             f"(bodies: {', '.join(bodies) or 'none'})")
    b = bodies[body]
    points = {p["name"]: p for p in model.points}
    p0, p1 = (points[n] for n in b["points"][:2])
    return p0, p1, float(b["length"])


def _point_at(p, q) -> np.ndarray:
    if p["index"] is None:
        return np.array([p["x"], p["y"]], dtype=float)
    i = p["index"]
    return np.asarray(q, dtype=float)[i:i + 2].copy()


def _local(model, local) -> np.ndarray:
    v = np.asarray(local, dtype=float)
    if v.shape != (2,) or not np.all(np.isfinite(v)):
        raise model._invalid(f"local must be (x, y) in the body's frame, finite, got {local!r:.60}")
    return v


def body_point_jacobian(model, body: str, local) -> np.ndarray:
    """∂r/∂q (2 × n) of the point at `local` = (ξ, η) in `body`'s frame (constant)."""
    p0, p1, length = body_frame(model, body)
    xi, eta = _local(model, local) / length
    j = np.zeros((2, model.n))
    if p0["index"] is not None:
        j[:, p0["index"]:p0["index"] + 2] += np.eye(2) - xi * np.eye(2) - eta * _S
    if p1["index"] is not None:
        j[:, p1["index"]:p1["index"] + 2] += xi * np.eye(2) + eta * _S
    return j


def body_point_position(model, q, body: str, local) -> np.ndarray:
    """(x, y) in m of the point at `local` in `body`'s frame."""
    p0, p1, length = body_frame(model, body)
    xi, eta = _local(model, local) / length
    a, b = _point_at(p0, q), _point_at(p1, q)
    return a + xi * (b - a) + eta * (_S @ (b - a))


def point_jacobian(model, point: str) -> np.ndarray:
    """∂(x, y)/∂q (2 × n) of a named point (zero for a fixed one)."""
    points = {p["name"]: p for p in model.points}
    if point not in points:
        from . import _did_you_mean
        raise model._invalid(f"no point named {point!r:.60}{_did_you_mean(point, points)} "
                             f"(points: {', '.join(points)})")
    j = np.zeros((2, model.n))
    i = points[point]["index"]
    if i is not None:
        j[:, i:i + 2] = np.eye(2)
    return j
