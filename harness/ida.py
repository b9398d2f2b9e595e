"""SUNDIALS IDA reference generator: integrates a scene's equations of motion as a DAE.

The equations are the model's own (M, Φ, Φq, Q from the `mbfg` module, natural
coordinates); what is independent of mbfg's solver is the method: IDA's
variable-order, variable-step BDF at tight tolerances on the full DAE.

Two formulations, unknowns y = [q, v, λ(, μ)] over the non-redundant rows of Φ:

- "ggl" (Gear–Gupta–Leimkuhler, stabilized index 2, the default):
      q̇ = v + Φqᵀμ,  M v̇ + Φqᵀλ = Q(q, v, t),  Φq v = 0,  Φ(q) = 0
  Both position and velocity constraints hold along the solution (μ = 0 there).
- "index3":  q̇ = v,  M v̇ + Φqᵀλ = Q,  Φ(q) = 0.
  BDF on index 3 only converges with v and λ left out of the error test (scikit-sundae
  does not expose IDASetSuppressAlg, so they get a huge atol); far less accurate
  than GGL, it serves as a cross-check.

    python -m harness.ida scenes/fourbar.yaml --t-end 5 --dt 1e-3 --out fourbar.csv.gz
"""
from __future__ import annotations

import argparse
import pathlib
import sys
import time

import numpy as np
import sksundae

import mbfg
from harness import trajectory as tj

FORMULATIONS = ("ggl", "index3")
# atol of the entries kept out of IDA's error test (index-2/3 variables).
UNTESTED = 1e6


class Dae:
    """Residual F(t, y, y') and iteration matrix ∂F/∂y + cj ∂F/∂y' of one formulation."""

    def __init__(self, model: mbfg.Model, formulation: str):
        if formulation not in FORMULATIONS:
            raise ValueError(f"unknown formulation {formulation!r}; one of {FORMULATIONS}")
        self.model = model
        self.ggl = formulation == "ggl"
        redundant = set(model.redundant)
        self.rows = np.array([i for i, e in enumerate(model.equations) if e not in redundant],
                             dtype=int)
        self.n, self.r = model.n, len(self.rows)
        self.size = 2 * self.n + (2 if self.ggl else 1) * self.r
        self.M = model.mass_matrix()
        self.eye = np.eye(self.n)

    def split(self, y):
        n, r = self.n, self.r
        return y[:n], y[n:2 * n], y[2 * n:2 * n + r], y[2 * n + r:]

    def residual(self, t, y, yp, res):
        n, r = self.n, self.r
        q, v, lam, mu = self.split(y)
        A = self.model.phi_q(q)[self.rows]
        res[:n] = yp[:n] - v
        res[n:2 * n] = self.M @ yp[n:2 * n] + A.T @ lam - self.model.generalized_forces(q, v, t)
        res[2 * n:2 * n + r] = self.model.phi(q)[self.rows]
        if self.ggl:
            res[:n] -= A.T @ mu
            res[2 * n + r:] = A @ v

    def jacobian(self, t, y, yp, res, cj, J):
        n, r = self.n, self.r
        q, v, lam, mu = self.split(y)
        m = self.model
        A = m.phi_q(q)[self.rows]
        # Φ̇q is linear in q̇, so Φ̇q(q, e_j) = ∂Φq/∂q_j exactly: H[i, k, j] = ∂²Φ_i/∂q_k∂q_j.
        H = np.stack([m.phi_q_dot(q, e)[self.rows] for e in self.eye], axis=2)
        dQdq, dQdv = self.force_derivatives(q, v, t)
        J[:] = 0.0
        J[:n, :n] = cj * self.eye
        J[:n, n:2 * n] = -self.eye
        J[n:2 * n, :n] = np.einsum("i,ikj->kj", lam, H) - dQdq
        J[n:2 * n, n:2 * n] = cj * self.M - dQdv
        J[n:2 * n, 2 * n:2 * n + r] = A.T
        J[2 * n:2 * n + r, :n] = A
        if self.ggl:
            J[:n, :n] -= np.einsum("i,ikj->kj", mu, H)
            J[:n, 2 * n + r:] = -A.T
            J[2 * n + r:, :n] = H @ v
            J[2 * n + r:, n:2 * n] = A

    def force_derivatives(self, q, v, t):
        """∂Q/∂q and ∂Q/∂v in closed form, from the module."""
        return self.model.force_jacobians(q, v, t)

    def initial(self):
        """Consistent y0, y'0: the scene's q, q̇; q̈ and λ from the KKT system; μ = 0."""
        m = self.model
        q, v = np.asarray(m.initial_q, float), np.asarray(m.initial_dq, float)
        a = m.accelerations(q, v, 0.0)
        A = m.phi_q(q)[self.rows]
        lam = np.linalg.lstsq(A.T, m.generalized_forces(q, v, 0.0) - self.M @ a, rcond=None)[0]
        k = self.size - 2 * self.n - self.r
        y0 = np.concatenate([q, v, lam, np.zeros(k)])
        yp0 = np.concatenate([v, a, np.zeros(self.r + k)])
        return y0, yp0

    def tolerances(self, atol: float) -> np.ndarray:
        """atol per entry: q and v tested (index-3 keeps only q), λ and μ not."""
        out = np.full(self.size, UNTESTED)
        out[:self.n if not self.ggl else 2 * self.n] = atol
        return out


