"""Writes the prescribed motions of the inverse-dynamics suite (scenes/trajectories/).

Each file has the header `t,<coordinate>,...` that `mbfg inverse --trajectory` reads.
Run: python3 harness/prescribed_motions.py  (standard library only).
"""
import math
import pathlib

OUT = pathlib.Path(__file__).resolve().parent.parent / "scenes" / "trajectories"


def write(name, columns, dt, t_end, motion):
    rows = round(t_end / dt) + 1
    lines = [",".join(["t"] + columns)]
    for k in range(rows):
        t = k * dt
        lines.append(",".join(repr(v) for v in [t] + motion(t)))
    (OUT / name).write_text("\n".join(lines) + "\n")


def main():
    OUT.mkdir(parents=True, exist_ok=True)
    # The paper's four-bar (section 7.2): crank angle 1.2 (1 - cos 2t) rad, 10 s at 5 ms.
    write("fourbar-theta.csv", ["theta"], 5e-3, 10.0,
          lambda t: [1.2 * (1.0 - math.cos(2.0 * t))])


if __name__ == "__main__":
    main()
