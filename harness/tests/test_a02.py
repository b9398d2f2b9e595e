"""The A02 page's pieces: its reference is the exact branch motion, its error measure
falls with dt on a short N four-bar run (at second order with the trapezoidal rule, at
fourth with Hermite–Simpson), and its page lists every run it made."""
import numpy as np

import mbfg
from harness import a02


def test_reference_keeps_the_branch_energy():
    loops = 40
    t = np.linspace(0.0, 4.0, 81)
    b0 = a02.exact_b0(loops, t)
    assert np.allclose(np.hypot(b0[:, 0], b0[:, 1]), 1.0)
    # θ from B0; the energy I θ̇²/2 + c g sin θ at the start is 0.5 I + c g.
    inertia, c = (loops + 1) / 3 + loops, (loops + 1) / 2 + loops
    theta = np.unwrap(np.arctan2(b0[:, 1], b0[:, 0]))
    assert theta[-1] < theta[0] - 2 * np.pi          # it turns over, clockwise
    omega = np.gradient(theta, t, edge_order=2)
    energy = 0.5 * inertia * omega**2 + c * 9.81 * np.sin(theta)
    assert np.max(np.abs(energy[1:-1] / (0.5 * inertia + c * 9.81) - 1)) < 2e-2


def test_error_falls_at_second_order_through_two_flats(tmp_path):
    rows = [a02.run_mbfg(5, "trapezoidal", dt, 2.0) for dt in (2e-3, 1e-3)]
    assert all(r["status"] == "converged" and r["passages"] == 2 for r in rows), rows
    assert 3.0 < rows[0]["error"] / rows[1]["error"] < 6.0, rows
    a02.write(rows, 5, 2.0, tmp_path, 1.0)
    page = (tmp_path / "a02.md").read_text()
    assert page.count("| mbfg | trapezoidal") == 2
    assert "| high (≤ 0.001 m) | " in page


def test_hermite_simpson_passes_both_flats_at_fourth_order(tmp_path):
    rows = [a02.run_mbfg(5, "hermite-simpson", dt, 2.0) for dt in (4e-3, 2e-3)]
    assert all(r["status"] == "converged" and r["passages"] == 2 for r in rows), rows
    assert rows[0]["error"] / rows[1]["error"] > 12.0, rows
    orders = a02.observed_orders(rows, "hermite-simpson")
    assert len(orders) == 1 and orders[0][3] > 3.5, orders
    a02.write(rows, 5, 2.0, tmp_path, 1.0)
    page = (tmp_path / "a02.md").read_text()
    assert page.count("| mbfg | hermite-simpson") == 2
    assert "| hermite-simpson | 4 | 2 |" in page


def test_the_shorter_chains_have_their_table(tmp_path):
    shorter = [{"loops": 5, **a02.run_mbfg(5, "trapezoidal", dt, 2.0)} for dt in (2e-3, 1e-3)]
    assert all(r["status"] == "converged" for r in shorter), shorter
    a02.write([], 40, 2.0, tmp_path, 1.0, shorter)
    page = (tmp_path / "a02.md").read_text()
    assert "## The shorter chains" in page
    row = next(line for line in page.splitlines() if line.startswith("| 5 | trapezoidal |"))
    cells = [c.strip() for c in row.strip("|").split("|")]
    assert cells[2] == "2 of 2"
    order = float(cells[-1])
    assert 1.5 < order < 3.0, row
    csv_text = (tmp_path / "a02.csv").read_text().splitlines()
    assert ",loops," in csv_text[0] and len(csv_text) == 3


def test_a_tolerance_on_the_run_lands_near_it_and_the_page_shows_it(tmp_path):
    """The 5-loop chain over 20 s: a tolerance on each step ends far off (the motion
    near its separatrix drifts in phase); on the run it lands within 10 times."""
    run = a02.run_mbfg_rtol(5, 1e-5, "run", 20.0)
    steps = a02.run_mbfg_rtol(5, 1e-5, "steps", 20.0)
    assert run["status"] == steps["status"] == "converged", (run, steps)
    assert 1e-6 <= run["error"] <= 1e-4, run
    assert steps["error"] > 1e-3, steps
    assert run["estimated"] <= 1.0 and len(run["step_rtols"].split()) >= 2, run
    a02.write([], 5, 20.0, tmp_path, 1.0, tolerance_rows=[run, steps])
    page = (tmp_path / "a02.md").read_text()
    assert "## With a tolerance" in page
    assert "| run | 1e-05 | converged |" in page and "| steps | 1e-05 | converged |" in page
