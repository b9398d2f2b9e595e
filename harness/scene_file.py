"""A scene file read by the harness itself, from its YAML, without mbfg.

The reference generators take the mechanism's numbers from here — masses, centres of
mass, inertias, lengths, effect constants and load expressions — and only the
assembled initial state (the solution of the position and velocity problems) from
`mbfg.load`. `check(model)` compares every quantity both read and the initial state
against this reading: a scene that mbfg reads differently is refused, naming the
quantity, before any simulator runs on it. The rules implemented here are those of
docs/scene-format.md (defaults, body variables, MBSE files), written a second time.

    scene = SceneFile.read("scenes/slider-crank.yaml")
    scene.check(mbfg.load("scenes/slider-crank.yaml"))     # raises Mismatch
"""
from __future__ import annotations

import dataclasses
import math
import pathlib
import re

import numpy as np
import yaml

from harness import expressions as ex
from harness.trajectory import Unsupported


class Mismatch(Unsupported):
    """mbfg read a quantity of the scene differently from the harness."""


# --- YAML 1.2 scalars: only true/false are booleans, floats need digits -----------------

class _Loader(yaml.SafeLoader):
    pass


_Loader.yaml_implicit_resolvers = {
    k: [(tag, rx) for tag, rx in v if tag not in ("tag:yaml.org,2002:bool",
                                                   "tag:yaml.org,2002:float",
                                                   "tag:yaml.org,2002:int")]
    for k, v in yaml.SafeLoader.yaml_implicit_resolvers.items()}
_Loader.add_implicit_resolver("tag:yaml.org,2002:bool", re.compile(r"^(?:true|false)$"),
                              list("tf"))
_Loader.add_implicit_resolver("tag:yaml.org,2002:int", re.compile(r"^[-+]?[0-9]+$"),
                              list("-+0123456789"))
_Loader.add_implicit_resolver(
    "tag:yaml.org,2002:float",
    re.compile(r"^[-+]?(?:\.[0-9]+|[0-9]+(?:\.[0-9]*)?)(?:[eE][-+]?[0-9]+)?$"),
    list("-+.0123456789"))


def load_yaml(path) -> dict:
    with open(path, encoding="utf-8") as f:
        doc = yaml.load(f, Loader=_Loader)
    if not isinstance(doc, dict):
        raise Unsupported(f"{path}: not a YAML mapping")
    return doc


# --- the mechanism -------------------------------------------------------------------

@dataclasses.dataclass
class Point:
    name: str
    x: float
    y: float
    fixed: bool
    mass: float                     # 0: none

    @property
    def r(self) -> np.ndarray:
        return np.array([self.x, self.y])


@dataclasses.dataclass
class Body:
    name: str
    points: list[str]
    mass: float
    length: float                   # kept between its first two points
    cog: np.ndarray                 # in the body frame
    inertia: float                  # about the centre of mass


@dataclasses.dataclass
class Effect:
    type: str
    name: str
    spec: dict                      # constants evaluated; "value": parsed Expressions


def _dist(a: Point, b: Point) -> float:
    return math.hypot(b.x - a.x, b.y - a.y)


