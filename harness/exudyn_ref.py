"""Reference trajectories from exudyn: the scene rebuilt as planar rigid bodies.

mbfg integrates natural coordinates (the x, y of points). This generator is a
genuinely different formulation of the same mechanism: every scene body becomes an
exudyn `ObjectRigidBody2D` whose node holds its centre of mass and its rotation
(x, y, ψ); scene points become markers on those bodies, a point shared by two bodies a
`RevoluteJoint2D`, a fixed point a revolute joint to ground, a slider a
`PrismaticJoint2D` that keeps only its point-on-line equation. The motion is mapped
back to the scene's coordinates (points from the bodies that carry them; angles and
distances from the points, with their rates by exact differentiation) and sampled.

Anything the generator cannot model raises `Unsupported`; nothing is dropped.

    python -m harness.exudyn_ref scenes/fourbar.yaml --t-end 5 --dt 1e-3 --h 1e-5 \
        --solver generalized_alpha --out fourbar.csv.gz

The default step h = 1e-4 takes under a second on the four-bar over 5 s (RMSE 6e-7 m);
the committed references' cross-checks use 1e-5 (15 s, 3e-9 m).
"""
from __future__ import annotations

import argparse
import dataclasses
import math
import pathlib
import sys
import time

import numpy as np

import exudyn as exu
import exudyn.itemInterface as ei
import mbfg
from harness import trajectory as tj
from harness.scene_file import SceneFile
from harness.trajectory import Unsupported

SOLVERS = {
    "generalized_alpha": exu.DynamicSolverType.GeneralizedAlpha,
    "trapezoidal_index2": exu.DynamicSolverType.TrapezoidalIndex2,
}


class ConstantLoad:
    """A constant in place of a load expression."""
    names: set = set()

    def __init__(self, value: float):
        self.value = value

    def __call__(self, env) -> float:
        return self.value


class _EnvLoad:
    """A load of the state computed by the generator (not a scene expression)."""
    names = {"state"}

    def __init__(self, fn):
        self.fn = fn

    def __call__(self, env) -> float:
        return self.fn(env)


class SolveError(RuntimeError):
    """exudyn's solve failed (a step's Newton iteration, a singular Jacobian)."""


# Newton tolerances with a load of the state (exudyn's defaults), see generate().
STATE_LOAD_RTOL, STATE_LOAD_ATOL = 1e-8, 1e-10

# Inertia given to the rotation of a lone point mass (a rigid body node, so that a
# slider can hold it): the rotation is coupled to nothing and stays at rest.
POINT_INERTIA = 1.0


# --- second-order jets: value, first and second time derivative -----------------
# The relative coordinates and their rates follow from the points' positions,
# velocities and accelerations by the chain rule; jets do it once for all formulas.

@dataclasses.dataclass
class Jet:
    v: np.ndarray
    d: np.ndarray
    dd: np.ndarray

    def __add__(self, o): return Jet(self.v + o.v, self.d + o.d, self.dd + o.dd)
    def __sub__(self, o): return Jet(self.v - o.v, self.d - o.d, self.dd - o.dd)

    def __mul__(self, o):
        return Jet(self.v * o.v, self.d * o.v + self.v * o.d,
                   self.dd * o.v + 2 * self.d * o.d + self.v * o.dd)

    def __truediv__(self, o):
        r = Jet(1 / o.v, -o.d / o.v ** 2, 2 * o.d ** 2 / o.v ** 3 - o.dd / o.v ** 2)
        return self * r


def jet_sqrt(a: Jet) -> Jet:
    s = np.sqrt(a.v)
    return Jet(s, a.d / (2 * s), a.dd / (2 * s) - a.d ** 2 / (4 * s ** 3))


def jet_atan2(y: Jet, x: Jet) -> Jet:
    """atan2 continued without jumps along the samples (np.unwrap)."""
    r2 = x.v ** 2 + y.v ** 2
    num = x.v * y.d - y.v * x.d
    d = num / r2
    dd = (x.v * y.dd - y.v * x.dd) / r2 - num * (2 * x.v * x.d + 2 * y.v * y.d) / r2 ** 2
    return Jet(np.unwrap(np.arctan2(y.v, x.v)), d, dd)


# --- the mechanism as rigid bodies ---------------------------------------------------

@dataclasses.dataclass
class Body:
    """An exudyn rigid body: a scene body (with the point masses it carries) or a lone
    point mass. Local positions are in the frame at the centre of mass turned by psi0."""
    name: str
    mass: float
    inertia: float                  # about the centre of mass
    c0: np.ndarray                  # centre of mass at t = 0
    psi0: float                     # orientation at t = 0
    v0: np.ndarray                  # velocity of the centre at t = 0
    omega0: float
    points: list[str]
    node: int = -1
    obj: int = -1

    def local(self, p: np.ndarray) -> np.ndarray:
        c, s = math.cos(self.psi0), math.sin(self.psi0)
        d = p - self.c0
        return np.array([c * d[0] + s * d[1], -s * d[0] + c * d[1]])


