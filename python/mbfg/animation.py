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
            speed: float = 1.0, trail: str | None = None, forces: bool = False) -> str:
    """Writes the motion of `result` (a `mbfg.Result`, or anything with `t` and `q`
    arrays in the model's coordinate order) to `out`: a GIF, or an MP4 when the name
    ends in .mp4 (that needs ffmpeg). `fps` frames per second of video, `speed` seconds
    of motion per second of video, `trail` the name of a point whose path is drawn.
    `model` defaults to the scene the result was run on. `forces=True` draws the
    ground's reaction at every fixed point as an arrow (it needs the result's q̇ and q̈).
    Beside the time, the label gives the independent angles (at most two): the speed of
    one that turns more than a full turn over the run, else its value. Returns the path written."""
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

    if not (hasattr(result, "t") and hasattr(result, "q")):
        raise InvalidArgument(_clip(
            f"result: expected the Result of mbfg.simulate, estimate or inverse (or an object "
            f"with t and q), got {type(result).__name__}: mbfg.animate(result, model, out)"))
    if isinstance(model, (str, os.PathLike)):
        model = load(model)
    elif model is not None and not isinstance(model, Model):
        raise InvalidArgument(_clip(f"model: expected a Model or a scene path, got "
                                    f"{type(model).__name__}"))
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

    # Every point's x and y at every frame, (frames, points), from q's columns.
    xs = np.empty((len(rows), len(names)))
    ys = np.empty((len(rows), len(names)))
    for j, p in enumerate(model.points):
        if p["index"] is None:
            xs[:, j], ys[:, j] = p["x"], p["y"]
        else:
            xs[:, j], ys[:, j] = q[rows, p["index"]], q[rows, p["index"] + 1]
    at = {n: j for j, n in enumerate(names)}
    pad = 0.1 * max(xs.max() - xs.min(), ys.max() - ys.min(), 1e-3)
    fig, ax = plt.subplots(figsize=(6, 6), dpi=80)
    fig.subplots_adjust(top=0.9)
    ax.set_xlim(xs.min() - pad, xs.max() + pad)
    ax.set_ylim(ys.min() - pad, ys.max() + pad)
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_title(os.path.basename(model.file), loc="left")
    # The ground: fixed points, and the guides of sliders on fixed lines (drawn across
    # the whole view); slots of sliders on moving lines move with their frames.
    fixed = [p for p in model.points if p["fixed"]]
    ax.plot([p["x"] for p in fixed], [p["y"] for p in fixed], "k^", ms=10)
    slots = []
    for c in model.constraints:
        if c["type"] not in ("fixed_slider", "mobile_slider"):
            continue
        a, b = at[c["points"][1]], at[c["points"][2]]
        if c["type"] == "fixed_slider":
            (x0, y0), (x1, y1) = (xs[0, a], ys[0, a]), (xs[0, b], ys[0, b])
            reach = 4 * (abs(xs).max() + abs(ys).max() + pad)
            d = np.array([x1 - x0, y1 - y0]) / max(np.hypot(x1 - x0, y1 - y0), 1e-300)
            ax.plot([x0 - reach * d[0], x0 + reach * d[0]], [y0 - reach * d[1], y0 + reach * d[1]],
                    "-", color="0.6", lw=6, alpha=0.5, solid_capstyle="butt")
        else:
            slots.append((a, b, ax.plot([], [], "-", color="0.6", lw=8, alpha=0.5,
                                        solid_capstyle="round")[0]))
    bodies = [[at[n] for n in b["points"] + (b["points"][:1] if len(b["points"]) > 2 else [])]
              for b in model.bodies]
    lines = [ax.plot([], [], "-o", lw=3, ms=4)[0] for _ in bodies]
    masses = [at[p["name"]] for p in model.points if p["mass"] > 0 and not p["fixed"]]
    dots = ax.plot([], [], "ks", ms=9)[0]
    path = ax.plot([], [], ":", lw=1)[0]
    # Outside the axes, so that it never covers the mechanism.
    clock = fig.text(0.98, 0.92, "", ha="right", va="bottom", family="monospace")
    dq = getattr(result, "dq", None)
    dq = None if dq is None else np.asarray(dq, dtype=float)
    angles = []
    for c in model.coordinates:
        if c["type"] != "angle" or (model.independent and c["name"] not in model.independent):
            continue
        k = model.index(c["name"])
        turns = np.ptp(q[:, k]) > 2 * np.pi
        if turns and dq is not None:
            angles.append((c["name"], dq[rows, k], "{:.2f} rad/s", ": "))
        else:
            angles.append((c["name"], q[rows, k], "{:.3f} rad", " = "))
    angles = angles[:2]
    arrows = None
    if forces:
        ddq = getattr(result, "ddq", None)
        if dq is None or ddq is None:
            raise InvalidArgument("forces: the result needs dq and ddq (a Result of mbfg.simulate)")
        ground = [p["name"] for p in fixed]
        pushes = np.zeros((len(rows), len(ground), 2))
        for i, k in enumerate(rows):
            f = model.joint_forces(q[k], dq[k], np.asarray(ddq)[k], t[k])
            for j, g in enumerate(ground):
                pushes[i, j] = -sum((v for (b, p), v in f.items() if p == g), np.zeros(2))
        largest = np.abs(pushes).max()
        scale = 2 * pad / largest if largest > 0 else 1.0
        gx, gy = [p["x"] for p in fixed], [p["y"] for p in fixed]
        arrows = ax.quiver(gx, gy, pushes[0, :, 0] * scale, pushes[0, :, 1] * scale,
                           angles="xy", scale_units="xy", scale=1, color="tab:red", width=0.006)
        ax.text(0.02, 0.02, f"ground reactions, largest {largest:.3g} N", transform=ax.transAxes,
                color="tab:red")
    moving = [*(s[2] for s in slots), *lines, dots, path, clock]
    if arrows is not None:
        moving.append(arrows)
    for artist in moving:
        artist.set_animated(True)

    def draw(i):
        x, y = xs[i], ys[i]
        for a, b, line in slots:
            line.set_data([x[a], x[b]], [y[a], y[b]])
        for line, pts in zip(lines, bodies):
            line.set_data(x[pts], y[pts])
        dots.set_data(x[masses], y[masses])
        if trail is not None:
            path.set_data(xs[:i + 1, at[trail]], ys[:i + 1, at[trail]])
        label = f"t = {t[rows[i]]:.3f} s"
        for name, values, form, prefix in angles:
            label += f"   {name}{prefix}" + form.format(values[i])
        clock.set_text(label)
        if arrows is not None:
            arrows.set_UVC(pushes[i, :, 0] * scale, pushes[i, :, 1] * scale)
        return moving

    if out.endswith(".mp4"):
        anim = animation.FuncAnimation(fig, draw, frames=len(rows), blit=True)
        anim.save(out, writer=animation.FFMpegWriter(fps=fps))
        plt.close(fig)
        return out
    # A GIF: the still background rendered once, each frame's moving parts drawn on a
    # copy of it, and every frame mapped to the first one's palette (the colours do not
    # change), which is what makes this fast.
    from PIL import Image
    canvas = fig.canvas
    canvas.draw()
    background = canvas.copy_from_bbox(fig.bbox)
    images = []
    for i in range(len(rows)):
        canvas.restore_region(background)
        for artist in draw(i):
            fig.draw_artist(artist)
        images.append(Image.fromarray(np.asarray(canvas.buffer_rgba())[..., :3].copy()))
    plt.close(fig)
    palette = images[0].quantize(colors=64, method=Image.Quantize.MEDIANCUT)
    frames_p = [im.quantize(palette=palette, dither=Image.Dither.NONE) for im in images]
    frames_p[0].save(out, save_all=True, append_images=frames_p[1:], duration=1000 / fps, loop=0)
    return out