class SceneFile:
    def __init__(self, path):
        self.path = pathlib.Path(path)
        doc = load_yaml(self.path)
        if "planar_bodies" in doc:
            doc = {"mechanism_doc": doc}
        elif "mechanism" in doc:
            doc = dict(doc, mechanism_doc=load_yaml(self.path.parent / doc["mechanism"]))
        self.doc = doc
        self.params = self._parameters(doc.get("parameters") or {})
        if "mechanism_doc" in doc:
            self._read_mbse(doc["mechanism_doc"])
        else:
            self._read_points(doc.get("points") or [])
            self._read_bodies(doc.get("bodies") or [])
            self.coordinates = []
        self._read_coordinates(doc.get("coordinates") or [])
        self._read_constraints(doc.get("constraints") or [])
        self._read_effects(doc.get("effects") or [])
        self.independent = list(doc.get("independent") or [])
        init = doc.get("initial") or {}
        self.initial_positions = {k: self.num(v) for k, v in (init.get("positions") or {}).items()}
        self.initial_velocities = {k: self.num(v) for k, v in (init.get("velocities") or {}).items()}

    @classmethod
    def read(cls, path) -> "SceneFile":
        return cls(path)

    # -- numbers ----------------------------------------------------------------------

    def num(self, x, extra: dict | None = None, what: str = "") -> float:
        env = {**self.params, **(extra or {})}
        try:
            return ex.value(x, env)
        except ex.ExpressionError as e:
            raise Unsupported(f"{self.path.name}: {what or x!r}: {e}") from None

    def _parameters(self, spec: dict) -> dict:
        out: dict[str, float] = {}
        for k, v in spec.items():
            out[str(k)] = ex.value(v, out)
        return out

    # -- the scene format -------------------------------------------------------------

    def _read_points(self, spec: list):
        self.points: dict[str, Point] = {}
        for p in spec:
            name = str(p["name"])
            self.points[name] = Point(name, self.num(p["x"]), self.num(p["y"]),
                                      bool(p.get("fixed", False)),
                                      self.num(p["mass"]) if "mass" in p else 0.0)

    def _body(self, name: str, index: int, pts: list[str], spec: dict, mbse: bool) -> Body:
        P = [self.points[n] for n in pts]
        var: dict[str, float] = {"index": float(index)}
        for i in range(len(P)):
            for j in range(len(P)):
                if i != j:
                    var[f"length{i + 1}{j + 1}"] = _dist(P[i], P[j])
        auto = _dist(P[0], P[1])
        length = auto
        if len(P) == 2:
            lspec = spec.get("length", "auto")
            length = self.num(lspec, {**var, "auto": auto}, f"body {name} length")
        var.update(length=length, L=length)
        mass = self.num(spec["mass"], var, f"body {name} mass")
        var["mass"] = mass
        if "cog" in spec:
            cog = np.array([self.num(c, var, f"body {name} cog") for c in spec["cog"]])
        else:
            cog = np.array([length / 2, 0.0])
        if "inertia" in spec and not mbse:
            inertia = self.num(spec["inertia"], var, f"body {name} inertia")
        elif "I0" in spec:
            inertia = self.num(spec["I0"], var, f"body {name} I0") - mass * float(cog @ cog)
        else:
            inertia = mass * length ** 2 / 12       # a uniform slender rod
        return Body(name, pts, mass, length, cog, inertia)

    def _read_bodies(self, spec: list):
        self.bodies = [self._body(str(b.get("name", f"body{i}")), i, [str(n) for n in b["points"]],
                                  b, mbse=False) for i, b in enumerate(spec)]

    def _read_mbse(self, doc: dict):
        params = self._parameters(doc.get("parameters") or {})
        saved, self.params = self.params, params
        self.points = {}
        env: dict[str, float] = {}
        for i, p in enumerate(doc["points"]):
            x = ex.value(p["x"], {**params, **env})
            y = ex.value(p["y"], {**params, **env})
            env[f"x{i}"], env[f"y{i}"] = x, y
            self.points[f"p{i}"] = Point(f"p{i}", x, y, bool(p.get("fixed", False)), 0.0)
        self.bodies = []
        for i, b in enumerate(doc["planar_bodies"]):
            pts = [f"p{int(round(self.num(k)))}" for k in b["points"]]
            self.bodies.append(self._body(f"body{i}", i, pts, b, mbse=True))
        self.params = saved
        self.mbse_coordinates = [
            {"name": f"r{i}", "type": "angle",
             "points": [f"p{int(round(ex.value(k, params)))}" for k in c["points"]]}
            for i, c in enumerate(doc.get("relative_coordinates") or [])]

    def _read_coordinates(self, spec: list):
        self.coordinates = list(getattr(self, "mbse_coordinates", []))
        for c in spec:
            kind = c["type"]
            if kind == "angle":
                pts = list(c["points"])
            elif kind == "relative_angle":
                pts = [*c["segments"][0], *c["segments"][1]]
            else:
                pts = [c["point"], *c["along"]]
            d = {"name": str(c["name"]), "type": kind, "points": [str(p) for p in pts]}
            if "initial" in c:
                d["initial"] = self.num(c["initial"])
            self.coordinates.append(d)
        self.coordinate = {c["name"]: c for c in self.coordinates}

    def _read_constraints(self, spec: list):
        self.constraints = []
        for i, c in enumerate(spec):
            kind = c["type"]
            d = {"name": str(c.get("name", f"{kind}{i}")), "type": kind}
            if kind == "distance":
                a, b = (str(p) for p in c["points"])
                auto = _dist(self.points[a], self.points[b])
                d["points"] = [a, b]
                d["length"] = self.num(c.get("length", "auto"), {"auto": auto},
                                       f"constraint {d['name']} length")
            else:
                d["points"] = [str(c["point"]), *(str(p) for p in c["line"])]
            self.constraints.append(d)

    def _read_effects(self, spec: list):
        self.effects: list[Effect] = []
        for i, e in enumerate(spec):
            kind = e["type"]
            name = str(e.get("name", f"{kind}{i}"))
            s: dict = {}
            if kind == "gravity":
                s["vector"] = np.array([self.num(v) for v in e["vector"]])
            elif kind == "spring_damper":
                a, b = (str(p) for p in e["points"])
                auto = _dist(self.points[a], self.points[b])
                s.update(points=[a, b], stiffness=self.num(e.get("stiffness", 0)),
                         damping=self.num(e.get("damping", 0)),
                         rest_length=self.num(e.get("rest_length", "auto"), {"auto": auto}))
            elif kind == "rotational_spring_damper":
                s.update(coordinate=str(e["coordinate"]), stiffness=self.num(e.get("stiffness", 0)),
                         damping=self.num(e.get("damping", 0)),
                         rest_angle=self.num(e.get("rest_angle", 0)))
            elif kind == "dc_motor":
                s.update(coordinate=str(e["coordinate"]), stall_torque=self.num(e["stall_torque"]),
                         no_load_speed=self.num(e["no_load_speed"]))
            elif kind in ("torque", "force"):
                texts = [e["value"]] if kind == "torque" else list(e["value"])
                s["value"] = [self._load_expression(v, name) for v in texts]
                s["coordinate" if kind == "torque" else "point"] = str(
                    e["coordinate" if kind == "torque" else "point"])
            else:
                raise Unsupported(f"effect {name!r} of type {kind!r}: not in the scene format")
            self.effects.append(Effect(kind, name, s))

    def _load_expression(self, v, effect: str) -> ex.Expression:
        """A load's value with the parameters substituted; t and the state stay names."""
        e = ex.parse(str(v))
        known = dict(self.params)
        for n in e.names:
            if n in self.coordinate:
                known.pop(n, None)      # a coordinate's name is the state, not a parameter
        return _Bound(e, known)

    # -- comparison with mbfg ---------------------------------------------------------

    def names(self) -> list[str]:
        out = [f"{n}.{a}" for n, p in self.points.items() if not p.fixed for a in "xy"]
        return out + [c["name"] for c in self.coordinates]

    def check(self, model, tol: float = 1e-9) -> None:
        """Raises Mismatch naming the first quantity mbfg reads differently."""
        def same(what, mine, theirs):
            mine, theirs = np.atleast_1d(np.asarray(mine, float)), np.atleast_1d(np.asarray(theirs, float))
            scale = max(1.0, float(np.max(np.abs(mine))))
            if mine.shape != theirs.shape or np.max(np.abs(mine - theirs)) > tol * scale:
                raise Mismatch(f"{self.path.name}: {what}: the scene file gives "
                               f"{np.array2string(mine, precision=12)}, mbfg read "
                               f"{np.array2string(theirs, precision=12)}")
        if list(model.names) != self.names():
            raise Mismatch(f"{self.path.name}: coordinates: the scene file gives "
                           f"{self.names()}, mbfg read {list(model.names)}")
        for p in model.points:
            mine = self.points[p["name"]]
            if mine.fixed != p["fixed"]:
                raise Mismatch(f"{self.path.name}: point {mine.name}: fixed is {mine.fixed} "
                               f"in the file, {p['fixed']} in mbfg")
            if mine.fixed:
                same(f"fixed point {mine.name} position", mine.r, [p["x"], p["y"]])
            same(f"point {mine.name} mass", mine.mass, p["mass"] or 0.0)
        if len(model.bodies) != len(self.bodies):
            raise Mismatch(f"{self.path.name}: {len(self.bodies)} bodies in the file, "
                           f"{len(model.bodies)} in mbfg")
        for b, mine in zip(model.bodies, self.bodies):
            if list(b["points"]) != mine.points:
                raise Mismatch(f"body {mine.name}: points {mine.points} in the file, "
                               f"{list(b['points'])} in mbfg")
            same(f"body {mine.name} mass", mine.mass, b["mass"])
            same(f"body {mine.name} centre of mass", mine.cog, b["cog"])
            same(f"body {mine.name} inertia about its centre of mass", mine.inertia,
                 b["inertia_cog"])
            if len(mine.points) == 2:
                same(f"body {mine.name} length", mine.length, b["length"])
        for c, mine in zip(model.constraints, self.constraints):
            if (c["name"], c["type"], list(c["points"])) != (mine["name"], mine["type"], mine["points"]):
                raise Mismatch(f"constraint {mine['name']}: {mine['type']} on {mine['points']} in "
                               f"the file, {c['type']} {c['name']} on {list(c['points'])} in mbfg")
            if mine["type"] == "distance":
                same(f"constraint {mine['name']} length", mine["length"], c["length"])
        for k, (e, mine) in enumerate(zip(model.effects, self.effects)):
            if e["type"] != mine.type:
                raise Mismatch(f"effect {mine.name}: {mine.type} in the file, {e['type']} in mbfg")
            for key in ("vector", "stiffness", "damping", "rest_length", "rest_angle",
                        "stall_torque", "no_load_speed"):
                if key in mine.spec and key in e:
                    same(f"effect {mine.name} {key}", mine.spec[key], e[key])
            if mine.type in ("torque", "force") and not any(v.state_names for v in mine.spec["value"]):
                for t in (0.0, 0.37, 1.9):
                    same(f"effect {mine.name} value at t = {t}",
                         [v({"t": t}) for v in mine.spec["value"]],
                         model.effect_value(k, t))
        if len(model.effects) != len(self.effects):
            raise Mismatch(f"{self.path.name}: {len(self.effects)} effects in the file, "
                           f"{len(model.effects)} in mbfg")
        self.check_initial_state(model)

    def positions(self, q) -> dict[str, np.ndarray]:
        """Every point's position at q (model order, `names()`)."""
        out, k = {}, 0
        for n, p in self.points.items():
            if p.fixed:
                out[n] = p.r
            else:
                out[n] = np.array(q[k:k + 2], dtype=float)
                k += 2
        return out

    def check_initial_state(self, model, tol: float = 1e-8) -> None:
        """mbfg's assembled q0, q̇0 satisfy the file's geometry and initial values."""
        q0, dq0 = np.asarray(model.initial_q), np.asarray(model.initial_dq)
        r = self.positions(q0)
        v = self.positions(dq0)
        for n, p in self.points.items():
            if p.fixed:
                v[n] = np.zeros(2)
        size = max(1.0, max(np.max(np.abs(p.r)) for p in self.points.values()))
        bad = []
        for b in self.bodies:
            P = b.points
            keep = [(P[0], P[1], b.length)]
            for c in P[2:]:
                keep += [(P[0], c, _dist(self.points[P[0]], self.points[c])),
                         (P[1], c, _dist(self.points[P[1]], self.points[c]))]
            for a, c, L in keep:
                d = r[c] - r[a]
                if abs(math.hypot(*d) - L) > tol * size:
                    bad.append(f"body {b.name}: |{a}{c}| = {math.hypot(*d):.12g}, the file's "
                               f"{L:.12g}")
                if abs(d @ (v[c] - v[a])) > tol * size * max(1.0, float(np.max(np.abs(dq0)))):
                    bad.append(f"body {b.name}: {a}{c} stretches at t = 0")
        for c in self.constraints:
            if c["type"] == "distance":
                a, b = c["points"]
                if abs(math.hypot(*(r[b] - r[a])) - c["length"]) > tol * size:
                    bad.append(f"constraint {c['name']}: length {math.hypot(*(r[b] - r[a])):.12g}, "
                               f"the file's {c['length']:.12g}")
            else:
                p, a, b = c["points"]
                e = (r[b] - r[a]) / math.hypot(*(r[b] - r[a]))
                off = e[0] * (r[p] - r[a])[1] - e[1] * (r[p] - r[a])[0]
                if abs(off) > tol * size:
                    bad.append(f"slider {c['name']}: {p} is {off:.3g} m off its line")
        names = self.names()
        for c in self.coordinates:
            k = names.index(c["name"])
            mine = self.coordinate_value(c, r, q0[k])
            if abs(mine - q0[k]) > tol * size:
                bad.append(f"coordinate {c['name']}: {q0[k]:.12g} in mbfg, {mine:.12g} from "
                           "the points")
        for n in self.independent:
            k = names.index(n)
            if n in self.initial_positions and abs(q0[k] - self.initial_positions[n]) > tol * size:
                bad.append(f"initial position of {n}: {q0[k]:.12g} in mbfg, the file's "
                           f"{self.initial_positions[n]:.12g}")
            want = self.initial_velocities.get(n, 0.0)
            if abs(dq0[k] - want) > tol * max(1.0, abs(want)):
                bad.append(f"initial velocity of {n}: {dq0[k]:.12g} in mbfg, the file's {want:.12g}")
        if not self.independent and np.any(dq0 != 0):
            bad.append("initial velocities: the file declares no independent coordinates, "
                       "so the mechanism starts at rest, but mbfg's q̇0 is not zero")
        if bad:
            raise Mismatch(f"{self.path.name}: mbfg's initial state does not fit the file: "
                           + "; ".join(bad[:3]))

    def coordinate_value(self, c: dict, r: dict, near: float) -> float:
        """A relative coordinate from point positions; an angle on the branch nearest `near`."""
        pts = c["points"]
        if c["type"] == "distance":
            p, a, b = pts
            e = r[b] - r[a]
            return float((r[p] - r[a]) @ e) / self.segment_length(a, b)
        if c["type"] == "angle":
            d = r[pts[1]] - r[pts[0]]
            v = math.atan2(d[1], d[0])
        else:
            a, b = r[pts[1]] - r[pts[0]], r[pts[3]] - r[pts[2]]
            v = math.atan2(a[0] * b[1] - a[1] * b[0], a @ b)
        return v + 2 * math.pi * round((near - v) / (2 * math.pi))

    def segment_length(self, a: str, b: str) -> float:
        """L of a distance coordinate's guide: the length its body or distance constraint
        keeps, else the distance as placed (docs/scene-format.md, section 6)."""
        for body in self.bodies:
            if body.points[:2] in ([a, b], [b, a]) and len(body.points) >= 2:
                return body.length
        for c in self.constraints:
            if c["type"] == "distance" and set(c["points"]) == {a, b}:
                return c["length"]
        return _dist(self.points[a], self.points[b])


class _Bound:
    """A load expression with the scene's parameters bound: call it with t and the state."""

    def __init__(self, e: ex.Expression, params: dict):
        self.expr = e
        self.params = {k: v for k, v in params.items() if k in e.names}
        self.names = e.names - set(self.params)
        self.text = e.text

    @property
    def state_names(self) -> set[str]:
        return self.names - {"t", "pi"}

    def __call__(self, env) -> float:
        return self.expr({**self.params, **env})
