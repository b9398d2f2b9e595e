"""A parameter study without writing a scene per run: the swinging bar of the tutorial,
its spring stiffness swept from 10 to 200 N/m, and the highest angle the bar reaches
against it. Writes sweep.png and prints the table.

    .venv/bin/python examples/python/parameter_sweep.py [OUT_DIR]
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
    stiffness = np.linspace(10, 200, 20)
    highest = []
    for k in stiffness:
        run = mbfg.simulate(SCENE, dt=2e-3, t_end=3.0, params={"k": float(k)})
        highest.append(run.column("q:theta").max())
    for k, th in zip(stiffness, highest):
        print(f"k = {k:6.1f} N/m   highest angle {np.degrees(th):7.2f}°")
    plt.plot(stiffness, np.degrees(highest), "o-")
    plt.xlabel("spring stiffness k (N/m)")
    plt.ylabel("highest bar angle (°)")
    plt.savefig(out / "sweep.png", dpi=100)


if __name__ == "__main__":
    main(pathlib.Path(sys.argv[1]) if len(sys.argv) > 1 else pathlib.Path("."))