def rotate(psi: float, v: np.ndarray) -> np.ndarray:
    c, s = math.cos(psi), math.sin(psi)
    return np.array([c * v[0] - s * v[1], s * v[0] + c * v[1]])


def cross(a, b) -> float:
    return a[0] * b[1] - a[1] * b[0]


class Mechanism:
    """The scene model built into an exudyn MainSystem."""

    def __init__(self, model: mbfg.Model, scene: SceneFile):
        # Everything but the assembled initial state comes from the harness's own reading
        # of the file (scene_file.py), checked against mbfg's before this is built.
        self.model = model
        self.scene = scene
        names = list(model.names)
        self.points = [{"name": n, "fixed": p.fixed, "mass": p.mass,
                        "index": None if p.fixed else names.index(f"{n}.x")}
                       for n, p in scene.points.items()]
        self.pos = scene.positions(model.initial_q)
        self.vel = scene.positions(model.initial_dq)
        self.fixed = {n for n, p in scene.points.items() if p.fixed}
        for n in self.fixed:
            self.vel[n] = np.zeros(2)
        self.coords = {c["name"]: dict(c, index=names.index(c["name"]))
                       for c in scene.coordinates}
        self.notes: list[str] = []       # modelling decisions worth recording
        self._last: dict[str, float] = {}  # angles read from points: the branch last seen
        self.state_loads = False
        self._env_key, self._env, self._locals = None, None, None
        self.bodies = self._bodies()
        # The body whose marker stands for a free point (its first body).
        self.carrier = {}
        for k, b in enumerate(self.bodies):
            for p in b.points:
                if p not in self.fixed:
                    self.carrier.setdefault(p, k)
        for p in self.points:
            if p["name"] not in self.fixed and p["name"] not in self.carrier:
                raise Unsupported(f"point {p['name']} is free but on no body and carries no mass")
        self._terms = {}                 # angle coordinates that are sums of body rotations
        for name in self.coords:
            try:
                self._terms[name] = self.coordinate_segments(name)
            except Unsupported:
                pass
        self.SC = exu.SystemContainer()
        self.mbs = self.SC.AddSystem()
        self._markers: dict = {}
        self.sensors: list[tuple[int, int, int]] = []
        self.joints: dict[str, int] = {}  # a scene constraint -> its exudyn object
        self._build()

    # -- bodies --------------------------------------------------------------------

    def _bodies(self) -> list[Body]:
        pos, vel = self.pos, self.vel
        masses = {p["name"]: p["mass"] for p in self.points if p["mass"] > 0 and not p["fixed"]}
        out = []
        for b in self.scene.bodies:
            pts = b.points
            if sum(p not in self.fixed for p in pts) == 0:
                raise Unsupported(f"body {b.name} has only fixed points")
            if sum(p in self.fixed for p in pts) > 1:
                raise Unsupported(f"body {b.name} has more than one fixed point (it cannot move; "
                                  "the joints to ground would be redundant)")
            p0, p1 = pos[pts[0]], pos[pts[1]]
            e = p1 - p0
            psi = math.atan2(e[1], e[0])
            c = p0 + rotate(psi, b.cog)
            omega = cross(e, vel[pts[1]] - vel[pts[0]]) / (e @ e)
            m, inertia = b.mass, b.inertia
            # A point mass rides on the first body that carries it: the body's mass,
            # centre and inertia become those of the pair (exact for a rigid pair).
            for p in pts:
                if p in masses:
                    mp = masses.pop(p)
                    cn = (m * c + mp * pos[p]) / (m + mp)
                    inertia += m * np.sum((c - cn) ** 2) + mp * np.sum((pos[p] - cn) ** 2)
                    m, c = m + mp, cn
                    self.notes.append(f"point mass of {p} added to body {b.name}")
            v = vel[pts[0]] + omega * np.array([-(c - p0)[1], (c - p0)[0]])
            out.append(Body(b.name, m, inertia, c, psi, v, omega, list(pts)))
        # A point mass on no body: a rigid body of its own, centred on the point.
        for p, mp in masses.items():
            out.append(Body(f"point {p}", mp, mp * POINT_INERTIA, pos[p].copy(), 0.0,
                            vel[p].copy(), 0.0, [p]))
            self.notes.append(f"lone point mass {p}: rigid body with a free, uncoupled rotation")
        return out

    # -- markers -------------------------------------------------------------------

    def _ground_marker(self, p: np.ndarray, rigid: bool) -> int:
        key = ("ground", tuple(p), rigid)
        if key not in self._markers:
            cls = ei.MarkerBodyRigid if rigid else ei.MarkerBodyPosition
            self._markers[key] = self.mbs.AddMarker(cls(bodyNumber=self.ground,
                                                        localPosition=[p[0], p[1], 0.0]))
        return self._markers[key]

    def _body_marker(self, k: int, p: np.ndarray, rigid: bool) -> int:
        key = (k, tuple(p), rigid)
        if key not in self._markers:
            cls = ei.MarkerBodyRigid if rigid else ei.MarkerBodyPosition
            loc = self.bodies[k].local(p)
            self._markers[key] = self.mbs.AddMarker(cls(bodyNumber=self.bodies[k].obj,
                                                        localPosition=[loc[0], loc[1], 0.0]))
        return self._markers[key]

    def marker(self, point: str, body: int | None = None, rigid: bool = False) -> int:
        """Marker at a scene point: on ground if it is fixed, else on `body` (default:
        its carrier)."""
        if point in self.fixed:
            return self._ground_marker(self.pos[point], rigid)
        k = self.carrier[point] if body is None else body
        return self._body_marker(k, self.pos[point], rigid)

    def segment_body(self, a: str, b: str) -> int | None:
        """The body both points are on (None: both fixed, the segment is ground)."""
        if a in self.fixed and b in self.fixed:
            return None
        for k, body in enumerate(self.bodies):
            if a in body.points and b in body.points:
                return k
        raise Unsupported(f"the segment {a}→{b} is on no single body: its angle is not a body "
                          "rotation")

    def rotation_marker(self, k: int | None) -> int:
        """Coordinate marker on a body's rotation (its displacement from psi0)."""
        key = ("rot", k)
        if key not in self._markers:
            if k is None:
                self._markers[key] = self.mbs.AddMarker(ei.MarkerNodeCoordinate(
                    nodeNumber=self.ground_node, coordinate=0))
            else:
                self._markers[key] = self.mbs.AddMarker(ei.MarkerNodeCoordinate(
                    nodeNumber=self.bodies[k].node, coordinate=2))
        return self._markers[key]

    def rigid_marker(self, k: int | None) -> int:
        key = ("rigid", k)
        if key not in self._markers:
            num = self.ground if k is None else self.bodies[k].obj
            self._markers[key] = self.mbs.AddMarker(ei.MarkerBodyRigid(bodyNumber=num,
                                                                      localPosition=[0, 0, 0]))
        return self._markers[key]

    def coordinate_segments(self, name: str) -> list[tuple[int | None, float]]:
        """An angle coordinate as (body, sign) terms: θ = Σ sign · ψ_body + constant."""
        c = self.coords.get(name)
        if c is None:
            raise Unsupported(f"effect on '{name}', which is not a relative coordinate")
        pts = c["points"]
        if c["type"] == "angle":
            return [(self.segment_body(pts[0], pts[1]), 1.0)]
        if c["type"] == "relative_angle":
            return [(self.segment_body(pts[0], pts[1]), -1.0),
                    (self.segment_body(pts[2], pts[3]), 1.0)]
        raise Unsupported(f"a torque or rotational spring on the {c['type']} coordinate {name}")

    # -- the system ----------------------------------------------------------------

    def _build(self):
        mbs, model = self.mbs, self.model
        for name in model.redundant:
            if name not in {c["name"] for c in self.scene.constraints}:
                raise Unsupported(f"redundant equation '{name}' (a rigid-body or coordinate "
                                  "equation): exudyn's joints would be redundant too")
        self.ground = mbs.AddObject(ei.ObjectGround())
        self.ground_node = mbs.AddNode(ei.NodePointGround())
        for k, b in enumerate(self.bodies):
            b.node = mbs.AddNode(ei.NodeRigidBody2D(
                referenceCoordinates=[b.c0[0], b.c0[1], b.psi0],
                initialVelocities=[b.v0[0], b.v0[1], b.omega0]))
            b.obj = mbs.AddObject(ei.ObjectRigidBody2D(mass=b.mass, inertia=b.inertia,
                                                       nodeNumber=b.node))
            for var in (exu.OutputVariableType.Coordinates, exu.OutputVariableType.Coordinates_t,
                        exu.OutputVariableType.Coordinates_tt):
                self.sensors.append(mbs.AddSensor(ei.SensorNode(
                    nodeNumber=b.node, storeInternal=True, writeToFile=False,
                    outputVariableType=var)))
        # Joints: each point ties every further body on it to its carrier; fixed points
        # tie bodies to ground.
        for k, b in enumerate(self.bodies):
            for p in b.points:
                if p in self.fixed or self.carrier[p] != k:
                    mbs.AddObject(ei.ObjectJointRevolute2D(markerNumbers=[
                        self.marker(p), self._body_marker(k, self.pos[p], rigid=False)]))
        redundant = set(model.redundant)
        for c in self.scene.constraints:
            if c["name"] in redundant:
                # mbfg leaves it out as implied by the others; exudyn's solver would meet
                # a singular Jacobian with it.
                self.notes.append(f"constraint {c['name']} left out: redundant")
                continue
            if c["type"] == "distance":
                a, b = c["points"]
                self.joints[c["name"]] = mbs.AddObject(ei.ObjectConnectorDistance(
                    markerNumbers=[self.marker(a), self.marker(b)], distance=c["length"]))
            elif c["type"] in ("fixed_slider", "mobile_slider"):
                self.joints[c["name"]] = self._slider(c)
            else:
                raise Unsupported(f"constraint {c['name']} of type {c['type']}")
        for e in self.scene.effects:
            self._effect(e)
        mbs.Assemble()

    def _slider(self, c):
        """Point on a line: PrismaticJoint2D without its rotation equation. Its normal is
        given in the frame of its second marker, which must therefore carry the line."""
        p, l0, l1 = c["points"]
        if l0 in self.fixed and l1 in self.fixed:
            k = None
        else:
            try:
                k = self.segment_body(l0, l1)
            except Unsupported:
                raise Unsupported(f"slider {c['name']}: its line {l0}–{l1} is on no single body")
        if p in self.fixed:
            raise Unsupported(f"slider {c['name']}: its point {p} is fixed")
        e = self.pos[l1] - self.pos[l0]
        n = np.array([-e[1], e[0]]) / np.hypot(*e)
        if k is not None:
            if self.carrier[p] == k:
                raise Unsupported(f"slider {c['name']}: point and line on the same body")
            n = rotate(-self.bodies[k].psi0, n)
            line = self._body_marker(k, self.pos[l0], rigid=True)
        else:
            line = self._ground_marker(self.pos[l0], rigid=True)
        return self.mbs.AddObject(ei.ObjectJointPrismatic2D(
            markerNumbers=[self.marker(p, rigid=True), line],
            axisMarker0=[1.0, 0.0, 0.0], normalMarker1=[n[0], n[1], 0.0],
            constrainRotation=False))

    def _effect(self, e):
        mbs = self.mbs
        kind, spec = e.type, e.spec
        if kind == "gravity":
            g = spec["vector"]
            for b in self.bodies:
                m = mbs.AddMarker(ei.MarkerBodyMass(bodyNumber=b.obj))
                mbs.AddLoad(ei.LoadMassProportional(markerNumber=m, loadVector=[g[0], g[1], 0.0]))
        elif kind == "spring_damper":
            a, b = spec["points"]
            mbs.AddObject(ei.ObjectConnectorSpringDamper(
                markerNumbers=[self.marker(a), self.marker(b)], referenceLength=spec["rest_length"],
                stiffness=spec["stiffness"], damping=spec["damping"]))
        elif kind == "force":
            p = spec["point"]
            if p in self.fixed:
                return                   # does no work
            fx, fy = spec["value"]
            mbs.AddLoad(ei.LoadForceVector(markerNumber=self.marker(p), **self._load(
                (fx, fy), lambda env: [fx(env), fy(env), 0.0])))
        elif kind in ("torque", "dc_motor") and spec["coordinate"] not in self._terms:
            name = spec["coordinate"]
            if kind == "torque":
                (tau,) = spec["value"]
            else:
                stall, w0 = spec["stall_torque"], spec["no_load_speed"]
                tau = _EnvLoad(lambda env: stall * (1.0 - env[f"rate({name})"] / w0))
            self._segment_forces(name, tau)
        elif kind in ("torque", "dc_motor"):
            name = spec["coordinate"]
            if kind == "torque":
                (tau,) = spec["value"]
            else:
                # T_s (1 − θ̇/ω₀): a constant torque T_s and a damper T_s/ω₀ on θ.
                stall = spec["stall_torque"]
                tau = ConstantLoad(stall)
                self._rotational(name, 0.0, stall / spec["no_load_speed"], 0.0)
            for k, sign in self.coordinate_segments(name):
                if k is None:
                    continue             # the ground takes it
                mbs.AddLoad(ei.LoadTorqueVector(markerNumber=self.rigid_marker(k), **self._load(
                    (tau,), lambda env, s=sign, tau=tau: [0.0, 0.0, s * tau(env)])))
        elif kind == "rotational_spring_damper" and spec["coordinate"] not in self._terms:
            name, k, c, rest = (spec[x] for x in ("coordinate", "stiffness", "damping", "rest_angle"))
            self._segment_forces(name, _EnvLoad(
                lambda env: -k * (env[name] - rest) - c * env[f"rate({name})"]))
        elif kind == "rotational_spring_damper":
            self._rotational(spec["coordinate"], spec["stiffness"], spec["damping"],
                             spec["rest_angle"])
        else:
            raise Unsupported(f"effect {e.name!r} of type {kind}")

    def _segment_forces(self, name: str, tau):
        """A generalized force τ on an angle whose segment no single body carries (its
        points tied by a distance): the forces at the segment's ends that do its work,
        τ ∂θ/∂r, with ∂θ/∂r_b = (−d_y, d_x)/|d|² for d = r_b − r_a."""
        c = self.coords[name]
        pts = c["points"]
        segs = ([(pts[0], pts[1], 1.0)] if c["type"] == "angle"
                else [(pts[0], pts[1], -1.0), (pts[2], pts[3], 1.0)])
        for a, b, sign in segs:
            for end, side in ((a, -1.0), (b, 1.0)):
                if end in self.fixed:
                    continue

                def force(env, a=a, b=b, k=sign * side):
                    dx, dy = env[f"x({b})"] - env[f"x({a})"], env[f"y({b})"] - env[f"y({a})"]
                    f = k * tau(env) / (dx * dx + dy * dy)
                    return [-f * dy, f * dx, 0.0]
                self.mbs.AddLoad(ei.LoadForceVector(markerNumber=self.marker(end), **self._load(
                    (_EnvLoad(None),), force)))

    def _rotational(self, name: str, stiffness: float, damping: float, rest: float):
        terms = self.coordinate_segments(name)
        if len(terms) == 1:
            terms = [(None, -1.0)] + terms
        (ka, _), (kb, _) = terms
        # θ = θ(0) + Δψ_b − Δψ_a; the connector acts on Δψ_b − Δψ_a − offset.
        theta0 = self.model.initial_q[self.coords[name]["index"]]
        self.mbs.AddObject(ei.ObjectConnectorCoordinateSpringDamper(
            markerNumbers=[self.rotation_marker(ka), self.rotation_marker(kb)],
            stiffness=stiffness, damping=damping, offset=rest - theta0))

    def _load(self, values, vector):
        """A load's arguments: a constant vector when every value is constant (a Python
        user function costs a call per residual), else a function of time and, when a
        value reads the state, of the bodies' current coordinates."""
        names = set().union(*(v.names for v in values))
        if not names:
            return {"loadVector": vector({})}
        if names <= {"t"}:
            return {"loadVectorUserFunction": lambda mbs, t, v: vector({"t": t})}
        if not self.state_loads:
            self.notes.append("state-dependent loads: Python user functions of the bodies' "
                              "current state (their Jacobian is not in exudyn's Newton matrix)")
        self.state_loads = True
        return {"loadVectorUserFunction": lambda mbs, t, v: vector(self.state_env(t))}

    def state_env(self, t: float) -> dict:
        """The expressions' variables (docs/scene-format.md, section 8) at exudyn's
        current state: points, coordinates, bodies' angles and rates. Several loads ask
        at the same state in a row: the last answer is kept."""
        mbs, Out = self.mbs, exu.OutputVariableType
        raw = [(mbs.GetNodeOutput(b.node, Out.Coordinates), mbs.GetNodeOutput(b.node, Out.Coordinates_t))
               for b in self.bodies]
        key = (t, tuple(float(x) for u, du in raw for x in (*u, *du)))
        if self._env_key == key:
            return self._env
        if self._locals is None:
            self._locals = [[(p, *b.local(self.pos[p])) for p in b.points
                             if p not in self.fixed and self.carrier[p] == k]
                            for k, b in enumerate(self.bodies)]
        env = {"t": t}
        pos, vel = {}, {}
        psi = []
        for k, (b, (u, du)) in enumerate(zip(self.bodies, raw)):
            ang, w = b.psi0 + u[2], du[2]
            psi.append((u[2], w))
            c, s = math.cos(ang), math.sin(ang)
            cx, cy = b.c0[0] + u[0], b.c0[1] + u[1]
            for p, lx, ly in self._locals[k]:
                rx, ry = c * lx - s * ly, s * lx + c * ly
                pos[p] = (cx + rx, cy + ry)
                vel[p] = (du[0] - w * ry, du[1] + w * rx)
        for p in self.fixed:
            pos[p], vel[p] = tuple(self.pos[p]), (0.0, 0.0)
        for p in pos:
            env[f"x({p})"], env[f"y({p})"] = pos[p]
            env[f"vx({p})"], env[f"vy({p})"] = vel[p]

        def seg(a, b):
            d = (pos[b][0] - pos[a][0], pos[b][1] - pos[a][1])
            dv = (vel[b][0] - vel[a][0], vel[b][1] - vel[a][1])
            return d, dv, cross(d, dv) / (d[0] ** 2 + d[1] ** 2)
        for b in self.scene.bodies:
            d, _, w = seg(b.points[0], b.points[1])
            env[f"angle({b.name})"], env[f"omega({b.name})"] = math.atan2(d[1], d[0]), w
        for name, c in self.coords.items():
            theta0 = self.model.initial_q[c["index"]]
            pts = c["points"]
            if c["type"] == "distance":
                p, a, b = pts
                e, de, _ = seg(a, b)
                w, dw, _ = seg(a, p)
                L = self.scene.segment_length(a, b)
                env[name] = (w[0] * e[0] + w[1] * e[1]) / L
                env[f"rate({name})"] = (dw[0] * e[0] + dw[1] * e[1] + w[0] * de[0] + w[1] * de[1]) / L
            elif name in self._terms:     # a sum of body rotations: continuous, exact
                terms = self._terms[name]
                env[name] = theta0 + sum(sg * psi[k][0] for k, sg in terms if k is not None)
                env[f"rate({name})"] = sum(sg * psi[k][1] for k, sg in terms if k is not None)
            else:
                near = self._last.get(name, theta0)
                env[name] = self.scene.coordinate_value(c, {n: np.array(v) for n, v in pos.items()}, near)
                self._last[name] = env[name]
                rates = [seg(a, b)[2] for a, b in ([pts[:2]] if c["type"] == "angle"
                                                   else [pts[:2], pts[2:]])]
                env[f"rate({name})"] = rates[0] if len(rates) == 1 else rates[1] - rates[0]
        self._env_key, self._env = key, env
        return env

    def reaction(self, name: str, raw: np.ndarray, traj: tj.Trajectory) -> np.ndarray:
        """A constraint's force over the samples, from exudyn's joint output, in the
        terms of `--columns constraints`: a distance's tension (exudyn's connector force,
        as it is); a slider's normal force on its point along the guide's left normal
        (the prismatic joint's force, given in the frame of the point's body, turned to
        global axes and projected on that normal)."""
        c = next(c for c in self.scene.constraints if c["name"] == name)
        if c["type"] == "distance":
            return raw[:, 0].copy()
        p, l0, l1 = c["points"]
        k = self.carrier[p]
        data = self.mbs.GetSensorStoredData(self.sensors[3 * k])
        psi = self.bodies[k].psi0 + data[:, 3]
        cs, sn = np.cos(psi), np.sin(psi)
        fx, fy = cs * raw[:, 0] - sn * raw[:, 1], sn * raw[:, 0] + cs * raw[:, 1]

        def at(n):
            if n in self.fixed:
                return np.broadcast_to(self.pos[n], (len(traj.t), 2))
            i = traj.names.index(f"{n}.x")
            return traj.q[:, i:i + 2]
        e = at(l1) - at(l0)
        e = e / np.hypot(e[:, 0], e[:, 1])[:, None]
        return -e[:, 1] * fx + e[:, 0] * fy

    # -- the motion in the scene's coordinates ------------------------------------

    def trajectory(self, t_expected: np.ndarray) -> tj.Trajectory:
        model = self.model
        data = [self.mbs.GetSensorStoredData(s) for s in self.sensors]
        t = data[0][:, 0]
        if len(t) != len(t_expected) or np.max(np.abs(t - t_expected)) > 1e-9 * max(1.0, t[-1]):
            raise RuntimeError(f"exudyn stored {len(t)} samples, expected {len(t_expected)} "
                               "at the multiples of the sampling step")
        rows = len(t)
        jets: dict[str, tuple[Jet, Jet]] = {}
        for k, b in enumerate(self.bodies):
            u, du, ddu = (d[:, 1:4] for d in data[3 * k:3 * k + 3])
            psi, w, al = b.psi0 + u[:, 2], du[:, 2], ddu[:, 2]
            cx, cy = b.c0[0] + u[:, 0], b.c0[1] + u[:, 1]
            for p in b.points:
                if p in self.fixed or self.carrier[p] != k:
                    continue
                loc = b.local(self.pos[p])
                c, s = np.cos(psi), np.sin(psi)
                rx, ry = c * loc[0] - s * loc[1], s * loc[0] + c * loc[1]
                jets[p] = (Jet(cx + rx, du[:, 0] - w * ry, ddu[:, 0] - al * ry - w ** 2 * rx),
                           Jet(cy + ry, du[:, 1] + w * rx, ddu[:, 1] + al * rx - w ** 2 * ry))
        zero = np.zeros(rows)
        for p in self.fixed:
            x, y = self.pos[p]
            jets[p] = (Jet(zero + x, zero, zero), Jet(zero + y, zero, zero))

        n = model.n
        q, dq, ddq = np.zeros((rows, n)), np.zeros((rows, n)), np.zeros((rows, n))
        for p in self.points:
            if p["index"] is not None:
                for j, jet in enumerate(jets[p["name"]]):
                    q[:, p["index"] + j], dq[:, p["index"] + j], ddq[:, p["index"] + j] = \
                        jet.v, jet.d, jet.dd

        def angle(a, b):
            (ax, ay), (bx, by) = jets[a], jets[b]
            return jet_atan2(by - ay, bx - ax)

        for c in self.coords.values():
            pts = c["points"]
            if c["type"] == "angle":
                j = angle(pts[0], pts[1])
            elif c["type"] == "relative_angle":
                j = angle(pts[2], pts[3]) - angle(pts[0], pts[1])
            elif c["type"] == "distance":
                (px, py), (ax, ay), (bx, by) = jets[pts[0]], jets[pts[1]], jets[pts[2]]
                ex, ey = bx - ax, by - ay
                j = ((px - ax) * ex + (py - ay) * ey) / jet_sqrt(ex * ex + ey * ey)
            else:
                raise Unsupported(f"coordinate {c['name']} of type {c['type']}")
            v = j.v
            if c["type"] != "distance":
                # The angle's branch (a multiple of 2π) is the scene's initial value's.
                v = v + 2 * np.pi * np.round((model.initial_q[c["index"]] - v[0]) / (2 * np.pi))
            q[:, c["index"]], dq[:, c["index"]], ddq[:, c["index"]] = v, j.d, j.dd
        return tj.Trajectory(list(model.names), t, q, dq, ddq)


