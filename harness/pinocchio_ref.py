"""Reference trajectories from Pinocchio: rigid-body dynamics in joint coordinates.

An independent check of mbfg's natural-coordinate formulation. The scene's bodies
become a kinematic tree of revolute joints about z (JointModelRZ): a body hinged at a
fixed point hangs from the universe, a body sharing a point with a body already in the
tree hangs from that body. Every joint angle is zero at the scene's assembled initial
configuration, so the joint placements are the initial pivot positions. Points shared
by bodies that the tree does not join (closed loops, a second fixed point) become
CONTACT_3D constraints solved by `pin.constraintDynamics`; open trees use ABA.

Forward: `generate(scene, t_end, sample_dt, h)` integrates with classical RK4 at the
fixed step h and maps every sample back to the scene's coordinates (point positions,
velocities and accelerations of frames placed at the scene's points; relative
coordinates from the joint angles or the points). Inverse: `inverse(scene, csv)`
gives the generalized forces on the prescribed coordinates by RNEA.

Sliders are carriages on prismatic joints, a free particle or a body joined to nothing
hangs from x and y prismatic joints; distance ties between bodies and a point's second
slider are equations of a constrained solve of Pinocchio's CRBA and RNEA. Anything this
generator cannot model raises `trajectory.Unsupported`; nothing is dropped silently.

    python -m harness.pinocchio_ref scenes/double-pendulum.yaml --t-end 5 --dt 1e-3 \\
        --h 1e-5 --out /tmp/dp.csv.gz        # writes /tmp/dp.json too
    python -m harness.pinocchio_ref scenes/double-pendulum.yaml \\
        --inverse scenes/trajectories/double-pendulum.csv --out /tmp/dp-Q.csv
"""
from __future__ import annotations

import argparse
import math
import pathlib
import sys
import time

import numpy as np
import pinocchio as pin

import mbfg
from harness import trajectory as tj
from harness.scene_file import SceneFile

LWA = pin.ReferenceFrame.LOCAL_WORLD_ALIGNED
# A 3D point contact closing a planar loop has an identically zero z row, so the
# constraint Gram matrix is singular: the proximal solver needs μ > 0 (μ = 0 gives NaN).
PROX_MU = 1e-10
PROX_ACCURACY = 1e-14
PROX_MAX_ITER = 50
# Baumgarte gains on the loop-closure error: small, only to keep the drift of the
# index-1 formulation from growing (critically damped, time constant 0.1 s).
BAUMGARTE_KP = 100.0
BAUMGARTE_KD = 20.0

# Closed forms of the suite's prescribed motions (harness/prescribed_motions.py writes
# the tables from these): coordinate -> (A, w) of c(t) = A (1 - cos w t).
CLOSED_FORMS = {
    "double-pendulum.csv": {"theta1": (-0.8, 1.5), "theta2": (-1.1, 2.3)},
    "fourbar-theta.csv": {"theta": (1.2, 2.0)},
}


def _angle_of(d) -> float:
    return math.atan2(d[1], d[0])


