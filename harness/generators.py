"""The simulators the harness knows, registered in one place.

Every tool that can integrate a scene is a `Generator`: a name, what it needs from the
scene, a `run(scene, t_end, dt, **settings) -> (Trajectory, provenance)` function, its
fast defaults (seconds on a few-second horizon, for the command line and
`harness.compare`) and its reference settings (accuracy first, for `harness.reference`).
reference.py, timing.py, report.py and compare.py all read this registry; adding a
simulator is one `register(Generator(...))` (docs/harness.md).

    python -m harness.generators        # lists the registered generators
"""
from __future__ import annotations

import argparse
import dataclasses
import hashlib
import importlib.util
import math
import os
import pathlib
import sys
import time
from typing import Mapping, Protocol

import mbfg
from harness import trajectory as tj


class Run(Protocol):
    """Integrates `scene` (a path) over [0, t_end] and returns its trajectory at the
    multiples of dt (in the scene's model order) with a provenance record
    (`trajectory.provenance`). Raises `trajectory.Unsupported` for a scene it cannot
    model, and any other exception when the run itself fails."""

    def __call__(self, scene: str | os.PathLike, t_end: float, dt: float,
                 **settings) -> tuple[tj.Trajectory, dict]: ...


@dataclasses.dataclass(frozen=True)
class Generator:
    name: str                          # what --tools takes: "ida"
    label: str                         # in tables and plots: "IDA"
    title: str                         # one line on what it is
    run: Run
    defaults: Mapping = dataclasses.field(default_factory=dict)   # fast settings
    reference: Mapping = dataclasses.field(default_factory=dict)  # accuracy settings
    # What the scene must declare: "independent" (independent coordinates).
    needs: tuple[str, ...] = ()
    # Python packages it imports (checked before a run, so that a missing one is a
    # refusal with its reason, not an ImportError).
    packages: tuple[str, ...] = ()
    # Higher: a better truth. compare's reference is the highest that runs.
    accuracy: int = 0
    # The accuracy-against-time sweeps of harness/timing.py: (variant, setting, values,
    # further settings); a point per value.
    sweeps: tuple[tuple[str, str, tuple[float, ...], Mapping], ...] = ()
    # The harness modules whose code makes its numbers (hashed into a reference's
    # provenance, so that a reference written by other code is told apart).
    source: tuple[str, ...] = ()

    def source_hash(self) -> str:
        """sha256 over the files of `source`, in order: which version of this generator's
        code a reference was written by."""
        digest = hashlib.sha256()
        for module in self.source:
            digest.update(pathlib.Path(importlib.util.find_spec(module).origin).read_bytes())
        return "sha256:" + digest.hexdigest()

    def request(self, settings: Mapping | None = None, accurate: bool = False) -> dict:
        """What a run asks of this generator: its settings (the defaults, or with accurate
        the reference settings, updated by `settings`) and its code's hash."""
        return {"generator": self.name, "settings": self.settings(settings, accurate),
                "source": self.source_hash()}

    def settings(self, settings: Mapping | None = None, accurate: bool = False) -> dict:
        """The defaults (or, with accurate, the reference settings) updated by `settings`."""
        return {**(self.reference if accurate else self.defaults), **(settings or {})}

    def refusal(self, model: mbfg.Model) -> str | None:
        """Why this generator cannot run the scene, known before running it; else None."""
        for p in self.packages:
            if importlib.util.find_spec(p) is None:
                return f"the Python package {p!r} is not installed"
        if "independent" in self.needs and not model.independent:
            return "needs independent coordinates; the scene declares none (`independent:`)"
        return None

    def generate(self, scene, t_end: float, dt: float, settings: Mapping | None = None,
                 accurate: bool = False) -> tuple[tj.Trajectory, dict]:
        """`run` with the defaults (or, with accurate, the reference settings) updated
        by `settings`."""
        return self.run(scene, t_end, dt, **self.settings(settings, accurate))


@dataclasses.dataclass
class Outcome:
    """One run as compare and reference report it: a trajectory, or why there is none."""
    generator: str
    status: str                        # "ok", "refused", "failed"
    reason: str = ""
    trajectory: tj.Trajectory | None = None
    provenance: dict | None = None
    wall_time_s: float | None = None


def attempt(gen: Generator, scene, t_end: float, dt: float, settings: Mapping | None = None,
            accurate: bool = False, model: mbfg.Model | None = None) -> Outcome:
    """Runs a generator and never raises for the scene's sake: refusals and failures
    come back as an Outcome with a one-line reason."""
    model = model if model is not None else mbfg.load(str(scene))
    why = gen.refusal(model)
    if why:
        return Outcome(gen.name, "refused", why)
    start = time.perf_counter()
    try:
        traj, prov = gen.generate(scene, t_end, dt, settings, accurate)
    except tj.Unsupported as e:
        return Outcome(gen.name, "refused", one_line(e))
    except KeyboardInterrupt:
        raise
    except Exception as e:  # a solver's failure, whatever its type: one line, no traceback
        return Outcome(gen.name, "failed", one_line(e))
    return Outcome(gen.name, "ok", "", traj, prov, time.perf_counter() - start)


def one_line(e: BaseException) -> str:
    text = " ".join(str(e).split())
    return text[:300] if text else type(e).__name__


def fit_step(h: float, dt: float) -> float:
    """The largest step ≤ h that divides the sample step dt (fixed-step generators);
    h itself when it does (so that the recorded settings are the ones asked for)."""
    k = round(dt / h)
    if k >= 1 and abs(k * h - dt) <= 1e-9 * dt:
        return h
    return dt / max(1, math.ceil(dt / h))


# ---------------------------------------------------------------- the runs