def generate(scene, t_end: float, sample_dt: float, solver: str = "generalized_alpha",
             h: float = 1e-4, newton_rtol: float | None = None,
             newton_atol: float | None = None,
             spectral_radius: float = 0.8, modified_newton: bool = True,
             ignore_singular_jacobian: bool = False,
             reactions: dict | None = None) -> tuple[tj.Trajectory, dict]:
    """Integrates the scene with exudyn at the fixed step h; returns the trajectory at the
    multiples of sample_dt up to t_end and its provenance.

    newton_rtol/atol: exudyn's Newton tolerances (its defaults, 1e-8 and 1e-10, limit the
    accuracy at small steps). spectral_radius: generalized-α's ρ∞ (< 1: with index-3
    constraints ρ∞ = 1 gives wrong velocities). ignore_singular_jacobian: let exudyn's
    dense solver pass a rank-deficient Jacobian (a singular configuration) instead of
    failing there.

    Accelerations: with index-3 constraints (generalized-α) q̈ carries the constraints'
    round-off amplified by 1/(β h²): about 1e-3 at h = 1e-5 on the four-bar, 5e-6 at
    1e-4; the index-2 trapezoidal rule's is smaller (velocity level), its |Φ| drifts."""
    if solver not in SOLVERS:
        raise ValueError(f"solver must be one of {sorted(SOLVERS)}, not {solver!r}")
    per_sample = round(sample_dt / h)
    samples = round(t_end / sample_dt)
    if per_sample < 1 or abs(per_sample * h - sample_dt) > 1e-9 * sample_dt:
        raise ValueError(f"the step h = {h} must divide the sampling step {sample_dt}")
    if abs(samples * sample_dt - t_end) > 1e-9 * t_end:
        raise ValueError(f"t_end = {t_end} is not a multiple of the sampling step {sample_dt}")
    model = mbfg.load(str(scene))
    sf = SceneFile(scene)
    sf.check(model)
    mech = Mechanism(model, sf)
    # exudyn's own constraint forces, sampled with the motion: a distance connector's
    # Force, a prismatic joint's ForceLocal.
    joint_sensors = {} if reactions is None else {
        name: mech.mbs.AddSensor(ei.SensorObject(
            objectNumber=obj, storeInternal=True, writeToFile=False,
            outputVariableType=(exu.OutputVariableType.Force
                                if "Distance" in mech.mbs.GetObject(obj)["objectType"]
                                else exu.OutputVariableType.ForceLocal)))
        for name, obj in mech.joints.items()}
    if joint_sensors:
        mech.mbs.Assemble()

    s = exu.SimulationSettings()
    ti = s.timeIntegration
    ti.endTime = t_end
    ti.numberOfSteps = samples * per_sample
    # Fixed steps: the adaptive step can cut h silently (and on a singular
    # configuration then land on the wrong branch while reporting success).
    ti.adaptiveStep = False
    ti.automaticStepSize = False
    if newton_rtol is None and newton_atol is None and mech.state_loads:
        # A load exudyn calls back for is not in its Newton matrix: the iteration
        # converges linearly and, at h = 1e-4, stalls short of 1e-12; exudyn's own
        # defaults it reaches.
        newton_rtol, newton_atol = STATE_LOAD_RTOL, STATE_LOAD_ATOL
        mech.notes.append(f"Newton tolerances {newton_rtol:g}/{newton_atol:g} (state-dependent loads)")
    newton_rtol = 1e-12 if newton_rtol is None else newton_rtol
    newton_atol = 1e-12 if newton_atol is None else newton_atol
    ti.newton.relativeTolerance = newton_rtol
    ti.newton.absoluteTolerance = newton_atol
    ti.newton.useModifiedNewton = modified_newton
    # ρ∞ = 1 with index-3 constraints gives wrong velocities; < 1 damps them.
    ti.generalizedAlpha.spectralRadius = spectral_radius
    ti.generalizedAlpha.computeInitialAccelerations = True
    ti.verboseMode = 0
    s.linearSolver.ignoreSingularJacobian = ignore_singular_jacobian
    s.solution.file.write = False
    s.solution.sensors.writePeriod = sample_dt

    start = time.perf_counter()
    # exudyn prints its own multi-line failure banner; the SolveError below says it in
    # one line.
    loud = exu.config.printToConsole
    exu.config.printToConsole = False
    try:
        ok = mech.mbs.SolveDynamic(s, solverType=SOLVERS[solver], storeSolver=True)
    except exu.SolverError as e:      # Newton did not converge, a singular Jacobian, ...
        ok, why = False, str(e).strip().splitlines()[0]
    else:
        why = "no reason given"
    finally:
        exu.config.printToConsole = loud
    wall = time.perf_counter() - start
    dyn = mech.mbs.sys["dynamicSolver"]
    it = dyn.it
    if not ok:
        why = " ".join(dyn.GetErrorString().split()) or why
        raise SolveError(f"exudyn: the {solver} solve of {scene} failed at t = "
                         f"{it.currentTime:.6g} s (h = {h}): {why}")
    steps = int(it.currentStepIndex) - 1        # the index of the step after the last
    if (steps != samples * per_sample or abs(it.currentTime - t_end) > 1e-9 * t_end
            or abs(it.lastStepSize - h) > 1e-9 * h):
        raise RuntimeError(f"exudyn took {steps} steps to t = {it.currentTime}, expected "
                           f"{samples * per_sample} fixed steps to {t_end}")

    traj = mech.trajectory(np.arange(samples + 1) * sample_dt)
    for name, sensor in joint_sensors.items():
        reactions[name] = mech.reaction(name, mech.mbs.GetSensorStoredData(sensor)[:, 1:], traj)
    phi = max(float(np.max(np.abs(model.phi(q)))) for q in traj.q) if model.m else 0.0
    settings = {"solver": solver, "h": h, "sample_dt": sample_dt, "t_end": t_end,
                "newton_relative_tolerance": newton_rtol,
                "newton_absolute_tolerance": newton_atol,
                "modified_newton": modified_newton, "adaptive_step": False,
                "ignore_singular_jacobian": ignore_singular_jacobian}
    if solver == "generalized_alpha":
        settings["spectral_radius"] = spectral_radius
    record = tj.provenance(
        "exudyn", scene,
        "exudyn rigid bodies (x, y, psi per body; ObjectRigidBody2D), RevoluteJoint2D / "
        "PrismaticJoint2D constraints, "
        + ("index 2 (trapezoidal)" if solver == "trapezoidal_index2" else "index 3 (generalized-alpha)"),
        settings, wall, packages=("exudyn",),
        steps=steps, newton_iterations=int(it.newtonStepsCount),
        jacobian_updates=int(it.newtonJacobiCount), max_abs_phi=phi,
        modelling_notes=mech.notes)
    return traj, record


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m harness.exudyn_ref", description=__doc__.split("\n\n")[0])
    ap.add_argument("scene")
    ap.add_argument("--t-end", type=float, default=5.0)
    ap.add_argument("--dt", type=float, default=1e-3, help="sampling step of the output")
    ap.add_argument("--h", type=float, default=1e-4,
                    help="integration step, divides --dt (default: %(default)s; the "
                    "references use 1e-5)")
    ap.add_argument("--solver", choices=sorted(SOLVERS), default="generalized_alpha")
    ap.add_argument("--newton-rtol", type=float, default=None,
                    help="default 1e-12; 1e-8 with a load of the state")
    ap.add_argument("--newton-atol", type=float, default=None,
                    help="default 1e-12; 1e-10 with a load of the state")
    ap.add_argument("--spectral-radius", type=float, default=0.8)
    ap.add_argument("--ignore-singular-jacobian", action="store_true",
                    help="pass singular configurations (with --newton-rtol 1e-8: the tight "
                    "default does not converge there)")
    ap.add_argument("--out", required=True, help="trajectory file (.csv or .csv.gz); "
                    "the provenance goes beside it as .json")
    a = ap.parse_args(argv)
    try:
        traj, record = generate(a.scene, a.t_end, a.dt, solver=a.solver, h=a.h,
                                newton_rtol=a.newton_rtol, newton_atol=a.newton_atol,
                                spectral_radius=a.spectral_radius,
                                ignore_singular_jacobian=a.ignore_singular_jacobian)
    except Unsupported as e:
        print(f"unsupported: {e}", file=sys.stderr)
        return 2
    except (SolveError, RuntimeError, ValueError) as e:  # one line, not a traceback
        print(f"exudyn_ref: {' '.join(str(e).split())}", file=sys.stderr)
        return 1
    out = pathlib.Path(a.out)
    tj.write(out, traj)
    base = out.name.removesuffix(".gz").removesuffix(".csv")
    tj.write_provenance(out.with_name(base + ".json"), record)
    print(f"{out}: {len(traj.t)} samples, {record['steps']} steps in {record['wall_time_s']:.3f} s, "
          f"max |Φ| = {record['max_abs_phi']:.2e}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
