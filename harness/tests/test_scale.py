"""The scaling scenes of scenes/scale/ (docs/benchmarks.md, section 3): the committed
files are the generator's (harness/scale_scenes.py), `mbfg check` passes on each, the
pendulums assemble to the sizes they should; mbfg's runs of the N four-bar against the
exact one-degree-of-freedom motion of the published problem, and of the n-link pendulum
against IDA. No reference here comes from mbfg.

The largest sizes are slow with today's dense per-step algebra; horizons are cut so that
each test stays within seconds to ~20 s (see HORIZON and SLOW below)."""
import math
import os
import pathlib
import subprocess
import time

import numpy as np
import pytest
from scipy.integrate import solve_ivp

import mbfg
from harness import ida, scale_scenes

ROOT = pathlib.Path(__file__).resolve().parents[2]
SCALE = ROOT / "scenes" / "scale"
MBFG = pathlib.Path(os.environ.get("CARGO_TARGET_DIR", ROOT / "target")) / "release" / "mbfg"
G = 9.81
DT = 1e-3

# N four-bar: seconds simulated in DC at dt = 1 ms. Up to just before the first flat
# configuration (0.7085 s at N = 1 … 0.7216 s at N = 40) for N ≤ 20; the larger chains
# cost 20-180 ms a step today, so shorter horizons keep each test under ~10 s.
HORIZON = {1: 0.7, 2: 0.7, 5: 0.7, 10: 0.7, 20: 0.7, 50: 0.2, 100: 0.05}
# Pendulum sizes whose steps take seconds (DC) to over ten minutes (IC, 128 links) today:
# run only with MBFG_SCALE_SLOW=1 (a few steps each).
SLOW = {128, 256}
slow = pytest.mark.skipif(not os.environ.get("MBFG_SCALE_SLOW"),
                          reason="seconds to minutes a step today; set MBFG_SCALE_SLOW=1")


def fourbar(n_loops):
    return SCALE / f"n-fourbar-{n_loops}.yaml"


def pendulum(n_links):
    return SCALE / f"n-pendulum-{n_links}.yaml"


# --- the files -------------------------------------------------------------------------

def test_committed_files_are_the_generators_output():
    expected = scale_scenes.scenes()
    on_disk = sorted(p.name for p in SCALE.glob("*.yaml"))
    assert on_disk == sorted(expected)
    for name, text in expected.items():
        assert (SCALE / name).read_text() == text, f"{name}: run python -m harness.scale_scenes"
    assert scale_scenes.main(["--check"]) == 0


def test_generator_writes_the_published_nfourbar_scenes(tmp_path):
    """Same text as the benchmark files of scenes/benchmarks/ for the sizes both have
    (N = 40 is only there), and --check notices a changed file."""
    for n in (1, 5, 10, 40):
        assert scale_scenes.fourbar(n) == (ROOT / "scenes" / "benchmarks" / f"n-fourbar-{n}.yaml").read_text()
    assert scale_scenes.main(["--out", str(tmp_path)]) == 0
    assert scale_scenes.main(["--out", str(tmp_path), "--check"]) == 0
    (tmp_path / "n-pendulum-4.yaml").write_text(scale_scenes.pendulum(4).replace("M: 1", "M: 2"))
    assert scale_scenes.main(["--out", str(tmp_path), "--check"]) == 1


