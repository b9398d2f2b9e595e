"""Trajectories in the CSV contract of DESIGN.md, and their provenance files.

Every generator returns a `Trajectory` (times and q, q̇, q̈ in the scene's model
order) and writes it with `write`, beside a JSON provenance record.
"""
from __future__ import annotations

import dataclasses
import datetime
import gzip
import hashlib
import io
import json
import pathlib
import platform
from importlib import metadata

import numpy as np


@dataclasses.dataclass
class Trajectory:
    names: list[str]
    t: np.ndarray          # (rows,)
    q: np.ndarray          # (rows, n)
    dq: np.ndarray         # (rows, n)
    ddq: np.ndarray        # (rows, n)

    def columns(self) -> list[str]:
        return (["t"] + [f"q:{c}" for c in self.names] + [f"dq:{c}" for c in self.names]
                + [f"ddq:{c}" for c in self.names])

    def data(self) -> np.ndarray:
        return np.column_stack([self.t, self.q, self.dq, self.ddq])

    def sample(self, dt: float) -> "Trajectory":
        """The rows at multiples of dt (the times must contain them)."""
        step = self.t[1] - self.t[0]
        every = round(dt / step)
        if every < 1 or abs(every * step - dt) > 1e-9 * dt:
            raise ValueError(f"cannot sample a trajectory of step {step} at {dt}")
        sl = slice(None, None, every)
        return Trajectory(self.names, self.t[sl], self.q[sl], self.dq[sl], self.ddq[sl])


def write(path: pathlib.Path, trajectory: Trajectory) -> None:
    """Writes the CSV contract (gzip-compressed when the name ends in .gz)."""
    if not np.all(np.isfinite(trajectory.data())):
        raise ValueError(f"{path}: refusing to write a trajectory with NaN or Inf")
    buf = io.StringIO()
    buf.write(",".join(trajectory.columns()) + "\n")
    for row in trajectory.data():
        buf.write(",".join(repr(float(v)) for v in row) + "\n")
    text = buf.getvalue().encode()
    path = pathlib.Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    if path.suffix == ".gz":
        # mtime=0 keeps the file identical when the numbers are.
        with open(path, "wb") as f, gzip.GzipFile(fileobj=f, mode="wb", mtime=0) as g:
            g.write(text)
    else:
        path.write_bytes(text)


def read(path: pathlib.Path) -> Trajectory:
    """Reads a trajectory in the CSV contract (plain or .gz)."""
    with (gzip.open(path, "rt") if str(path).endswith(".gz") else open(path)) as f:
        header = f.readline().strip().split(",")
        data = np.loadtxt(f, delimiter=",", ndmin=2)
    names = [c[2:] for c in header if c.startswith("q:")]
    n = len(names)
    if header[0] != "t" or len(header) < 1 + 3 * n:
        raise ValueError(f"{path}: not a trajectory in the CSV contract")
    return Trajectory(names, data[:, 0], data[:, 1:1 + n], data[:, 1 + n:1 + 2 * n],
                      data[:, 1 + 2 * n:1 + 3 * n])


def scene_hash(scene: str | pathlib.Path) -> str:
    """sha256 of the scene file's bytes (and of the MBSE file it names, if any)."""
    h = hashlib.sha256(pathlib.Path(scene).read_bytes())
    return "sha256:" + h.hexdigest()


def versions(*packages: str) -> dict[str, str]:
    out = {"python": platform.python_version()}
    for p in packages:
        try:
            out[p] = metadata.version(p)
        except metadata.PackageNotFoundError:
            out[p] = "not installed"
    return out


def provenance(generator: str, scene: str | pathlib.Path, formulation: str,
               settings: dict, wall_time: float, packages: tuple[str, ...] = (),
               **extra) -> dict:
    """The provenance record every reference carries."""
    return {
        "generator": generator,
        "formulation": formulation,
        "settings": settings,
        "wall_time_s": wall_time,
        "scene": str(scene),
        "scene_hash": scene_hash(scene),
        "versions": versions("numpy", *packages),
        "machine": platform.machine(),
        "date": datetime.date.today().isoformat(),
        **extra,
    }


def write_provenance(path: pathlib.Path, record: dict) -> None:
    pathlib.Path(path).write_text(json.dumps(record, indent=2, sort_keys=True) + "\n")


class Unsupported(ValueError):
    """A scene element a generator cannot model: it refuses rather than drop it."""