class PinocchioModel:
    """The Pinocchio counterpart of an `mbfg.Model`, built at its initial configuration.

    The numbers of the mechanism (masses, centres, inertias, effect constants, load
    expressions) come from the harness's own reading of the file (scene_file.py), checked
    against mbfg's; from mbfg only the assembled initial state."""

    def __init__(self, scene: str | pathlib.Path):
        self.scene = pathlib.Path(scene)
        self.mb = mb = mbfg.load(scene)
        self.sf = sf = SceneFile(scene)
        sf.check(mb)
        names = list(mb.names)
        self.points = {n: {"name": n, "fixed": p.fixed, "mass": p.mass,
                           "index": None if p.fixed else names.index(f"{n}.x")}
                       for n, p in sf.points.items()}
        self.bodies = sf.bodies
        self.coords = {c["name"]: dict(c, index=names.index(c["name"])) for c in sf.coordinates}
        self.p0 = sf.positions(mb.initial_q)
        self._last: dict[str, float] = {}
        self.notes: list[str] = []
        self._check_constraints()
        self._build_tree()
        self._add_point_frames()
        self._coordinate_rows()
        self._effects()
        self.data = self.model.createData()
        if self.loops:
            self.cdatas = [c.createData() for c in self.cmodels]
            self.prox = pin.ProximalSettings(PROX_ACCURACY, PROX_MU, PROX_MAX_ITER)
            pin.initConstraintDynamics(self.model, self.data, self.cmodels, self.cdatas)

    # ---- building -------------------------------------------------------------------

    def _check_constraints(self):
        """Sliders become carriages (prismatic joints); a distance between points of one
        body is implied; any other distance is a tie, held with the loop closures by a
        constraint-dynamics solve of Pinocchio's M and bias forces (`_tied_acceleration`)."""
        body_points = [set(b.points) for b in self.bodies]
        self.carriages = {}        # slider point -> (constraint name, line points, kind)
        self.ties = []             # (name, a, b, length)
        self.slots = []            # (name, point, line start, line end): second sliders
        for c in self.sf.constraints:
            if c["type"] == "distance":
                a, b = c["points"]
                implied = any({a, b} <= s for s in body_points)
                if implied and abs(np.linalg.norm(self.p0[a] - self.p0[b]) - c["length"]) < 1e-9:
                    continue  # a rigid body already keeps this distance
                if implied:
                    raise tj.Unsupported(f"constraint {c['name']!r}: a distance between two "
                                         "points of one body that differs from the body's own")
                self.ties.append((c["name"], a, b, c["length"]))
                continue
            p, l0, l1 = c["points"]
            if p in self.carriages:
                # A second slider on the point: an equation of the constrained solve.
                self.slots.append((c["name"], p, l0, l1))
                continue
            if any({p, l0, l1} <= s for s in body_points):
                raise tj.Unsupported(f"constraint {c['name']!r}: point and line on one body")
            fixed_line = self.points[l0]["fixed"] and self.points[l1]["fixed"]
            if not fixed_line and not any({l0, l1} <= s for s in body_points):
                # No body carries the guide (its points are tied by a distance): an
                # equation of the constrained solve.
                self.slots.append((c["name"], p, l0, l1))
                continue
            self.carriages[p] = (c["name"], (l0, l1), c["type"])
        # A body hangs from one carriage; a second slider point of the body (a block
        # with two points in a slot) is an equation of the constrained solve, or its
        # carriage would be a massless leaf.
        for b in self.bodies:
            on = [n for n in b.points if n in self.carriages]
            for n in on[1:]:
                name, (l0, l1), _ = self.carriages.pop(n)
                self.slots.append((name, n, l0, l1))

    def _carriage_parent(self, p: str):
        _, line, kind = self.carriages[p]
        if kind == "particle":
            return "ground"
        l0, l1 = line
        if self.points[l0]["fixed"] and self.points[l1]["fixed"]:
            return "ground"
        return next(i for i, b in enumerate(self.bodies) if {l0, l1} <= set(b.points))

    def _build_tree(self):
        """Joints from the ground outwards: a carriage (prismatic along its guide) hangs
        from the guide's body or the ground; a body hangs from a carriage at its point
        first, then from a fixed point, then from a body it shares a point with. Points
        the tree does not join become loop closures."""
        bodies = self.bodies
        fixed = {n for n, p in self.points.items() if p["fixed"]}
        on_body = {n for b in bodies for n in b.points}
        for n, p in self.points.items():
            if not p["fixed"] and n not in on_body and n not in self.carriages:
                if p["mass"] <= 0:
                    raise tj.Unsupported(f"point {n!r} is on no body and no slider, and "
                                         "carries no mass")
                # A free particle: two prismatic joints, along x then y.
                self.carriages[n] = (f"particle {n}", None, "particle")
            if n in self.carriages and n not in on_body and p["mass"] <= 0:
                raise tj.Unsupported(f"slider point {n!r} carries no mass and no body")
        # Entities: "ground", a body's index, ("carriage", point).
        parent = {}            # entity -> (point, parent entity)
        placed = ["ground"]
        relaxed = False
        while len(parent) < len(bodies) + len(self.carriages):
            progress = False
            for p in self.carriages:
                ent = ("carriage", p)
                if ent not in parent and self._carriage_parent(p) in placed:
                    parent[ent] = (p, self._carriage_parent(p))
                    placed.append(ent)
                    progress = True
            for i, b in enumerate(bodies):
                if i in parent:
                    continue
                hinge = next(((n, ("carriage", n)) for n in b.points
                              if ("carriage", n) in placed), None)
                waiting = any(n in self.carriages and ("carriage", n) not in placed
                              for n in b.points)
                if hinge is None and (not waiting or relaxed):
                    hinge = next(((n, "ground") for n in b.points if n in fixed), None)
                    if hinge is None:
                        for j in placed:  # the earliest placed neighbour
                            if isinstance(j, int):
                                shared = [n for n in b.points if n in bodies[j].points]
                                if shared:
                                    hinge = (shared[0], j)
                                    break
                if hinge is not None:
                    parent[i] = hinge
                    placed.append(i)
                    progress = True
            if not progress:
                if not relaxed:
                    relaxed = True
                    continue
                # A body joined to nothing placed floats: it hangs from a massless
                # particle at its first point (x and y joints), turning about it.
                i = next(i for i in range(len(bodies)) if i not in parent)
                n = bodies[i].points[0]
                if n in self.carriages or self.points[n]["fixed"]:
                    raise tj.Unsupported(f"body {bodies[i].name!r} is joined to nothing the "
                                         "generator can place")
                self.carriages[n] = (f"float {bodies[i].name}", None, "particle")
                self.notes.append(f"body {bodies[i].name} floats: x, y joints at {n}")
        # ... joints added depth-first: Pinocchio's CRBA and constraint Cholesky assume
        # every subtree has contiguous velocity indices.
        model = pin.Model()
        model.name = self.mb.file
        self.joint = {}        # entity -> joint id
        self.pivot = {0: np.zeros(2)}  # joint id -> world position of its axis at q = 0
        self.revolute = set()  # joint ids that turn
        self.axis = {}         # carriage joint id -> its unit direction
        self.particle_x = {}   # a free particle's entity -> its x joint (its y joint: joint[])
        self.tree_edges = []   # (point, child entity, parent entity)
        order = []

        def add(entity):
            for child in placed[1:]:
                n, pent = parent[child]
                if pent != entity:
                    continue
                pjoint = 0 if pent == "ground" else self.joint[pent]
                at = self.p0[n]
                placement = pin.SE3(np.eye(3), np.r_[at - self.pivot[pjoint], 0.0])
                if isinstance(child, tuple) and self.carriages[n][2] == "particle":
                    jx = model.addJoint(pjoint, pin.JointModelPrismaticUnaligned(np.array([1.0, 0, 0])),
                                        placement, f"particle@{n}.x")
                    jid = model.addJoint(jx, pin.JointModelPrismaticUnaligned(np.array([0, 1.0, 0])),
                                         pin.SE3.Identity(), f"particle@{n}.y")
                    self.pivot[jx] = at
                    self.axis[jx], self.axis[jid] = np.array([1.0, 0]), np.array([0, 1.0])
                    self.particle_x[child] = jx
                elif isinstance(child, tuple):
                    l0, l1 = self.carriages[n][1]
                    e = self.p0[l1] - self.p0[l0]
                    e = e / np.linalg.norm(e)
                    jid = model.addJoint(pjoint, pin.JointModelPrismaticUnaligned(np.r_[e, 0.0]),
                                         placement, f"{self.carriages[n][0]}@{n}")
                    self.axis[jid] = e
                else:
                    jid = model.addJoint(pjoint, pin.JointModelRZ(), placement,
                                         f"{bodies[child].name}@{n}")
                    self.revolute.add(jid)
                self.joint[child] = jid
                self.pivot[jid] = at
                self.tree_edges.append((n, child, pent))
                order.append(child)
                add(child)
        add("ground")
        self.order = order
        self.body_order = [e for e in order if isinstance(e, int)]
        # Inertias: each body's mass, centre of mass and inertia about it; a point mass
        # goes to its carriage, else to the first body (in tree order) that carries it.
        for i in self.body_order:
            b = bodies[i]
            jid = self.joint[i]
            origin, x_to = self.p0[b.points[0]], self.p0[b.points[1]]
            th = _angle_of(x_to - origin)
            c, s = math.cos(th), math.sin(th)
            cog = origin + np.array([c * b.cog[0] - s * b.cog[1], s * b.cog[0] + c * b.cog[1]])
            # Planar motion only sees Izz; Ixx = Iyy = Izz keeps the inertia physical.
            inertia = pin.Inertia(b.mass, np.r_[cog - self.pivot[jid], 0.0], np.eye(3) * b.inertia)
            model.appendBodyToJoint(jid, inertia, pin.SE3.Identity())
        for n, p in self.points.items():
            if p["mass"] > 0 and not p["fixed"]:
                if n in self.carriages:
                    jid = self.joint[("carriage", n)]
                else:
                    jid = self.joint[next(i for i in self.body_order if n in bodies[i].points)]
                lever = np.r_[self.p0[n] - self.pivot[jid], 0.0]
                model.appendBodyToJoint(jid, pin.Inertia(p["mass"], lever, np.zeros((3, 3))),
                                        pin.SE3.Identity())
        for i in self.body_order:
            jid = self.joint[i]
            if model.inertias[jid].mass <= 0 and model.inertias[jid].inertia[2, 2] <= 0:
                raise tj.Unsupported(f"body {bodies[i].name!r} has no mass and no inertia")
        self.model = model
        self._loop_closures()

    def _holders(self, n: str) -> list:
        return ((["ground"] if self.points[n]["fixed"] else [])
                + ([("carriage", n)] if n in self.carriages else [])
                + [i for i in self.body_order if n in self.bodies[i].points])

    def _loop_closures(self):
        """A point joining entities the tree does not join at that point is a loop closure."""
        self.cmodels = []
        self.loops = []
        self.loop_frames = []      # (frame on the first entity, on the second) per loop
        for n in self.points:
            ents = self._holders(n)
            comp = {e: e for e in ents}

            def root(e):
                while comp[e] != e:
                    e = comp[e]
                return e
            for pt, child, parent in self.tree_edges:
                if pt == n and not isinstance(child, tuple):  # a carriage slides, not pins
                    comp[root(child)] = root(parent)
            roots = []
            for e in ents:
                if root(e) not in [root(r) for r in roots]:
                    roots.append(e)
            for other in roots[1:]:
                self.loops.append((n, roots[0], other))
                j1, j2 = (self._joint_of(roots[0]), self._joint_of(other))
                pl1 = pin.SE3(np.eye(3), np.r_[self.p0[n] - self.pivot[j1], 0.0])
                pl2 = pin.SE3(np.eye(3), np.r_[self.p0[n] - self.pivot[j2], 0.0])
                if j1 == 0:  # Pinocchio wants the moving joint first
                    j1, j2, pl1, pl2 = j2, j1, pl2, pl1
                self.loop_frames.append(tuple(
                    self.model.addFrame(pin.Frame(f"loop {n} {k}", j, pl, pin.FrameType.OP_FRAME))
                    for k, (j, pl) in enumerate(((j1, pl1), (j2, pl2)))))
                cm = pin.RigidConstraintModel(pin.ContactType.CONTACT_3D, self.model,
                                              j1, pl1, j2, pl2, pin.ReferenceFrame.LOCAL)
                cm.name = f"loop@{n}"
                cm.setBaumgarteCorrectorParameters(
                    pin.BaumgarteCorrectorParameters(BAUMGARTE_KP, BAUMGARTE_KD))
                self.cmodels.append(cm)
        self.cmodels = pin.StdVec_RigidConstraintModel(self.cmodels)

    def _joint_of(self, entity) -> int:
        return 0 if entity == "ground" else self.joint[entity]

    def _add_point_frames(self):
        """An operational frame at every scene point, on its carriage or the first body
        carrying it."""
        self.frame = {}
        for n, p in self.points.items():
            holders = [e for e in self._holders(n) if e != "ground"]
            jid = 0 if p["fixed"] or not holders else self.joint[holders[0]]
            placement = pin.SE3(np.eye(3), np.r_[self.p0[n] - self.pivot[jid], 0.0])
            self.frame[n] = self.model.addFrame(
                pin.Frame(f"point {n}", jid, placement, pin.FrameType.OP_FRAME))

    def _body_rows(self) -> dict[int, np.ndarray]:
        """Body index -> row r with (body angle - its initial angle) = r · q."""
        rows = {}
        for i in self.body_order:
            r = np.zeros(self.model.nv)
            jid = self.joint[i]
            while jid != 0:
                if jid in self.revolute:
                    r[self.model.idx_vs[jid]] = 1.0
                jid = self.model.parents[jid]
            rows[i] = r
        return rows

    def _segment_row(self, a: str, b: str):
        """Row r with (angle of a→b - its initial angle) = r · q, if one body carries a, b."""
        body_rows = self._body_rows()
        for i in self.body_order:
            if {a, b} <= set(self.bodies[i].points):
                return body_rows[i]
        if self.points[a]["fixed"] and self.points[b]["fixed"]:
            return np.zeros(self.model.nv)
        return None

    def _coordinate_rows(self):
        """Relative coordinates linear in the joint angles: c = c0 + row · q."""
        self.rows = {}
        q0 = self.mb.initial_q
        for c in self.coords.values():
            row = None
            if c["type"] == "angle":
                row = self._segment_row(*c["points"])
            elif c["type"] == "relative_angle":
                ra = self._segment_row(*c["points"][:2])
                rb = self._segment_row(*c["points"][2:])
                if ra is not None and rb is not None:
                    row = rb - ra
            if row is not None:
                self.rows[c["name"]] = (q0[c["index"]], row)

    def _effects(self):
        """Sorts the scene's effects; gravity goes into the model."""
        self.model.gravity.linear = np.zeros(3)
        self.loads = []
        for e in self.sf.effects:
            if e.type == "gravity":
                self.model.gravity.linear = self.model.gravity.linear + np.r_[e.spec["vector"], 0.0]
            else:
                self.loads.append(e)
        self.needs_state = any(e.type in ("torque", "force") and
                               any(v.state_names for v in e.spec["value"]) for e in self.loads)
        self.needs_points = self.needs_state or any(
            e.type in ("spring_damper", "force") or
            (e.spec.get("coordinate") is not None and e.spec["coordinate"] not in self.rows)
            for e in self.loads)

    # ---- dynamics -------------------------------------------------------------------

    def _point_jacobians(self, q, names):
        """(positions, 2×nv Jacobians) of named points; call after forwardKinematics."""
        pin.computeJointJacobians(self.model, self.data, q)
        pin.updateFramePlacements(self.model, self.data)
        out = {}
        for n in names:
            fid = self.frame[n]
            pos = self.data.oMf[fid].translation[:2].copy()
            # reshape: with one joint, the binding returns the 6×1 Jacobian as a vector
            J = np.reshape(pin.getFrameJacobian(self.model, self.data, fid, LWA),
                           (6, self.model.nv))[:2]
            out[n] = (pos, J)
        return out

    def _angle_row(self, name, q, pts):
        """(value continued from its last, d value / d joint q) of an angle coordinate."""
        if name in self.rows:
            c0, row = self.rows[name]
            return c0 + row @ q, row
        c = self.coords[name]
        segs = [c["points"][:2]] if c["type"] == "angle" else [c["points"][:2], c["points"][2:]]
        rows = []
        for a, b in segs:
            (pa, Ja), (pb, Jb) = pts[a], pts[b]
            d, dJ = pb - pa, Jb - Ja
            rows.append((d[0] * dJ[1] - d[1] * dJ[0]) / (d @ d))
        row = rows[0] if len(rows) == 1 else rows[1] - rows[0]
        r = {n: p for n, (p, _) in pts.items()}
        value = self.sf.coordinate_value(c, r, self._last.get(name, self.mb.initial_q[c["index"]]))
        self._last[name] = value
        return value, row

    def state_env(self, t, q, v) -> dict:
        """The load expressions' variables (docs/scene-format.md, section 8) at (q, v)."""
        Q, dQ, _ = self.scene_state(q, v, np.zeros(self.model.nv))
        env = {"t": t}
        for name, c in self.coords.items():
            env[name], env[f"rate({name})"] = Q[c["index"]], dQ[c["index"]]
            if c["type"] != "distance":
                near = self._last.get(name, self.mb.initial_q[c["index"]])
                env[name] += 2 * math.pi * round((near - env[name]) / (2 * math.pi))
                self._last[name] = env[name]
        for n in self.points:
            env[f"x({n})"], env[f"y({n})"] = self._pos[n]
            env[f"vx({n})"], env[f"vy({n})"] = self._vel[n]
        for b in self.bodies:
            a0, a1 = b.points[:2]
            d, dv = self._pos[a1] - self._pos[a0], self._vel[a1] - self._vel[a0]
            env[f"angle({b.name})"] = math.atan2(d[1], d[0])
            env[f"omega({b.name})"] = (d[0] * dv[1] - d[1] * dv[0]) / (d @ d)
        return env

    def applied_torques(self, t, q, v):
        """Joint torques of every effect but gravity (that one is in the model)."""
        tau = np.zeros(self.model.nv)
        if not self.loads:
            return tau
        env = self.state_env(t, q, v) if self.needs_state else {"t": t}
        pts = self._point_jacobians(q, list(self.points)) if self.needs_points else {}
        for e in self.loads:
            kind, s = e.type, e.spec
            if kind in ("torque", "rotational_spring_damper", "dc_motor"):
                angle, row = self._angle_row(s["coordinate"], q, pts)
                rate = row @ v
                if kind == "torque":
                    value = s["value"][0]({**env, s["coordinate"]: angle})
                elif kind == "dc_motor":
                    value = s["stall_torque"] * (1.0 - rate / s["no_load_speed"])
                else:
                    value = -s["stiffness"] * (angle - s["rest_angle"]) - s["damping"] * rate
                tau += value * row
            elif kind == "force":
                pos, J = pts[s["point"]]
                tau += J.T @ np.array([f(env) for f in s["value"]])
            else:  # spring_damper
                (pa, Ja), (pb, Jb) = pts[s["points"][0]], pts[s["points"][1]]
                d = pb - pa
                length = math.hypot(*d)
                if length < 1e-12:
                    raise ValueError(f"spring {e.name!r}: its ends coincide, direction undefined")
                u = d / length
                rate = u @ ((Jb - Ja) @ v)
                tension = s["stiffness"] * (length - s["rest_length"]) + s["damping"] * rate
                tau += (Ja - Jb).T @ (tension * u)  # pulls b towards a and a towards b
        return tau

    def acceleration(self, t, q, v):
        tau = self.applied_torques(t, q, v)
        if self.ties or self.slots:
            return self._tied_acceleration(q, v, tau)
        if self.loops:
            a = pin.constraintDynamics(self.model, self.data, q, v, tau,
                                       self.cmodels, self.cdatas, self.prox)
        else:
            a = pin.aba(self.model, self.data, q, v, tau)
        return np.array(a)  # a copy: Pinocchio may reuse its buffer

    def _frame_state(self, fid):
        """(position, velocity, classical acceleration at q̈ = 0, 2×nv Jacobian) of a frame;
        after forwardKinematics(q, v, 0), computeJointJacobians and updateFramePlacements."""
        m, d = self.model, self.data
        return (d.oMf[fid].translation[:2].copy(),
                pin.getFrameVelocity(m, d, fid, LWA).linear[:2].copy(),
                pin.getFrameClassicalAcceleration(m, d, fid, LWA).linear[:2].copy(),
                np.reshape(pin.getFrameJacobian(m, d, fid, LWA), (6, m.nv))[:2])

    def _tied_acceleration(self, q, v, tau):
        """q̈ of the tree held by its loop closures (the point's x, y on both sides) and its
        distance ties (|r_b − r_a|² = L²), each stabilized as the loops are (Baumgarte):
        [M Jᵀ; J 0] [q̈; −λ] = [τ − b(q, q̇); −J̇q̇ − K_d φ̇ − K_p φ], with Pinocchio's M (CRBA),
        bias forces b (RNEA at q̈ = 0, gravity included) and frame Jacobians."""
        m, d = self.model, self.data
        nv = m.nv
        M = pin.crba(m, d, q)
        M = np.triu(M) + np.triu(M, 1).T
        b = pin.rnea(m, d, q, v, np.zeros(nv))
        pin.forwardKinematics(m, d, q, v, np.zeros(nv))
        pin.computeJointJacobians(m, d, q)
        pin.updateFramePlacements(m, d)
        rows, rhs = [], []
        for f1, f2 in self.loop_frames:
            (p1, v1, a1, J1), (p2, v2, a2, J2) = self._frame_state(f1), self._frame_state(f2)
            rows.append(J1 - J2)
            rhs.append(-(a1 - a2) - BAUMGARTE_KD * (v1 - v2) - BAUMGARTE_KP * (p1 - p2))
        for _, a, bb, length in self.ties:
            (pa, va, aa, Ja), (pb, vb, ab, Jb) = (self._frame_state(self.frame[n]) for n in (a, bb))
            dd, dv = pb - pa, vb - va
            rows.append((2 * dd @ (Jb - Ja))[None, :])
            phi = dd @ dd - length ** 2
            rhs.append(np.array([-(2 * dd @ (ab - aa) + 2 * dv @ dv)
                                 - BAUMGARTE_KD * 2 * (dd @ dv) - BAUMGARTE_KP * phi]))
        for _, p, l0, l1 in self.slots:
            # φ = e × w, e = r_l1 − r_l0, w = r_p − r_l0 (× the planar cross product).
            (p0, v0, a0, J0), (p1, v1, a1, J1), (pp, vp, ap, Jp) = (
                self._frame_state(self.frame[n]) for n in (l0, l1, p))
            e, de, ae, Je = p1 - p0, v1 - v0, a1 - a0, J1 - J0
            w, dw, aw, Jw = pp - p0, vp - v0, ap - a0, Jp - J0
            cr = lambda a, b: a[0] * b[1] - a[1] * b[0]  # noqa: E731
            rows.append((Je[0] * w[1] - Je[1] * w[0] + e[0] * Jw[1] - e[1] * Jw[0])[None, :])
            rhs.append(np.array([-(cr(ae, w) + 2 * cr(de, dw) + cr(e, aw))
                                 - BAUMGARTE_KD * (cr(de, w) + cr(e, dw))
                                 - BAUMGARTE_KP * cr(e, w)]))
        J = np.vstack(rows)
        k = J.shape[0]
        K = np.block([[M, J.T], [J, np.zeros((k, k))]])
        sol = np.linalg.lstsq(K, np.concatenate([tau - b, *rhs]), rcond=1e-13)[0]
        return sol[:nv]

    def loop_error(self, q) -> float:
        """Largest loop-closure gap or distance tie error (m) at q."""
        if not self.loops and not self.ties and not self.slots:
            return 0.0
        pin.framesForwardKinematics(self.model, self.data, q)
        worst = 0.0
        for _, p, l0, l1 in self.slots:
            r = {n: self.data.oMf[self.frame[n]].translation[:2] for n in (p, l0, l1)}
            e, w = r[l1] - r[l0], r[p] - r[l0]
            worst = max(worst, abs(float(e[0] * w[1] - e[1] * w[0])) / np.linalg.norm(e))
        for _, a, b, length in self.ties:
            gap = np.linalg.norm(self.data.oMf[self.frame[b]].translation[:2]
                                 - self.data.oMf[self.frame[a]].translation[:2]) - length
            worst = max(worst, abs(float(gap)))
        for (n, a, b) in self.loops:
            pos = []
            for ent in (a, b):
                jid = self._joint_of(ent)
                pos.append(self.data.oMi[jid].act(np.r_[self.p0[n] - self.pivot[jid], 0.0])[:2])
            worst = max(worst, float(np.max(np.abs(pos[0] - pos[1]))))
        return worst

    # ---- states ---------------------------------------------------------------------

    def initial_state(self):
        """Joint coordinates (zero by construction) and rates from mbfg's initial q̇."""
        mb = self.mb
        v0 = self.sf.positions(mb.initial_dq)

        def vel(n):
            return np.zeros(2) if self.points[n]["fixed"] else v0[n]
        omega = {"ground": 0.0}
        v = np.zeros(self.model.nv)
        for ent in self.order:
            n, pent = next((p, par) for p, c, par in self.tree_edges if c == ent)
            jid = self.joint[ent]
            if isinstance(ent, tuple):
                # The guide's material point under n moves with the parent body.
                if pent == "ground":
                    v_guide = np.zeros(2)
                else:
                    b = self.bodies[pent]
                    a = b.points[0]
                    r = self.p0[n] - self.p0[a]
                    v_guide = vel(a) + omega[pent] * np.array([-r[1], r[0]])
                omega[ent] = omega[pent]
                v[self.model.idx_vs[jid]] = (vel(n) - v_guide) @ self.axis[jid]
                if ent in self.particle_x:
                    jx = self.particle_x[ent]
                    v[self.model.idx_vs[jx]] = (vel(n) - v_guide) @ self.axis[jx]
            else:
                a, b = self.bodies[ent].points[:2]
                d = self.p0[b] - self.p0[a]
                dv = vel(b) - vel(a)
                omega[ent] = (d[0] * dv[1] - d[1] * dv[0]) / (d @ d)
                v[self.model.idx_vs[jid]] = omega[ent] - omega[pent]
        return np.zeros(self.model.nq), v

    def scene_state(self, q, v, a):
        """(q, q̇, q̈) of the mbfg model, in its order, from the joint state."""
        model, data = self.model, self.data
        pin.forwardKinematics(model, data, q, v, a)
        pin.updateFramePlacements(model, data)
        n = self.mb.n
        Q, dQ, ddQ = np.zeros(n), np.zeros(n), np.zeros(n)
        pos, vel, acc = {}, {}, {}
        for name, p in self.points.items():
            fid = self.frame[name]
            pos[name] = data.oMf[fid].translation[:2].copy()
            vel[name] = pin.getFrameVelocity(model, data, fid, LWA).linear[:2].copy()
            acc[name] = pin.getFrameClassicalAcceleration(model, data, fid, LWA).linear[:2].copy()
            k = p["index"]
            if k is not None:
                Q[k:k + 2], dQ[k:k + 2], ddQ[k:k + 2] = pos[name], vel[name], acc[name]
        self._pos, self._vel = pos, vel
        for c in self.coords.values():
            k = c["index"]
            if c["name"] in self.rows:
                c0, row = self.rows[c["name"]]
                Q[k], dQ[k], ddQ[k] = c0 + row @ q, row @ v, row @ a
            elif c["type"] == "angle":
                a0, b = c["points"]
                Q[k], dQ[k], ddQ[k] = _angle_state(pos[b] - pos[a0], vel[b] - vel[a0],
                                                   acc[b] - acc[a0])
            elif c["type"] == "relative_angle":
                s = [_angle_state(pos[b] - pos[a0], vel[b] - vel[a0], acc[b] - acc[a0])
                     for a0, b in (c["points"][:2], c["points"][2:])]
                Q[k], dQ[k], ddQ[k] = (s[1][j] - s[0][j] for j in range(3))
            else:  # distance of p from a0 along a0→a1
                p_, a0, a1 = c["points"]
                Q[k], dQ[k], ddQ[k] = _distance_state(
                    (pos[p_] - pos[a0], vel[p_] - vel[a0], acc[p_] - acc[a0]),
                    (pos[a1] - pos[a0], vel[a1] - vel[a0], acc[a1] - acc[a0]))
        return Q, dQ, ddQ


