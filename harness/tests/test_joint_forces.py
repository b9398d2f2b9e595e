"""Joint forces from Python: the slider-crank's pin between crank and rod balances, and
the forces on each body give it its Newton acceleration."""

import pathlib

import numpy as np

import mbfg

SCENE = pathlib.Path(__file__).resolve().parents[2] / "scenes/slider-crank.yaml"


def test_joint_forces_balance_and_accelerate_the_bodies():
    m = mbfg.load(SCENE)
    r = mbfg.simulate(SCENE, dt=1e-3, t_end=1.0)
    g = np.array([0.0, -9.81])
    for k in range(0, len(r.t), 100):
        f = m.joint_forces(r.q[k], r.dq[k], r.ddq[k], r.t[k])
        assert set(f) == {("crank", "A"), ("crank", "P1"), ("rod", "P1"), ("rod", "S")}
        scale = max(np.abs(v).max() for v in f.values())
        assert np.abs(f[("crank", "P1")] + f[("rod", "P1")]).max() <= 1e-6 * scale
        # The rod (2 kg, uniform, centre at its middle): Σ F + m g = m a_G.
        i = {n: j for j, n in enumerate(m.names)}
        a_p1 = r.ddq[k][[i["P1.x"], i["P1.y"]]]
        a_s = r.ddq[k][[i["S.x"], i["S.y"]]]
        a_g = 0.5 * (a_p1 + a_s)
        total = f[("rod", "P1")] + f[("rod", "S")] + 2.0 * g
        assert np.abs(total - 2.0 * a_g).max() <= 1e-6 * scale
