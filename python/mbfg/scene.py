"""Scenes built in code: `mbfg.Scene()` holds the same sections as a scene file (name,
parameters, points, bodies, coordinates, constraints, effects, independent, initial,
sensors, estimation, mechanism), each entry with the file format's keys
(docs/scene-format.md), and writes them as YAML. The Rust reader checks them, so a
built scene gets the same messages as a file, naming the line of its YAML."""
from __future__ import annotations

import json
import math
import re
from typing import Any, Mapping

from . import _native

_PLAIN = re.compile(r"^[A-Za-z_][A-Za-z0-9_.]*$")
# Plain words the reader (YAML 1.2, strict booleans) reads as something else than a string.
_RESERVED = {"true", "false", "null", "~"}


def _scalar(v: Any) -> str:
    if v is None:
        return "null"
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, str):
        if _PLAIN.match(v) and v.lower() not in _RESERVED:
            return v
        return json.dumps(v, ensure_ascii=False)
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        if not math.isfinite(v):
            raise ValueError(f"{v} is not a finite number; a scene holds finite numbers only")
        return repr(v)  # the shortest text that reads back as the same double
    raise TypeError(f"cannot write {v!r:.60} ({type(v).__name__}) in a scene")


def _flow(v: Any) -> str:
    if hasattr(v, "tolist"):
        v = v.tolist()  # numpy arrays and scalars as Python values
    if isinstance(v, Mapping):
        return "{" + ", ".join(f"{_key(k)}: {_flow(x)}" for k, x in v.items()) + "}"
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_flow(x) for x in v) + "]"
    return _scalar(v)


def _key(k: Any) -> str:
    if not isinstance(k, str):
        raise TypeError(f"scene keys are strings, got {k!r:.60}")
    return _scalar(k)


def to_yaml(sections: Mapping[str, Any]) -> str:
    """A scene's sections as YAML in the style of the suite's files: one line per
    entry of a list, nested mappings indented."""
    lines: list[str] = []

    def block(d: Mapping, indent: int) -> None:
        pad = " " * indent
        for k, v in d.items():
            if isinstance(v, Mapping) and v:
                lines.append(f"{pad}{_key(k)}:")
                block(v, indent + 2)
            elif isinstance(v, (list, tuple)) and v and any(isinstance(x, Mapping) for x in v):
                lines.append(f"{pad}{_key(k)}:")
                for item in v:
                    lines.append(f"{pad}  - {_flow(item)}")
            else:
                lines.append(f"{pad}{_key(k)}: {_flow(v)}")
    block(sections, 0)
    return "\n".join(lines) + "\n"