def _angle_state(d, dv, da):
    """Angle of d against x and its first two time derivatives."""
    r2 = d @ d
    cross = d[0] * dv[1] - d[1] * dv[0]
    rate = cross / r2
    dcross = d[0] * da[1] - d[1] * da[0]
    return _angle_of(d), rate, dcross / r2 - cross * 2.0 * (d @ dv) / r2 ** 2


def _distance_state(w, e):
    """s = w·e/|e| and its first two time derivatives; w, e as (x, ẋ, ẍ)."""
    (w0, w1, w2), (e0, e1, e2) = w, e
    L = math.sqrt(e0 @ e0)
    L1 = (e0 @ e1) / L
    L2 = (e1 @ e1 + e0 @ e2 - L1 ** 2) / L
    n0 = w0 @ e0
    n1 = w1 @ e0 + w0 @ e1
    n2 = w2 @ e0 + 2.0 * (w1 @ e1) + w0 @ e2
    s0 = n0 / L
    s1 = (n1 - s0 * L1) / L
    s2 = (n2 - 2.0 * s1 * L1 - s0 * L2) / L
    return s0, s1, s2


def _unwrap_angles(pm: PinocchioModel, q: np.ndarray) -> None:
    """Angle coordinates computed by atan2 made continuous, starting at mbfg's values."""
    q0 = pm.mb.initial_q
    for c in pm.mb.coordinates:
        if c["type"] in ("angle", "relative_angle") and c["name"] not in pm.rows:
            k = c["index"]
            col = np.unwrap(q[:, k])
            q[:, k] = col + 2 * math.pi * round((q0[k] - col[0]) / (2 * math.pi))


