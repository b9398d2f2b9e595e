"""Writes the prescribed motions of the inverse-dynamics suite (scenes/trajectories/).

Each file has the header `t,<coordinate>,...` that `mbfg inverse --trajectory` reads.
Run: python3 harness/prescribed_motions.py [--out DIR]  (standard library only),
or python -m harness.prescribed_motions.
"""
import argparse
import math
import pathlib
import random

OUT = pathlib.Path(__file__).resolve().parent.parent / "scenes" / "trajectories"


def write(name, columns, dt, t_end, motion, out=OUT, fmt=repr):
    rows = round(t_end / dt) + 1
    lines = [",".join(["t"] + columns)]
    for k in range(rows):
        t = k * dt
        lines.append(",".join([repr(t)] + [fmt(v) for v in motion(t)]))
    (out / name).write_text("\n".join(lines) + "\n")


def main(argv=None):
    ap = argparse.ArgumentParser(prog="python -m harness.prescribed_motions",
                                 description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=pathlib.Path, default=OUT,
                    help="folder of the tables (default: scenes/trajectories/)")
    out = ap.parse_args(argv).out
    out.mkdir(parents=True, exist_ok=True)
    # The paper's four-bar (section 7.2): crank angle 1.2 (1 - cos 2t) rad, 10 s at 5 ms.
    write("fourbar-theta.csv", ["theta"], 5e-3, 10.0,
          lambda t: [1.2 * (1.0 - math.cos(2.0 * t))], out)
    # The same as measured data (`mbfg inverse --sample-sigma`): written to 8
    # significant digits, and with 1e-4 rad Gaussian noise (Python's random, seed 1).
    write("fourbar-theta-8digits.csv", ["theta"], 5e-3, 10.0,
          lambda t: [1.2 * (1.0 - math.cos(2.0 * t))], out, fmt=lambda v: f"{v:.8g}")
    noise = random.Random(1)
    write("fourbar-theta-noisy.csv", ["theta"], 5e-3, 10.0,
          lambda t: [1.2 * (1.0 - math.cos(2.0 * t)) + noise.gauss(0.0, 1e-4)], out)
    # The pick-and-place robot: both motors from rest at the scene's configuration
    # (motor1 = -3π/4, motor2 = -π/4) through one 5 s cycle; with τ = 2πt/5 and
    # c = (1 - cos τ)/2 the plate goes down and sideways and back:
    # motor1 = m1 + 0.3c + 0.2c·sin τ, motor2 = m2 - 0.3c + 0.2c·sin τ.
    def robot(t):
        tau = 2.0 * math.pi * t / 5.0
        c = (1.0 - math.cos(tau)) / 2.0
        return [-0.75 * math.pi + 0.3 * c + 0.2 * c * math.sin(tau),
                -0.25 * math.pi - 0.3 * c + 0.2 * c * math.sin(tau)]
    write("pick-and-place.csv", ["motor1", "motor2"], 5e-3, 5.0, robot, out)
    # The double pendulum, both joints driven from rest, horizontal (absolute angles).
    write("double-pendulum.csv", ["theta1", "theta2"], 5e-3, 5.0,
          lambda t: [-0.8 * (1.0 - math.cos(1.5 * t)), -1.1 * (1.0 - math.cos(2.3 * t))], out)


if __name__ == "__main__":
    main()
