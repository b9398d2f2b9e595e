"""The tutorial's numbers are what its commands print. Each number docs/tutorial.md
quotes is read from the page and compared with a fresh run at the precision it is
quoted to, so that a change in the solver, the scene or the page shows here. (Wall
times are quoted as approximate and not checked.)"""

import json
import pathlib
import re
import subprocess
import sys

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[2]
MBFG = ROOT / "target/release/mbfg"
PAGE = (ROOT / "docs/tutorial.md").read_text()
SCENE = "examples/tutorial/swinging-bar.yaml"


def quoted(pattern: str) -> str:
    """The first group of `pattern` in the tutorial (the page must still say it)."""
    m = re.search(pattern, PAGE)
    assert m, f"docs/tutorial.md no longer says /{pattern}/"
    return m.group(1)


def significant(text: str) -> int:
    mantissa = text.lstrip("+-").split("e")[0].replace(".", "").lstrip("0")
    return max(len(mantissa), 1)


def agrees(text: str, value: float) -> bool:
    """`value` rounded to the significant digits of `text` is `text`'s number."""
    digits = significant(text)
    return float(f"{value:.{digits - 1}e}") == float(text)


def test_agreement_is_at_the_quoted_precision():
    assert agrees("9.23e-6", 9.2275e-6) and not agrees("9.23e-6", 9.2351e-6)
    assert agrees("5.618150", 5.6181501) and not agrees("5.618150", 5.6181549)


def run(*argv, cwd=ROOT):
    r = subprocess.run([str(MBFG), *argv], cwd=cwd, capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    return r


def test_check_prints_what_the_page_quotes():
    out = run("check", SCENE).stdout
    n = quoted(r"n = (\d+) coordinates \(")
    coords = quoted(r"n = \d+ coordinates \(([^)]*)\)")
    m = quoted(r"m = (\d+) constraints")
    dof = quoted(r"(\d+)\s+degree of freedom")
    assert f"n = {n} coordinates: {coords}" in out
    assert f"m = {m} constraints" in out
    assert f"degrees of freedom: {dof}" in out
    energy = float(re.search(r"potential energy (\S+) J", out).group(1))
    assert agrees(quoted(r"potential energy (\S+) J"), energy)
    accel = float(re.search(r"initial max \|q̈\| = (\S+)", out).group(1))
    assert agrees(quoted(r"largest initial acceleration (\S+)\)"), accel)


def test_simulate_prints_what_the_page_quotes(tmp_path):
    argv = ["simulate", SCENE, "--dt", "0.001", "--t-end", "5"]
    r = run(*argv, "--out", str(tmp_path / "swing.csv"))
    summary = r.stdout
    rows = (tmp_path / "swing.csv").read_text().splitlines()
    assert len(rows) - 1 == int(quoted(r"writes (\d+) rows"))
    assert quoted(r"`(\d+ steps \(dt = [^`]*\))`") in summary
    m = re.search(r"iterations per solve: mean (\S+), max (\d+) \(factorizations: mean (\S+)\)",
                  summary)
    assert agrees(quoted(r"([\d.]+) iterations per step"), float(m.group(1)))
    assert m.group(2) == quoted(r"at most (\d+),")
    assert agrees(quoted(r"([\d.]+) new ones a step"), float(m.group(3)))
    worst = float(re.search(r"worst \|Φ\| (\S+),", summary).group(1))
    assert agrees(quoted(r"worst \|Φ\| (\S+),"), worst)
    # "`--window 10` and `--batch` write the same rows here, to the bit".
    assert "write the same rows here, to the bit" in PAGE
    for extra in (["--window", "10"], ["--batch"]):
        out = tmp_path / f"swing{len(extra)}.csv"
        run(*argv, *extra, "--out", str(out))
        assert out.read_bytes() == (tmp_path / "swing.csv").read_bytes(), extra


def compare(tmp_path, tools, dt=None):
    out = tmp_path / f"compare-{tools}-{dt}"
    argv = [sys.executable, "-m", "harness.compare", SCENE, "--tools", tools, "--out", str(out)]
    if dt is not None:
        argv += ["--dt", str(dt)]
    r = subprocess.run(argv, cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    result = json.loads((out / "compare.json").read_text())
    return result, {t["tool"]: t for t in result["tools"]}


def table(header: str) -> dict[str, list[str]]:
    """The rows of the markdown table under the line starting with `header`, by their
    first cell."""
    start = PAGE.index(header)
    rows = {}
    for line in PAGE[start:].splitlines()[1:]:
        if not line.startswith("|"):
            if rows:
                break
            continue
        cells = [c.strip() for c in line.strip("|").split("|")]
        rows[cells[0]] = cells[1:]
    return rows


def metres(cell: str) -> str:
    assert cell.endswith(" m"), cell
    return cell[:-2]


def test_the_comparison_table_is_what_compare_prints(tmp_path):
    result, tools = compare(tmp_path, "mbfg,ida,exudyn,pinocchio")
    assert result["t_end"] == float(quoted(r"on the same file over (\d+) s"))
    rows = table("| tool | RMSE of the points against IDA")
    labels = {"mbfg, DC, dt = 1 ms": "mbfg", "exudyn, h = 0.1 ms": "exudyn",
              "Pinocchio (RK4), h = 0.2 ms": "pinocchio"}
    assert set(rows) == set(labels) | {"---"}
    for label, tool in labels.items():
        assert tools[tool]["status"] == "ok"
        cell = rows[label][0]
        if cell.startswith("below "):
            # At the reference's own precision: its digits are the machine's rounding.
            assert tools[tool]["rmse_m"] < float(metres(cell.removeprefix("below "))), label
        else:
            assert agrees(metres(cell), tools[tool]["rmse_m"]), (label, tools[tool])


@pytest.mark.parametrize("label, dt", [("1 ms", 1e-3), ("0.5 ms", 5e-4), ("0.25 ms", 2.5e-4)])
def test_the_time_step_table_is_what_compare_prints(tmp_path, label, dt):
    _, tools = compare(tmp_path, "mbfg,mbfg-ic,ida", dt)
    dc, ic = table("| dt | DC | IC |")[label]
    assert agrees(metres(dc), tools["mbfg"]["rmse_m"]), (label, tools["mbfg"])
    assert agrees(metres(ic), tools["mbfg-ic"]["rmse_m"]), (label, tools["mbfg-ic"])
    if label == "1 ms":
        closer = tools["mbfg"]["rmse_m"] / tools["mbfg-ic"]["rmse_m"] - 1
        assert round(100 * closer) == int(quoted(r"here IC is (\d+) %\s+closer"))