def _rk4(f, q, v, t_end, h, every, record):
    """Classical RK4 at the fixed step h; record(t, q, v) every `every` steps.

    The state sums are compensated (Kahan): over 10⁶ steps plain addition would lose
    more to round-off than the method's truncation error at h = 1e-5.
    """
    steps = round(t_end / h)
    cq, cv = np.zeros_like(q), np.zeros_like(v)
    h2, h6 = h / 2.0, h / 6.0
    for k in range(steps + 1):
        t = k * h
        if k % every == 0:
            record(t, q, v)
        if k == steps:
            break
        a1 = f(t, q, v)
        v2 = v + h2 * a1
        a2 = f(t + h2, q + h2 * v, v2)
        v3 = v + h2 * a2
        a3 = f(t + h2, q + h2 * v2, v3)
        v4 = v + h * a3
        a4 = f(t + h, q + h * v3, v4)
        dq = h6 * (v + 2.0 * (v2 + v3) + v4) - cq
        dv = h6 * (a1 + 2.0 * (a2 + a3) + a4) - cv
        qn, vn = q + dq, v + dv
        cq, cv = (qn - q) - dq, (vn - v) - dv
        q, v = qn, vn
    return q, v


def _dop853(f, q, v, t_end, sample_dt, rtol, record):
    """scipy's adaptive DOP853 (Dormand–Prince 8(5,3)) on y = (q, v), recorded at the
    multiples of sample_dt from its dense output; atol = rtol on every component."""
    from scipy.integrate import solve_ivp
    n = len(q)

    def rhs(t, y):
        return np.concatenate([y[n:], f(t, y[:n], y[n:])])

    times = np.arange(round(t_end / sample_dt) + 1) * sample_dt
    sol = solve_ivp(rhs, (0.0, times[-1]), np.concatenate([q, v]), method="DOP853",
                    rtol=rtol, atol=rtol, t_eval=times)
    if sol.status != 0:
        raise RuntimeError(f"DOP853 failed: {sol.message}")
    for k, t in enumerate(sol.t):
        record(t, sol.y[:n, k], sol.y[n:, k])
    return sol.nfev


