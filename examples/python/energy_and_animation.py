"""A damped run's energy balance and its animation: the tutorial's swinging bar loses
energy to its damper; the damper's work accounts for it. Writes energy.png and
swing.gif.

    .venv/bin/python examples/python/energy_and_animation.py [OUT_DIR]
"""

import pathlib
import sys

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

import mbfg

ROOT = pathlib.Path(__file__).resolve().parents[2]
SCENE = ROOT / "examples/tutorial/swinging-bar.yaml"


def main(out: pathlib.Path) -> None:
    model = mbfg.load(SCENE)
    run = mbfg.simulate(SCENE, dt=1e-3, t_end=4.0)
    energy = np.array([model.kinetic_energy(dq) + model.potential_energy(q)
                       for q, dq in zip(run.q, run.dq)])
    print(f"energy lost to the damper over 4 s: {energy[0] - energy[-1]:.4f} J")
    plt.plot(run.t, energy)
    plt.xlabel("t (s)")
    plt.ylabel("kinetic + potential energy (J)")
    plt.savefig(out / "energy.png", dpi=100)
    mbfg.animate(run, out=out / "swing.gif", fps=15, trail="T")


if __name__ == "__main__":
    main(pathlib.Path(sys.argv[1]) if len(sys.argv) > 1 else pathlib.Path("."))