def run_mbfg(scene, t_end, dt, coords="dc", **options):
    """mbfg.simulate; options as its keywords (window, batch, integrator, noise, …)."""
    model = mbfg.load(str(scene))
    start = time.perf_counter()
    r = mbfg.simulate(str(scene), coords=coords, dt=dt, t_end=t_end, **options)
    wall = time.perf_counter() - start
    n = model.n
    traj = tj.Trajectory(list(model.names), r.t, r.q[:, :n], r.dq[:, :n], r.ddq[:, :n])
    summary = {k: v for k, v in r.summary.items() if k not in ("reselections", "warnings")}
    prov = tj.provenance("mbfg", scene, f"natural coordinates, {coords.upper()}",
                         {"coords": coords, "dt": dt, **options}, wall, packages=("mbfg",),
                         summary=summary, warnings=list(r.summary.get("warnings", [])),
                         sample_dt=dt, t_end=t_end)
    return traj, prov


def run_ida(scene, t_end, dt, **settings):
    from harness import ida
    return ida.generate(scene, t_end, dt, **settings)


def run_exudyn(scene, t_end, dt, h=1e-4, **settings):
    from harness import exudyn_ref
    return exudyn_ref.generate(scene, t_end, dt, h=fit_step(h, dt), **settings)


def run_pinocchio(scene, t_end, dt, h=2e-4, **settings):
    from harness import pinocchio_ref
    return pinocchio_ref.generate(scene, t_end, dt, h=fit_step(h, dt), **settings)


REGISTRY: dict[str, Generator] = {}


def register(gen: Generator) -> Generator:
    if gen.name in REGISTRY:
        raise ValueError(f"a generator named {gen.name!r} is already registered")
    REGISTRY[gen.name] = gen
    return gen


def get(name: str) -> Generator:
    try:
        return REGISTRY[name]
    except KeyError:
        raise KeyError(f"unknown generator {name!r}; registered: {', '.join(REGISTRY)}") from None


# Fast defaults, measured on the four-bar over 5 s at dt = 1 ms (RMSE of the points
# against the committed reference): IDA rtol 1e-12 6e-10 m in 0.8 s; exudyn h = 1e-4
# 6e-7 m in 0.8 s (1e-5: 15 s); Pinocchio RK4 h = 2e-4 3e-12 m in 1 s (1e-5: 50 s).
# The reference settings are those of the committed references (reference.py).
# In this order in tables and plots.
register(Generator(
    "mbfg", "mbfg", "mbfg, natural coordinates (dependent coordinates, DC)", run_mbfg,
    defaults={"coords": "dc"}, reference={"coords": "dc"}))
register(Generator(
    "mbfg-ic", "mbfg IC", "mbfg, independent coordinates (IC)", run_mbfg,
    defaults={"coords": "ic"}, reference={"coords": "ic"}, needs=("independent",)))
register(Generator(
    "exudyn", "exudyn", "exudyn: the scene as planar rigid bodies, generalized-alpha", run_exudyn,
    defaults={"solver": "generalized_alpha", "h": 1e-4},
    reference={"solver": "generalized_alpha", "h": 1e-5}, packages=("exudyn",), accuracy=1,
    source=("harness.exudyn_ref", "harness.scene_file"),
    sweeps=(("generalized-alpha", "h", (1e-3, 5e-4, 2e-4, 1e-4, 1e-5),
             {"solver": "generalized_alpha"}),
            ("trapezoidal index-2", "h", (1e-3, 5e-4, 2e-4, 1e-4, 1e-5),
             {"solver": "trapezoidal_index2"}))))
register(Generator(
    "ida", "IDA", "SUNDIALS IDA: BDF on mbfg's equations as a GGL index-2 DAE", run_ida,
    defaults={"formulation": "ggl", "rtol": 1e-12},
    reference={"formulation": "ggl", "rtol": 1e-14}, packages=("sksundae",), accuracy=3,
    source=("harness.ida",),
    sweeps=(("GGL index-2", "rtol", (1e-4, 1e-5, 1e-6, 1e-7, 1e-8, 1e-9, 1e-10, 1e-11, 1e-12),
             {"formulation": "ggl"}),)))
register(Generator(
    "pinocchio", "Pinocchio", "Pinocchio: joint coordinates of a tree of revolute and "
    "prismatic joints (+ loop closures), RK4", run_pinocchio,
    defaults={"h": 2e-4}, reference={"h": 1e-5}, packages=("pinocchio",), accuracy=2,
    source=("harness.pinocchio_ref", "harness.scene_file"),
    sweeps=(("RK4", "h", (1e-3, 5e-4, 1e-4), {}),
            ("DOP853 adaptive", "rtol", (1e-6, 1e-8, 1e-10, 1e-12), {"method": "dop853"}))))


def parse_settings(items: list[str]) -> dict:
    """KEY=VALUE strings to settings: numbers as numbers, true/false as booleans."""
    out = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep or not key:
            raise ValueError(f"expected KEY=VALUE, not {item!r}")
        low = value.lower()
        if low in ("true", "false"):
            out[key] = low == "true"
            continue
        for cast in (int, float):
            try:
                out[key] = cast(value)
                break
            except ValueError:
                pass
        else:
            out[key] = value
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m harness.generators",
                                 description=__doc__.split("\n\n")[0])
    ap.parse_args(argv)
    for g in REGISTRY.values():
        print(f"{g.name:<10} {g.title}")
        print(f"{'':<10} defaults {dict(g.defaults)}; reference {dict(g.reference)}"
              + (f"; needs {', '.join(g.needs)}" if g.needs else "")
              + (f"; packages {', '.join(g.packages)}" if g.packages else ""))
    return 0


if __name__ == "__main__":
    sys.exit(main())