def generate(scene, t_end: float, sample_dt: float, h: float = 2e-4,
             method: str = "rk4", rtol: float = 1e-10) -> tuple[tj.Trajectory, dict]:
    """Forward dynamics of the scene over [0, t_end], sampled every sample_dt: classical
    RK4 at the fixed step h, or (method="dop853") scipy's adaptive DOP853 at rtol."""
    start = time.perf_counter()
    pm = PinocchioModel(scene)
    if method not in ("rk4", "dop853"):
        raise ValueError(f"method must be rk4 or dop853, not {method!r}")
    every = round(sample_dt / h)
    if method == "rk4" and (every < 1 or abs(every * h - sample_dt) > 1e-9 * sample_dt):
        raise ValueError(f"the sample step {sample_dt} is not a multiple of h = {h}")
    if abs(round(t_end / sample_dt) * sample_dt - t_end) > 1e-9 * sample_dt:
        raise ValueError(f"t_end {t_end} is not a multiple of the sample step {sample_dt}")
    rows_t, rows = [], []
    loop_gap = [0.0]

    def record(t, q, v):
        a = pm.acceleration(t, q, v)
        rows_t.append(t)
        rows.append(pm.scene_state(q, v, a))
        loop_gap[0] = max(loop_gap[0], pm.loop_error(q))

    q, v = pm.initial_state()
    if method == "rk4":
        _rk4(pm.acceleration, q, v, t_end, h, every, record)
        integrator, step = "RK4", {"h": h}
    else:
        nfev = _dop853(pm.acceleration, q, v, t_end, sample_dt, rtol, record)
        integrator, step = "DOP853 (scipy, adaptive)", {"method": "dop853", "rtol": rtol,
                                                        "atol": rtol, "evaluations": nfev}
    Q = np.array([r[0] for r in rows])
    _unwrap_angles(pm, Q)
    traj = tj.Trajectory(list(pm.mb.names), np.array(rows_t), Q,
                         np.array([r[1] for r in rows]), np.array([r[2] for r in rows]))
    wall = time.perf_counter() - start
    mb = pm.mb
    max_phi = max(float(np.max(np.abs(mb.phi(qk)))) for qk in traj.q) if mb.m else 0.0
    extra = {}
    if mb.is_conservative:
        e = np.array([mb.kinetic_energy(v) + mb.potential_energy(q)
                      for q, v in zip(traj.q, traj.dq)])
        extra["max_energy_drift_J"] = float(np.max(np.abs(e - e[0])))
    if pm.ties or pm.slots:
        formulation = (f"KKT of CRBA/RNEA with loop closures, distance ties and second "
                       f"sliders (Baumgarte) + {integrator}")
        settings = {**step, "baumgarte": {"Kp": BAUMGARTE_KP, "Kd": BAUMGARTE_KD},
                    "loops": [f"{n}: {a}-{b}" for n, a, b in pm.loops],
                    "ties": [f"{name}: {a}-{b}" for name, a, b, _ in pm.ties],
                    "sliders": [f"{name}: {p} on {a}-{b}" for name, p, a, b in pm.slots]}
    elif pm.loops:
        formulation = f"constraintDynamics (CONTACT_3D loop closures) + {integrator}"
        settings = {**step, "mu": PROX_MU, "prox_accuracy": PROX_ACCURACY,
                    "prox_max_iter": PROX_MAX_ITER,
                    "baumgarte": {"Kp": BAUMGARTE_KP, "Kd": BAUMGARTE_KD},
                    "loops": [f"{n}: {a}-{b}" for n, a, b in pm.loops]}
    else:
        formulation = f"ABA + {integrator}"
        settings = step
    prov = tj.provenance("pinocchio", scene, formulation, settings, wall, packages=("pin",),
                         joints=[pm.model.names[j] for j in range(1, pm.model.njoints)],
                         max_abs_phi=max_phi, max_loop_gap_m=loop_gap[0],
                         modelling_notes=pm.notes,
                         sample_dt=sample_dt, t_end=t_end, **extra)
    return traj, prov


