"""The mechanism in motion, as a GIF or an MP4 (matplotlib): bodies as lines (polygons
for bodies on three or more points), fixed points as triangles, point masses as dots.

From Python: `mbfg.animate(result, model, "run.gif")`. From the command line, on a CSV
that `mbfg simulate` wrote: `mbfg animate RUN.csv --scene SCENE [--out run.gif]`, or
`python -m mbfg.animation RUN.csv --scene SCENE`.
"""

from __future__ import annotations

import argparse
import os
import sys

import numpy as np


def animate(result, model=None, out: str | os.PathLike = "mbfg.gif", fps: int = 25,
            speed: float = 1.0, trail: str | None = None) -> str:
    """Writes the motion of `result` (a `mbfg.Result`, or anything with `t` and `q`
    arrays in the model's coordinate order) to `out`: a GIF, or an MP4 when the name
    ends in .mp4 (that needs ffmpeg). `fps` frames per second of video, `speed` seconds
    of motion per second of video, `trail` the name of a point whose path is drawn.
    `model` defaults to the scene the result was run on. Returns the path written."""
    try:
        import matplotlib
    except ModuleNotFoundError:
        raise ModuleNotFoundError('mbfg.animate draws with matplotlib, which is not installed: '
                                  'pip install "mbfg[plot]" (or pip install matplotlib)',
                                  name="matplotlib") from None
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib import animation

    from . import InvalidArgument, Model, _clip, load

    if model is None:
        scene = getattr(result, "scene", None)
        if scene is None:
            raise InvalidArgument("model: give the Model (or run the result with mbfg.simulate)")
        model = scene if isinstance(scene, Model) else load(scene)
    t = np.asarray(result.t, dtype=float)
    q = np.asarray(result.q, dtype=float)
    if q.ndim != 2 or q.shape[1] != model.n or len(t) != q.shape[0] or len(t) == 0:
        raise InvalidArgument(_clip(f"result: expected t and q with {model.n} columns in the "
                                    f"model's order, got q of shape {q.shape}"))
    if not (fps > 0 and speed > 0):
        raise InvalidArgument("fps and speed must be positive")
    out = os.fspath(out)
    names = [p["name"] for p in model.points]
    if trail is not None and trail not in names:
        raise InvalidArgument(_clip(f"trail: no point {trail!r:.40} (points: {', '.join(names)})"))

    # Frames evenly spaced in time: at most one per sample.
    duration = t[-1] - t[0]
    frames = max(1, min(len(t), int(duration / speed * fps) + 1))
    rows = np.unique(np.searchsorted(t, np.linspace(t[0], t[-1], frames)).clip(0, len(t) - 1))

    def positions(k):
        return {p["name"]: model.point_position(q[k], p["name"]) for p in model.points}

    every = [positions(k) for k in rows]
    xs = np.array([[xy[0] for xy in f.values()] for f in every])
    ys = np.array([[xy[1] for xy in f.values()] for f in every])
    pad = 0.1 * max(xs.max() - xs.min(), ys.max() - ys.min(), 1e-3)
    fig, ax = plt.subplots(figsize=(6, 6))
    ax.set_xlim(xs.min() - pad, xs.max() + pad)
    ax.set_ylim(ys.min() - pad, ys.max() + pad)
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_title(os.path.basename(model.file))
    lines = [ax.plot([], [], "-o", lw=3, ms=4)[0] for _ in model.bodies]
    fixed = [p for p in model.points if p["fixed"]]
    ax.plot([p["x"] for p in fixed], [p["y"] for p in fixed], "k^", ms=10)
    masses = [p["name"] for p in model.points if p["mass"] > 0 and not p["fixed"]]
    dots = ax.plot([], [], "ks", ms=9)[0]
    path = ax.plot([], [], ":", lw=1)[0]
    clock = ax.text(0.02, 0.96, "", transform=ax.transAxes)

    def draw(i):
        f = every[i]
        for line, body in zip(lines, model.bodies):
            pts = body["points"] + (body["points"][:1] if len(body["points"]) > 2 else [])
            line.set_data([f[p][0] for p in pts], [f[p][1] for p in pts])
        dots.set_data([f[p][0] for p in masses], [f[p][1] for p in masses])
        if trail is not None:
            path.set_data([g[trail][0] for g in every[:i + 1]], [g[trail][1] for g in every[:i + 1]])
        clock.set_text(f"t = {t[rows[i]]:.3f} s")
        return [*lines, dots, path, clock]

    anim = animation.FuncAnimation(fig, draw, frames=len(rows), blit=True)
    if out.endswith(".mp4"):
        writer = animation.FFMpegWriter(fps=fps)
    else:
        writer = animation.PillowWriter(fps=fps)
    anim.save(out, writer=writer)
    plt.close(fig)
    return out


class _Csv:
    """A trajectory CSV of `mbfg simulate` read back: t and q in the model's order."""

    def __init__(self, path: str, model):
        import csv
        import gzip
        opener = gzip.open if path.endswith(".gz") else open
        with opener(path, "rt", newline="") as f:
            rows = [r for r in csv.reader(f) if r and not r[0].startswith("#")]
        header, body = rows[0], np.array(rows[1:], dtype=float)
        self.t = body[:, header.index("t")]
        try:
            self.q = body[:, [header.index(f"q:{c}") for c in model.names]]
        except ValueError:
            raise ValueError(f"{path}: its columns are not those of {model.file}") from None


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="mbfg animate", description=__doc__.splitlines()[0])
    ap.add_argument("run", help="a trajectory CSV written by mbfg simulate (.csv or .csv.gz)")
    ap.add_argument("--scene", required=True, help="the scene the run was made from")
    ap.add_argument("--out", help="GIF or MP4 to write [default: the run's name with .gif]")
    ap.add_argument("--fps", type=int, default=25, help="frames per second [25]")
    ap.add_argument("--speed", type=float, default=1.0,
                    help="seconds of motion per second of video [1]")
    ap.add_argument("--trail", help="draw the path of this point")
    args = ap.parse_args(argv)
    from . import InvalidArgument, SceneError, load
    try:
        model = load(args.scene)
        run = _Csv(args.run, model)
        out = args.out or (args.run.removesuffix(".gz").removesuffix(".csv") + ".gif")
        print(animate(run, model, out, fps=args.fps, speed=args.speed, trail=args.trail))
    except (SceneError, InvalidArgument, OSError, ValueError) as e:
        print(f"error: {str(e).splitlines()[0][:290]}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