class _Csv:
    """A trajectory CSV of `mbfg simulate` read back by mbfg's own reader: t and q in
    the model's order (q̇, q̈ zero where the file has none); a missing file, a
    missing column or a row that is not numbers is named as the CLI names it."""

    def __init__(self, path: str, model):
        from . import _native
        raw = _native.read_trajectory(model._m, path)
        self.t, self.q, self.dq, self.ddq = raw["t"], raw["q"], raw["dq"], raw["ddq"]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="mbfg animate", description=__doc__.splitlines()[0])
    ap.add_argument("run", help="a trajectory CSV written by mbfg simulate (.csv or .csv.gz)")
    ap.add_argument("--scene", required=True, help="the scene the run was made from")
    ap.add_argument("--out", help="GIF or MP4 to write [default: the run's name with .gif]")
    ap.add_argument("--fps", type=int, default=25, help="frames per second [25]")
    ap.add_argument("--speed", type=float, default=1.0,
                    help="seconds of motion per second of video [1]")
    ap.add_argument("--trail", help="draw the path of this point")
    ap.add_argument("--forces", action="store_true",
                    help="draw the ground's reaction at every fixed point")
    args = ap.parse_args(argv)
    from . import InvalidArgument, SceneError, load
    try:
        model = load(args.scene)
        run = _Csv(args.run, model)
        out = args.out or (args.run.removesuffix(".gz").removesuffix(".csv") + ".gif")
        print(animate(run, model, out, fps=args.fps, speed=args.speed, trail=args.trail,
                      forces=args.forces))
    except (SceneError, InvalidArgument, OSError, ValueError) as e:
        print(f"error: {str(e).splitlines()[0][:290]}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