# ---- inverse dynamics -------------------------------------------------------------------

def _read_prescription(path):
    path = pathlib.Path(path)
    with open(path) as f:
        header = f.readline().strip().split(",")
    data = np.loadtxt(path, delimiter=",", skiprows=1, ndmin=2)
    if header[0] != "t":
        raise ValueError(f"{path}: the first column must be t")
    return header[1:], data[:, 0], data[:, 1:]


# Fourth-order finite-difference stencils (weights × 1/(12 dt^k)): central inside,
# one-sided for the first two rows (mirrored for the last two).
_D1_CENTRAL = np.array([1, -8, 0, 8, -1])
_D2_CENTRAL = np.array([-1, 16, -30, 16, -1])
_D1_EDGE = np.array([[-25, 48, -36, 16, -3, 0], [-3, -10, 18, -6, 1, 0]])
_D2_EDGE = np.array([[45, -154, 214, -156, 61, -10], [10, -15, -4, 14, -6, 1]])


def _derivatives(t, x):
    """First and second derivatives of uniformly sampled columns, fourth order."""
    dt = t[1] - t[0]
    if len(t) < 6 or np.max(np.abs(np.diff(t) - dt)) > 1e-9 * dt:
        raise ValueError("finite differences need at least 6 uniformly spaced rows")
    d1, d2 = np.empty_like(x), np.empty_like(x)
    n = len(t)
    d1[2:-2] = sum(w * x[k:n - 4 + k] for k, w in enumerate(_D1_CENTRAL)) / (12 * dt)
    d2[2:-2] = sum(w * x[k:n - 4 + k] for k, w in enumerate(_D2_CENTRAL)) / (12 * dt ** 2)
    head, tail = x[:6], x[::-1][:6]
    d1[:2], d1[-2:] = _D1_EDGE @ head / (12 * dt), -(_D1_EDGE @ tail)[::-1] / (12 * dt)
    d2[:2], d2[-2:] = _D2_EDGE @ head / (12 * dt ** 2), (_D2_EDGE @ tail)[::-1] / (12 * dt ** 2)
    return d1, d2