@pytest.mark.parametrize("name", sorted(scale_scenes.scenes()))
def test_mbfg_check_passes(name):
    assert MBFG.exists(), f"{MBFG}: build it with cargo build --release"
    r = subprocess.run([MBFG, "check", SCALE / name], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    size = int(name.split("-")[-1].removesuffix(".yaml"))
    dof = 1 if name.startswith("n-fourbar") else size
    assert f"degrees of freedom: {dof}\n" in r.stdout


@pytest.mark.parametrize("n_links", scale_scenes.PENDULUM_SIZES)
def test_pendulum_assembles(n_links):
    """3n coordinates (the n free points' x, y and the n link angles), 2n equations,
    n degrees of freedom; 1 m and 1 kg in total, straight at 30° from the downward
    vertical, at rest."""
    m = mbfg.load(str(pendulum(n_links)))
    assert (m.n, m.m, m.dof) == (3 * n_links, 2 * n_links, n_links)
    assert m.redundant == []
    assert m.independent == [f"phi{i}" for i in range(1, n_links + 1)]
    assert len(m.bodies) == n_links
    assert sum(b["mass"] for b in m.bodies) == pytest.approx(1.0, rel=1e-14)
    assert sum(b["length"] for b in m.bodies) == pytest.approx(1.0, rel=1e-12)
    for b in m.bodies:                     # uniform slender rods
        assert b["inertia_cog"] == pytest.approx(b["mass"] * b["length"] ** 2 / 12, rel=1e-12)
    q = np.asarray(m.initial_q)
    assert np.max(np.abs(m.phi(q))) <= 1e-12
    assert np.all(np.asarray(m.initial_dq) == 0.0)
    a = math.radians(30)
    tip = np.array([math.sin(a), -math.cos(a)])
    np.testing.assert_allclose(m.point_position(q, f"P{n_links}"), tip, atol=1e-12)
    np.testing.assert_allclose(q[[m.names.index(f"phi{i}") for i in range(1, n_links + 1)]],
                               -math.pi / 2 + a, atol=1e-14)
    # the centre of mass of the straight chain is at its middle
    assert m.potential_energy(q) == pytest.approx(-G * 0.5 * math.cos(a), rel=1e-12)
    assert m.is_conservative


# --- N four-bar against its exact motion -----------------------------------------------

def exact_theta(n_loops, times):
    """The parallelogram branch as a one-degree-of-freedom system (docs/benchmarks.md):
    I θ̈ = −c g cos θ, I = (N+1)/3 + N, c = (N+1)/2 + N, θ(0) = π/2, θ̇(0) = −1 rad/s."""
    inertia, c = (n_loops + 1) / 3 + n_loops, (n_loops + 1) / 2 + n_loops
    sol = solve_ivp(lambda t, s: [s[1], -c * G / inertia * math.cos(s[0])], (0, times[-1]),
                    [math.pi / 2, -1.0], method="DOP853", t_eval=times, rtol=1e-12, atol=1e-12)
    assert sol.success
    return sol.y[0]


@pytest.mark.parametrize("n_loops", scale_scenes.FOURBAR_SIZES)
def test_nfourbar_dc_follows_the_exact_motion(n_loops):
    """DC, N_w = 1, dt = 1 ms, up to HORIZON[N]: every step converges, |Φ| ≤ 1e-9 at
    every step, the mechanism stays on the parallelogram branch (every crank at θ, every
    B_i at the height of B0) and θ(t) follows the exact motion to within the trapezoidal
    rule's O(dt²) error."""
    t_end = HORIZON[n_loops]
    start = time.perf_counter()
    r = mbfg.simulate(str(fourbar(n_loops)), coords="dc", dt=DT, t_end=t_end)
    wall = time.perf_counter() - start
    m = mbfg.load(str(fourbar(n_loops)))
    q = np.asarray(r.q)
    assert r.summary["complete"] and len(r.t) == round(t_end / DT) + 1
    phi = max(float(np.max(np.abs(m.phi(qk)))) for qk in q)
    assert phi <= 1e-9
    th = q[:, m.names.index("theta")]
    th_ex = exact_theta(n_loops, np.asarray(r.t))
    # every crank has the angle θ: B_i = A_i + (cos θ, sin θ), A_i = (i, 0)
    branch = 0.0
    for i in range(n_loops + 1):
        bx, by = q[:, m.names.index(f"B{i}.x")], q[:, m.names.index(f"B{i}.y")]
        branch = max(branch, float(np.max(np.abs(bx - i - np.cos(th)))),
                     float(np.max(np.abs(by - np.sin(th)))),
                     float(np.max(np.abs(by - q[:, m.names.index("B0.y")]))))
    err = float(np.max(np.abs(th - th_ex)))
    print(f"N = {n_loops}: {len(r.t) - 1} steps in {wall:.1f} s, max |Φ| {phi:.1e}, "
          f"branch {branch:.1e} m, θ error {err:.2e} rad")
    assert branch <= 1e-8
    assert err <= 2e-5                      # O(dt²): 5e-6 rad at 0.7 s today, for every N


def test_nfourbar_dc_error_is_second_order():
    """The θ error at 0.7 s falls about fourfold when dt halves (N = 2)."""
    errs = []
    for dt in (2e-3, 1e-3):
        r = mbfg.simulate(str(fourbar(2)), coords="dc", dt=dt, t_end=0.7)
        m = mbfg.load(str(fourbar(2)))
        th = np.asarray(r.q)[:, m.names.index("theta")]
        errs.append(float(np.max(np.abs(th - exact_theta(2, np.asarray(r.t))))))
    print(f"θ error {errs[0]:.2e} at 2 ms, {errs[1]:.2e} at 1 ms")
    assert 2.5 <= errs[0] / errs[1] <= 6


# --- n-link pendulum ------------------------------------------------------------------

@pytest.mark.parametrize("coords", ["dc", "ic"])
@pytest.mark.parametrize("n_links", [2, 4, 8])
def test_pendulum_against_ida(n_links, coords):
    """0.2 s against IDA (GGL, rtol 1e-10): the points' error is the integrator's
    O(dt²) and falls about fourfold from dt = 1 ms to 0.5 ms; |Φ| ≤ 1e-9."""
    t_end = 0.2
    traj, prov = ida.generate(pendulum(n_links), t_end, 1e-3, "ggl", 1e-10)
    assert prov["max_abs_phi"] <= 1e-9
    m = mbfg.load(str(pendulum(n_links)))
    pts = [i for i, name in enumerate(m.names) if name.startswith("P")]
    errs = []
    for dt in (1e-3, 5e-4):
        r = mbfg.simulate(str(pendulum(n_links)), coords=coords, dt=dt, t_end=t_end)
        q = np.asarray(r.q)
        step = round(1e-3 / dt)
        assert len(r.t) == round(t_end / dt) + 1
        assert max(float(np.max(np.abs(m.phi(qk)))) for qk in q) <= 1e-9
        errs.append(float(np.max(np.abs(q[::step][:, pts] - traj.q[:, pts]))))
    print(f"n = {n_links} {coords}: max point error {errs[0]:.2e} m at 1 ms, "
          f"{errs[1]:.2e} m at 0.5 ms")
    assert errs[0] <= 1e-5                  # 0.6-2e-6 m today
    assert errs[0] / errs[1] >= 3


@pytest.mark.parametrize("coords", ["dc", "ic"])
@pytest.mark.parametrize("n_links", [n if n not in SLOW else pytest.param(n, marks=slow)
                                     for n in scale_scenes.PENDULUM_SIZES])
def test_pendulum_constraints_hold(n_links, coords):
    """A few steps of every size: each converges, |Φ| ≤ 1e-9, and the chain falls
    (the tip moves down, the energy is kept to the integrator's accuracy)."""
    steps = 3
    r = mbfg.simulate(str(pendulum(n_links)), coords=coords, dt=DT, t_end=steps * DT)
    m = mbfg.load(str(pendulum(n_links)))
    q = np.asarray(r.q)
    assert r.summary["complete"] and len(r.t) == steps + 1
    assert max(float(np.max(np.abs(m.phi(qk)))) for qk in q) <= 1e-9
    tip = m.names.index(f"P{n_links}.y")
    assert q[-1, tip] < q[0, tip]
    e = [m.kinetic_energy(v) + m.potential_energy(x) for x, v in zip(q, np.asarray(r.dq))]
    assert m.kinetic_energy(np.asarray(r.dq)[-1]) > 0
    assert abs(e[-1] - e[0]) <= 1e-3 * abs(e[0])


# --- the report page (harness/scaling.py) ----------------------------------------------

def test_scaling_slope_fits_a_power_law():
    from harness import scaling
    rows = [{"n": n, "us_per_step": 3.0 * n ** 1.5, "status": "ok"} for n in (4, 8, 16, 32)]
    rows.append({"n": 64, "status": "skipped: over the budget"})
    assert scaling.slope(rows, upper_half=False) == pytest.approx(1.5, rel=1e-12)
    rows[3]["us_per_step"] = 3.0 * 32 ** 1.5 * 2       # only the upper half sees the kink
    assert scaling.slope(rows, upper_half=True) == pytest.approx(2.5, rel=1e-12)
    assert scaling.slope(rows[:1], upper_half=False) is None


def test_scaling_page_on_small_sizes(tmp_path, monkeypatch):
    """The page, its CSV and its plot for the smallest pendulums, with a baseline; then
    with a budget no run meets: every size skipped, and the page names each."""
    import csv as csvmod
    from harness import scaling
    # The page's own horizon (a step of these pendulums costs 10-70 µs against a set-up
    # of about 1 ms: with 200 steps, a loaded machine's timing noise made a whole run
    # no slower than its first step now and then).
    monkeypatch.setattr(scaling, "MAX_STEPS", 600)
    monkeypatch.setattr(scaling, "MIN_MEASURED", 0.05)
    baseline = tmp_path / "old.csv"
    baseline.write_text("family,size,series,us_per_step,status\n"
                        "n-pendulum,2,DC N_w=1,1e9,ok\n")
    rows = scaling.write(tmp_path, "test machine", families=["n-pendulum"], repeats=1,
                         baseline_path=baseline, max_size=8)
    page = (tmp_path / "scaling.md").read_text()
    assert (tmp_path / "scaling.png").stat().st_size > 1000
    with open(tmp_path / "scaling.csv", newline="") as f:
        table = list(csvmod.DictReader(f))
    assert len(table) == len(rows) == 3 * 4                    # 3 sizes × 4 series
    assert {r["n"] for r in rows} == {6, 12, 24}
    assert all(r["status"] == "ok" for r in rows), [r["status"] for r in rows]
    assert all(r["max_phi"] <= 1e-9 and r["steps"] >= scaling.MIN_STEPS for r in rows)
    assert page.startswith("# Per-step cost") and "| n-link pendulum | DC N_w=1 | 2 … 8 (3) |" in page
    assert "× baseline" in page
    assert "## Hermite–Simpson against the trapezoidal rule" in page
    assert [(f, n) for f, n, _ in scaling.hs_ratios(rows)] == [("n-pendulum", n) for n in (2, 4, 8)]
    assert "| n-link pendulum | 2 | " in page
    assert "## Not measured" not in page
    assert "Above `--max-size`, not run: n-pendulum-16, n-pendulum-32" in page

    rows = scaling.write(tmp_path, "test machine", families=["n-pendulum"], repeats=1,
                         budget=1e-6, max_size=4)
    page = (tmp_path / "scaling.md").read_text()
    assert len(rows) == 2 * 4 and all(r["status"].startswith("skipped") for r in rows)
    for r in rows:
        assert f"- n-pendulum-{r['size']} {r['series']}: skipped" in page
    assert "× baseline" not in page
    assert "## Hermite–Simpson against the trapezoidal rule" not in page


def test_hermite_simpson_ratio_is_per_size_where_both_ran():
    from harness import scaling
    rows = [{"family": "n-fourbar", "size": 5, "series": "DC N_w=1", "us_per_step": 40.0, "status": "ok"},
            {"family": "n-fourbar", "size": 5, "series": "DC N_w=1 HS", "us_per_step": 110.0,
             "status": "ok"},
            {"family": "n-fourbar", "size": 10, "series": "DC N_w=1", "us_per_step": 80.0, "status": "ok"},
            {"family": "n-fourbar", "size": 10, "series": "DC N_w=1 HS", "status": "skipped: budget"}]
    assert scaling.hs_ratios(rows) == [("n-fourbar", 5, 2.75)]
    lines = scaling.hs_ratio_lines(rows)
    assert lines[-1] == "| N four-bar (IFToMM A02) | 5 | 2.75 | not met |"


def test_max_size_bounds_one_family_or_all():
    from harness.scaling import parse_max_size
    assert parse_max_size(None) is None
    assert parse_max_size("8") == 8
    assert parse_max_size("n-pendulum=64") == {"n-pendulum": 64}
    assert parse_max_size("n-pendulum=64,n-fourbar=10") == {"n-pendulum": 64, "n-fourbar": 10}
    for bad, says in [("x", "not a whole number"), ("foo=3", "unknown family 'foo'"),
                      ("n-pendulum=x", "'x' for n-pendulum")]:
        with pytest.raises(ValueError, match=says):
            parse_max_size(bad)


def test_a_long_run_is_tried_apart_and_given_up_after_its_time():
    from harness import scaling
    path = scaling.scene("n-pendulum", 2)
    assert scaling.run_within(path, "dc", {"window": 1}, 5, timeout=60)
    assert not scaling.run_within(path, "dc", {"window": 1}, 5, timeout=1e-3)
