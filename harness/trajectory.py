"""Trajectories in the CSV contract of DESIGN.md, and their provenance files.

Every generator returns a `Trajectory` (times and q, q̇, q̈ in the scene's model
order) and writes it with `write`, beside a JSON provenance record.
"""
from __future__ import annotations

import dataclasses
import datetime
import functools
import gzip
import hashlib
import io
import json
import pathlib
import platform
import re
import subprocess
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


ROOT = pathlib.Path(__file__).resolve().parent.parent

# A scene's `mechanism:` key (block style at the top level, or inside a top-level flow
# mapping): the only other file a scene reads (docs/scene-format.md, section 10).
_MECHANISM = re.compile(r"""(?:^|[{,][ \t]*)mechanism[ \t]*:[ \t]*(?P<v>"[^"]*"|'[^']*'|[^\s,}#][^,}#\n]*)""",
                        re.MULTILINE)


def display_path(path: str | pathlib.Path) -> str:
    """A path for a record: relative to the repository when inside it (so that records
    do not carry the writing machine's folders), else as given."""
    try:
        return pathlib.Path(path).resolve().relative_to(ROOT).as_posix()
    except ValueError:
        return str(path)


def scene_files(scene: str | pathlib.Path) -> list[pathlib.Path]:
    """Every file the scene reads: itself, then the MBSE file it names with `mechanism:`
    (relative to the scene's folder), if any."""
    scene = pathlib.Path(scene)
    files = [scene]
    text = scene.read_bytes().decode("utf-8", errors="replace")
    m = _MECHANISM.search(text)
    if m:
        name = m.group("v").strip()
        if name[:1] in "'\"" and name[-1:] == name[:1]:
            name = name[1:-1]
        files.append(scene.parent / name)
    return files


def file_hash(path: str | pathlib.Path) -> str:
    return "sha256:" + hashlib.sha256(pathlib.Path(path).read_bytes()).hexdigest()


def scene_hash(scene: str | pathlib.Path) -> str:
    """sha256 of what the scene reads. A scene alone: of its bytes; a scene naming an
    MBSE file: of the sha256 digests of the scene's and the MBSE file's bytes, in that
    order (names left out, so that moving the files keeps the hash)."""
    files = scene_files(scene)
    if len(files) == 1:
        return file_hash(files[0])
    h = hashlib.sha256()
    for f in files:
        h.update(hashlib.sha256(f.read_bytes()).digest())
    return "sha256:" + h.hexdigest()


def is_current(record: dict, scene: str | pathlib.Path) -> bool:
    """Whether a provenance record was written from the scene's files as they are now.
    Records written before `files` was recorded hashed the scene file alone."""
    if "files" not in record:
        return record.get("scene_hash") == file_hash(scene)
    return record.get("scene_hash") == scene_hash(scene)


@functools.lru_cache(maxsize=None)
def git_state() -> dict:
    """The repository's commit and whether its tracked files differ from it (the
    harness and the scenes of the suite live there); {} outside a git checkout."""
    def git(*args):
        return subprocess.run(["git", "-C", str(ROOT), *args], capture_output=True,
                              text=True, timeout=30, check=True).stdout.strip()
    try:
        commit = git("rev-parse", "HEAD")
        dirty = bool(git("status", "--porcelain", "--untracked-files=no"))
    except (OSError, subprocess.SubprocessError):
        return {}
    return {"commit": commit, "dirty": dirty}


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
        "scene": display_path(scene),
        "scene_hash": scene_hash(scene),
        "files": {display_path(f): file_hash(f) for f in scene_files(scene)},
        "git": git_state(),
        "versions": versions("numpy", *packages),
        "machine": platform.machine(),
        "date": datetime.date.today().isoformat(),
        **extra,
    }


def write_provenance(path: pathlib.Path, record: dict) -> None:
    pathlib.Path(path).write_text(json.dumps(record, indent=2, sort_keys=True) + "\n")


class Unsupported(ValueError):
    """A scene element a generator cannot model: it refuses rather than drop it."""


def main(argv=None) -> int:
    """Summarizes a trajectory file, or the difference of two on their common times."""
    import argparse
    import sys
    ap = argparse.ArgumentParser(
        prog="python -m harness.trajectory",
        description="Summarize a trajectory in the CSV contract (plain or .gz), or compare "
                    "two (max |Δq| per coordinate at the times both have).")
    ap.add_argument("file", type=pathlib.Path)
    ap.add_argument("other", type=pathlib.Path, nargs="?")
    args = ap.parse_args(argv)
    try:
        a = read(args.file)
        b = read(args.other) if args.other else None
    except (OSError, ValueError) as e:
        print(f"trajectory: {' '.join(str(e).split())}", file=sys.stderr)
        return 1
    print(f"{args.file}: {len(a.t)} rows, t from {a.t[0]:g} to {a.t[-1]:g} s, "
          f"{len(a.names)} coordinates: {', '.join(a.names)}")
    if b is None:
        return 0
    if a.names != b.names:
        print(f"trajectory: the coordinates differ ({', '.join(b.names)})", file=sys.stderr)
        return 1
    common, ia, ib = np.intersect1d(np.round(a.t, 9), np.round(b.t, 9), return_indices=True)
    if not len(common):
        print("trajectory: no common times", file=sys.stderr)
        return 1
    d = np.max(np.abs(a.q[ia] - b.q[ib]), axis=0)
    print(f"max |Δq| over {len(common)} common times:")
    for name, v in zip(a.names, d):
        print(f"  {name:<16} {v:.3e}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