def prescribed_motion(path):
    """(names, t, c, ċ, c̈) of a prescription file; exact derivatives for the suite's
    closed forms when the table matches them, finite differences otherwise."""
    names, t, c = _read_prescription(path)
    form = CLOSED_FORMS.get(pathlib.Path(path).name)
    if form is not None and set(form) == set(names):
        amp = np.array([form[n][0] for n in names])
        w = np.array([form[n][1] for n in names])
        wt = np.outer(t, w)
        exact = amp * (1.0 - np.cos(wt))
        if np.max(np.abs(exact - c)) < 1e-12:
            return names, t, exact, amp * w * np.sin(wt), amp * w ** 2 * np.cos(wt), "closed form"
    dc, ddc = _derivatives(t, c)
    return names, t, c, dc, ddc, "finite differences (4th order)"


def inverse(scene, trajectory_csv, with_method: bool = False):
    """Generalized forces on the prescribed coordinates (RNEA in joint space).

    The prescribed coordinates c must be angles of single bodies, one per joint, so that
    c = c0 + A q with A invertible. The joint torques τ = RNEA(q, q̇, q̈) minus the
    scene's applied loads do virtual work τᵀδq = τᵀA⁻¹δc, so the forces on c are
    Q = A⁻ᵀτ (for the double pendulum's absolute angles: Q1 = τ1 − τ2, Q2 = τ2).
    Returns (t, {coordinate: Q}) and, with with_method, the derivative method too.
    """
    pm = PinocchioModel(scene)
    if pm.loops or pm.ties or pm.slots:
        raise tj.Unsupported("inverse dynamics of closed loops is not modelled by the "
                             "Pinocchio generator (RNEA needs a tree)")
    names, t, c, dc, ddc, method = prescribed_motion(trajectory_csv)
    missing = [n for n in names if n not in pm.rows]
    if missing:
        raise tj.Unsupported(f"prescribed coordinates {missing} are not angles of single bodies")
    A = np.array([pm.rows[n][1] for n in names])
    c0 = np.array([pm.rows[n][0] for n in names])
    if A.shape[0] != A.shape[1] or abs(np.linalg.det(A)) < 1e-12:
        raise tj.Unsupported(f"the prescribed coordinates {names} do not fix the "
                             f"{pm.model.nv} joint angles one to one")
    Ainv = np.linalg.inv(A)
    q, v, a = (c - c0) @ Ainv.T, dc @ Ainv.T, ddc @ Ainv.T
    Q = np.zeros_like(c)
    for k, tk in enumerate(t):
        tau = pin.rnea(pm.model, pm.data, q[k], v[k], a[k]) - pm.applied_torques(tk, q[k], v[k])
        Q[k] = Ainv.T @ tau
    out = (t, {n: Q[:, j] for j, n in enumerate(names)})
    return (*out, method) if with_method else out