class Scene:
    """A scene built in code, section by section, with the file format's keys:

        s = mbfg.Scene("fourbar")
        s.point("A", 0, 0, fixed=True).point("P1", 1, 0).point("P2", 1, 2)
        s.point("B", 4, 0, fixed=True)
        s.body("crank", ["A", "P1"], mass=1).body("coupler", ["P1", "P2"], mass=2)
        s.body("rocker", ["P2", "B"], mass=4, length="sqrt(13)")
        s.gravity()
        model = s.model()            # or mbfg.simulate(s, ...)

    Every method returns the scene, so calls chain. Values are numbers or expression
    strings over the parameters ("L*cos(th0)"), as in a file. Keys not named by a
    method's arguments go through as given (`cog=[0.5, 0]`, `inertia=0.1`), so every
    scene the file format can express can be built; `set(section, value)` sets any
    top-level section whole. `to_yaml()` writes the scene file, `Scene.from_yaml(text)`
    and `Scene.from_dict(d)` read one back; `model()` assembles it."""

    def __init__(self, name: str | None = None, description: str | None = None):
        self._s: dict[str, Any] = {}
        if name is not None:
            self._s["name"] = name
        if description is not None:
            self._s["description"] = description

    # Sections -------------------------------------------------------------------
    def parameter(self, name: str, value) -> "Scene":
        """A named value that later values and expressions may use."""
        self._s.setdefault("parameters", {})[name] = value
        return self

    def mechanism(self, file: str) -> "Scene":
        """Take points, bodies and coordinates from an MBSE mechanism file."""
        self._s["mechanism"] = file
        return self

    def point(self, name: str, x, y, fixed: bool = False, mass=None) -> "Scene":
        """A point at (x, y) m: fixed to the ground, or free (its x, y are
        coordinates); `mass` puts a point mass on it (kg)."""
        p: dict[str, Any] = {"name": name, "x": x, "y": y}
        if fixed:
            p["fixed"] = True
        if mass is not None:
            p["mass"] = mass
        self._s.setdefault("points", []).append(p)
        return self

    def body(self, name: str, points, mass=None, **keys) -> "Scene":
        """A rigid body on two or more points (its frame: origin at the first, x axis
        towards the second), with `mass` (kg) and optionally `length`, `cog` ([x, y] in
        its frame), `inertia` (about the centre of mass) or `I0` (about the first point)."""
        b: dict[str, Any] = {"name": name, "points": list(points)}
        if mass is not None:
            b["mass"] = mass
        b.update(keys)
        self._s.setdefault("bodies", []).append(b)
        return self

    def coordinate(self, name: str, type: str, **keys) -> "Scene":
        """A relative coordinate added to q: `angle` (points=[from, to]),
        `relative_angle` (segments=[[a, b], [c, d]]) or `distance` (point=, along=[a,
        b]); `initial` gives its value at t = 0."""
        self._s.setdefault("coordinates", []).append({"name": name, "type": type, **keys})
        return self

    def constraint(self, type: str, name: str | None = None, **keys) -> "Scene":
        """An explicit constraint: `distance` (points=[a, b], length=), `fixed_slider`
        or `mobile_slider` (point=, line=[a, b])."""
        c: dict[str, Any] = {"type": type}
        if name is not None:
            c["name"] = name
        c.update(keys)
        self._s.setdefault("constraints", []).append(c)
        return self

    def effect(self, type: str, name: str | None = None, **keys) -> "Scene":
        """Something that acts: `gravity` (vector=[gx, gy]), `spring_damper`,
        `rotational_spring_damper`, `dc_motor`, `torque` (coordinate=, value=) or
        `force` (point=, value=[fx, fy]), with the file format's keys."""
        e: dict[str, Any] = {"type": type}
        if name is not None:
            e["name"] = name
        e.update(keys)
        self._s.setdefault("effects", []).append(e)
        return self

    def gravity(self, gx=0, gy=-9.81) -> "Scene":
        """Uniform gravity, m/s² (nothing acts unless the scene names it)."""
        return self.effect("gravity", vector=[gx, gy])

    def independent(self, *names: str) -> "Scene":
        """The coordinates a run in IC integrates (as many as the degrees of freedom)."""
        self._s["independent"] = list(names)
        return self

    def initial(self, positions: Mapping[str, Any] | None = None,
                velocities: Mapping[str, Any] | None = None) -> "Scene":
        """Initial values of coordinates of q, and velocities of independent ones."""
        init = self._s.setdefault("initial", {})
        if positions:
            init.setdefault("positions", {}).update(positions)
        if velocities:
            init.setdefault("velocities", {}).update(velocities)
        return self

    def sensor(self, name: str, type: str, **keys) -> "Scene":
        """A sensor (`sensors:`, docs/estimation.md): encoder, gyroscope,
        accelerometer, marker or expression, with sigma, rate, …"""
        self._s.setdefault("sensors", []).append({"name": name, "type": type, **keys})
        return self

    def estimation(self, **keys) -> "Scene":
        """The `estimation:` section (process_sigma, initial_sigma, inputs, …)."""
        self._s.setdefault("estimation", {}).update(keys)
        return self

    def set(self, section: str, value) -> "Scene":
        """Any top-level section, whole (as it would be written in the file)."""
        self._s[section] = value
        return self

    # Out and back ----------------------------------------------------------------
    def to_dict(self) -> dict:
        """The sections as plain Python values (a copy)."""
        return json.loads(json.dumps(self._s))

    def to_yaml(self) -> str:
        """The scene file."""
        return to_yaml(self._s)

    @classmethod
    def from_dict(cls, sections: Mapping[str, Any]) -> "Scene":
        scene = cls()
        scene._s = json.loads(json.dumps(dict(sections)))
        return scene

    @classmethod
    def from_yaml(cls, text: str) -> "Scene":
        """A scene file's text, read by the same parser as `mbfg check`."""
        parsed = _native.parse_yaml(text)
        if not isinstance(parsed, dict):
            raise _native.SceneError(f"<yaml>: a scene is a mapping, got {type(parsed).__name__}")
        return cls.from_dict(_integers(parsed))

    def model(self, params: Mapping[str, float] | None = None):
        """The assembled Model (as `mbfg.load` of the file)."""
        from . import load
        return load(self, params)

    def __eq__(self, other) -> bool:
        return isinstance(other, Scene) and self.to_dict() == other.to_dict()

    def __repr__(self) -> str:
        counts = ", ".join(f"{len(v)} {k}" for k, v in self._s.items() if isinstance(v, list))
        return f"<mbfg.Scene {self._s.get('name', '')!r}: {counts}>"


def _integers(v):
    """Whole numbers the parser read as floats back as ints (as they were written)."""
    if isinstance(v, dict):
        return {k: _integers(x) for k, x in v.items()}
    if isinstance(v, list):
        return [_integers(x) for x in v]
    if isinstance(v, float) and v.is_integer() and abs(v) < 2**53:
        return int(v)
    return v
