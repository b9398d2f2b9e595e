"""harness.horizons on tiny horizons: the runs, the slopes, the page."""
from __future__ import annotations

import csv
import math
import os
import pathlib

import pytest

from harness import horizons
from harness.pages import ROOT

# MBFG_BINARY: a release binary built elsewhere (another CARGO_TARGET_DIR).
BINARY = pathlib.Path(os.environ.get("MBFG_BINARY", ROOT / "target" / "release" / "mbfg"))


def test_slope_is_the_log_log_least_squares_slope():
    assert horizons.slope([1e3, 1e4, 1e5], [2.0, 20.0, 200.0]) == pytest.approx(1.0)
    assert horizons.slope([1e3, 1e4], [5.0, 5.0]) == pytest.approx(0.0)
    assert horizons.slope([1e3, 1e4], [1.0, 100.0]) == pytest.approx(2.0)
    assert math.isnan(horizons.slope([1e3], [1.0]))


def test_t_end_counts_step_zero():
    assert horizons.t_end(1000) == "0.999"
    assert horizons.t_end(1_000_000) == "999.999"


def test_verdicts_flag_super_linear_time_and_growing_smoother_memory():
    rows = [
        {"config": "smoother N_w=1", "steps": n, "exit": 0, "wall_s": n * n * 1e-6,
         "cpu_s": n * n * 1e-6,
         "peak_rss_mib": 5.0 + n * 1e-3}
        for n in (1000, 10000)
    ]
    text = "\n".join(horizons.verdicts(rows, horizons.fits(rows)))
    assert "**super-linear**" in text and "**growing**" in text


@pytest.mark.skipif(not BINARY.exists(), reason="needs target/release/mbfg")
def test_tiny_horizons_write_the_page(tmp_path: pathlib.Path):
    assert horizons.main(["--steps", "100,100000", "--configs", "smoother N_w=1,batch",
                          "--mbfg", str(BINARY), "--out-dir", str(tmp_path)]) == 0
    rows = list(csv.DictReader(open(tmp_path / "horizons.csv")))
    assert [(r["config"], int(r["steps"])) for r in rows] == [
        ("smoother N_w=1", 100), ("smoother N_w=1", 100000), ("batch", 100), ("batch", 100000)]
    for r in rows:
        assert int(r["exit"]) == 0
        # Every step written, step 0 included; a process's peak is a few MiB at least.
        assert int(r["rows"]) == int(r["steps"])
        assert float(r["peak_rss_mib"]) > 1.0
        assert float(r["reported_mib"]) > 1.0
        assert float(r["cpu_s"]) >= 0.0 and float(r["mean_iterations"]) >= 1.0
    batch = {int(r["steps"]): float(r["peak_rss_mib"]) for r in rows if r["config"] == "batch"}
    # The batch asked of square steps is taken one step at a time and streams its rows
    # (holding them would add 96 bytes a four-bar step, 9.6 MB for 1e5 steps).
    assert batch[100000] < batch[100] + 2.0
    smoother = {int(r["steps"]): float(r["peak_rss_mib"]) for r in rows
                if r["config"] == "smoother N_w=1"}
    assert smoother[100000] < smoother[100] + 2.0
    page = (tmp_path / "horizons.md").read_text()
    assert "| smoother N_w=1 | 100,000 |" in page and "## Verdicts" in page
    assert (tmp_path / "horizons.png").stat().st_size > 1000