# ---- command line -----------------------------------------------------------------------

def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m harness.pinocchio_ref",
                                 description=__doc__.splitlines()[0])
    ap.add_argument("scene")
    ap.add_argument("--t-end", type=float, default=5.0)
    ap.add_argument("--dt", type=float, default=1e-3, help="sample step of the output")
    ap.add_argument("--h", type=float, default=2e-4,
                    help="RK4 step (default: %(default)s, 1 s for the four-bar over 5 s at "
                    "3e-12 m; the references use 1e-5)")
    ap.add_argument("--inverse", metavar="CSV", help="inverse dynamics of this prescription")
    ap.add_argument("--out", required=True, help="output CSV (.gz compresses)")
    args = ap.parse_args(argv)
    out = pathlib.Path(args.out)
    base = out.name.removesuffix(".gz").removesuffix(".csv")
    try:
        if args.inverse:
            start = time.perf_counter()
            t, Q, method = inverse(args.scene, args.inverse, with_method=True)
            names = list(Q)
            out.parent.mkdir(parents=True, exist_ok=True)
            np.savetxt(out, np.column_stack([t] + [Q[n] for n in names]), delimiter=",",
                       header=",".join(["t"] + [f"Q:{n}" for n in names]), comments="",
                       fmt="%.17g")
            prov = tj.provenance("pinocchio", args.scene, "RNEA", {"derivatives": method},
                                 time.perf_counter() - start, packages=("pin",),
                                 trajectory=tj.display_path(args.inverse))
        else:
            traj, prov = generate(args.scene, args.t_end, args.dt, h=args.h)
            tj.write(out, traj)
    except tj.Unsupported as e:
        print(f"pinocchio_ref: {args.scene}: unsupported: {e}", file=sys.stderr)
        return 2
    except (RuntimeError, ValueError) as e:  # one line, not a traceback
        print(f"pinocchio_ref: {args.scene}: {' '.join(str(e).split())}", file=sys.stderr)
        return 1
    tj.write_provenance(out.with_name(base + ".json"), prov)
    print(f"wrote {out} ({prov['wall_time_s']:.1f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
