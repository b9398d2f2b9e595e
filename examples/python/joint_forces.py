"""The force at a four-bar's pins over time, from a forward run: the ground's reaction
at the crank's hinge A and the force the coupler takes at P1. Writes pins.png.

    .venv/bin/python examples/python/joint_forces.py [OUT_DIR]
"""

import pathlib
import sys

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

import mbfg

ROOT = pathlib.Path(__file__).resolve().parents[2]
SCENE = ROOT / "scenes/fourbar.yaml"


def main(out: pathlib.Path) -> None:
    model = mbfg.load(SCENE)
    run = mbfg.simulate(SCENE, dt=1e-3, t_end=3.0)
    at_a, at_p1 = [], []
    for k in range(len(run.t)):
        f = model.joint_forces(run.q[k], run.dq[k], run.ddq[k], run.t[k])
        at_a.append(np.hypot(*f[("crank", "A")]))
        at_p1.append(np.hypot(*f[("coupler", "P1")]))
    print(f"largest force at A {max(at_a):.2f} N, at P1 {max(at_p1):.2f} N")
    plt.plot(run.t, at_a, label="on the crank at A (from the ground)")
    plt.plot(run.t, at_p1, label="on the coupler at P1")
    plt.xlabel("t (s)")
    plt.ylabel("|F| (N)")
    plt.legend()
    plt.savefig(out / "pins.png", dpi=100)


if __name__ == "__main__":
    main(pathlib.Path(sys.argv[1]) if len(sys.argv) > 1 else pathlib.Path("."))