def generate(scene, t_end: float, sample_dt: float, formulation: str = "ggl",
             rtol: float = 1e-12, atol: float | None = None, max_num_steps: int = 1_000_000,
             max_step: float = 0.0, params: dict | None = None):
    """Integrates `scene` (a path) over [0, t_end]; returns the Trajectory at multiples of
    sample_dt and its provenance. atol (on q and v, SI units) defaults to rtol;
    max_num_steps bounds the internal steps of the whole run; `params` gives some of the
    scene's parameters other values (as `mbfg.load` does)."""
    start = time.perf_counter()
    model = mbfg.load(str(scene), params)
    dae = Dae(model, formulation)
    atol = rtol if atol is None else atol
    solver = sksundae.ida.IDA(
        dae.residual, jacfn=dae.jacobian, rtol=rtol, atol=dae.tolerances(atol),
        max_num_steps=max_num_steps, max_step=max_step,
        algebraic_idx=list(range(2 * dae.n, dae.size)))
    samples = round(t_end / sample_dt)
    if samples < 1 or abs(samples * sample_dt - t_end) > 1e-9 * t_end:
        raise ValueError(f"t_end {t_end} is not a multiple of sample_dt {sample_dt}")
    times = np.arange(samples + 1) * sample_dt
    times[-1] = t_end

    y0, yp0 = dae.initial()
    ys = np.empty((samples + 1, dae.size))
    ys[0] = y0
    worst_phi = float(np.max(np.abs(model.phi(y0[:dae.n]))))
    solver.init_step(0.0, y0, yp0)
    steps, k, t = 0, 1, 0.0
    # One internal step at a time (to count them and watch Φ at every step); each
    # sample time passed is then taken from IDA's own interpolant (IDASolve, normal mode).
    while k <= samples:
        out = solver.step(t_end, method="onestep", tstop=t_end)
        if not out.success:
            raise RuntimeError(f"IDA ({formulation}, rtol {rtol}) failed after {steps} steps "
                               f"at t = {out.t}: {out.message}")
        if out.t <= t:
            continue    # after an interpolated output IDA first returns its current tn
        steps += 1
        if steps > max_num_steps:
            raise RuntimeError(f"IDA ({formulation}, rtol {rtol}) reached max_num_steps "
                               f"= {max_num_steps} at t = {out.t} before t_end = {t_end}")
        t = out.t
        worst_phi = max(worst_phi, float(np.max(np.abs(model.phi(out.y[:dae.n])))))
        while k <= samples and times[k] <= t:
            sample = solver.step(times[k])
            if not sample.success:
                raise RuntimeError(f"IDA could not output t = {times[k]}: {sample.message}")
            ys[k] = sample.y
            k += 1
    n = dae.n
    q, dq = ys[:, :n], ys[:, n:2 * n]
    ddq = np.array([model.accelerations(qi, vi, ti) for qi, vi, ti in zip(q, dq, times)])
    traj = tj.Trajectory(list(model.names), times, q, dq, ddq)
    worst_phi_dot = max(float(np.max(np.abs(model.phi_q(qi) @ vi))) for qi, vi in zip(q, dq))
    wall = time.perf_counter() - start
    settings = {"rtol": rtol, "atol": atol,
                "error_test": "q, v" if dae.ggl else "q", "atol_untested": UNTESTED,
                "max_num_steps": max_num_steps, "max_step": max_step,
                "jacobian": "analytic; dQ/dq, dQ/dv by forward differences"}
    prov = tj.provenance("ida", scene, formulation, settings, wall,
                         packages=("scikit-sundae", "scipy", "mbfg"),
                         steps=steps, residual_evaluations=int(out.nfev),
                         jacobian_evaluations=int(out.njev), max_abs_phi=worst_phi,
                         max_abs_phi_dot_samples=worst_phi_dot,
                         redundant_rows_dropped=list(model.redundant),
                         sample_dt=sample_dt, t_end=t_end)
    return traj, prov


def provenance_path(out: pathlib.Path) -> pathlib.Path:
    """FILE.csv.gz / FILE.csv → FILE.json."""
    name = out.name
    for suffix in (".gz", ".csv"):
        name = name.removesuffix(suffix)
    return out.with_name(name + ".json")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m harness.ida",
                                 description=__doc__.splitlines()[0])
    ap.add_argument("scene", type=pathlib.Path)
    ap.add_argument("--t-end", type=float, default=5.0)
    ap.add_argument("--dt", type=float, default=1e-3, help="sample step of the output")
    ap.add_argument("--out", type=pathlib.Path, required=True, help="FILE.csv[.gz]")
    ap.add_argument("--formulation", choices=FORMULATIONS, default="ggl")
    ap.add_argument("--rtol", type=float, default=1e-12)
    ap.add_argument("--atol", type=float, default=None, help="on q and v (default: rtol)")
    ap.add_argument("--max-steps", type=int, default=1_000_000,
                    help="bound on the internal steps of the whole run")
    args = ap.parse_args(argv)
    try:
        traj, prov = generate(args.scene, args.t_end, args.dt, args.formulation, args.rtol,
                              args.atol, args.max_steps)
    except (RuntimeError, ValueError) as e:  # IDA's failure, a scene error: one line
        print(f"ida: {' '.join(str(e).split())}", file=sys.stderr)
        return 1
    tj.write(args.out, traj)
    tj.write_provenance(provenance_path(args.out), prov)
    print(f"{args.out}: {prov['steps']} steps in {prov['wall_time_s']:.2f} s, "
          f"max |Φ| {prov['max_abs_phi']:.1e}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
