"""The harness as a tool for the user's own scenes: --help everywhere, compare and
reference on a scene outside the repository, the generator registry, provenance."""
import csv
import json
import os
import pathlib
import shutil
import subprocess
import sys
import time

import numpy as np
import pytest

import mbfg
from harness import compare, exudyn_ref, generators, reference, timing
from harness import trajectory as tj

ROOT = pathlib.Path(__file__).resolve().parents[2]
ENTRY_POINTS = ["reference", "report", "timing", "robustness", "hard_cases", "compare",
                "crosscheck", "coverage", "ida",
                "exudyn_ref", "pinocchio_ref", "prescribed_motions", "regression", "trajectory",
                "generators", "scaling", "scale_scenes", "inverse_measured"]
# What a runaway entry point would write into the repository.
WATCHED = ["reports", "references", "tests/data", "scenes/trajectories", "scenes/scale"]


def snapshot() -> dict:
    return {str(p): (p.stat().st_mtime_ns, p.stat().st_size)
            for d in WATCHED for p in (ROOT / d).rglob("*") if p.is_file()}


@pytest.mark.parametrize("module", ENTRY_POINTS)
def test_help_exits_at_once_and_writes_nothing(module, tmp_path):
    before = snapshot()
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    start = time.perf_counter()
    p = subprocess.run([sys.executable, "-m", f"harness.{module}", "--help"], cwd=tmp_path,
                       env=env, capture_output=True, text=True, timeout=60)
    wall = time.perf_counter() - start
    assert p.returncode == 0, p.stderr
    assert p.stdout.startswith(f"usage: python -m harness.{module}"), p.stdout[:200]
    assert wall < 10, f"--help took {wall:.1f} s"
    assert list(tmp_path.iterdir()) == []
    assert snapshot() == before


def users_scene(tmp_path, name="pendulum") -> pathlib.Path:
    """A copy of a suite scene in a folder of the user's, outside the repository."""
    folder = tmp_path / "my-project"
    folder.mkdir()
    return pathlib.Path(shutil.copy(ROOT / "scenes" / f"{name}.yaml", folder / f"my-{name}.yaml"))


def read_rows(path) -> dict:
    with open(path) as f:
        return {r["tool"]: r for r in csv.DictReader(f)}


def test_compare_on_a_users_scene(tmp_path):
    scene = users_scene(tmp_path)
    out = tmp_path / "out"
    assert compare.main([str(scene), "--tools", "mbfg,ida,exudyn", "--t-end", "1",
                         "--out", str(out)]) == 0
    for name in ("compare.md", "compare.csv", "compare.json", "trajectories/mbfg.csv.gz",
                 "trajectories/exudyn.json"):
        assert (out / name).is_file(), name
    assert (out / "compare.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    rows = read_rows(out / "compare.csv")
    assert rows["ida"]["status"] == "ok" and rows["ida"]["note"] == "the reference"
    # mbfg at dt = 1 ms: trapezoidal, ~1e-5 m; exudyn at h = 1e-4: ~1e-7 m.
    assert 0 < float(rows["mbfg"]["rmse_m"]) < 1e-4
    assert 0 < float(rows["exudyn"]["rmse_m"]) < 1e-5
    for r in rows.values():
        assert np.isfinite(float(r["max_abs_phi"])) and float(r["wall_time_s"]) > 0
    md = (out / "compare.md").read_text()
    assert "| mbfg | ok |" in md and "| exudyn | ok |" in md
    for record in [out / "compare.json", *(out / "trajectories").glob("*.json")]:
        text = record.read_text()
        assert str(ROOT) not in text, record
        assert json.loads(text)["scene"] == str(scene)


def test_compare_reports_refusals_and_failures_in_the_table(tmp_path):
    scene = users_scene(tmp_path, "fourbar")     # declares no independent coordinates
    out = tmp_path / "out"
    assert compare.main([str(scene), "--tools", "mbfg,mbfg-ic", "--t-end", "0.2",
                         "--out", str(out), "--set", "ida.max_num_steps=3"]) == 0
    rows = read_rows(out / "compare.csv")
    assert rows["mbfg-ic"]["status"] == "refused" and "independent" in rows["mbfg-ic"]["note"]
    # The reference tool runs even when not asked for; it fails here (3 steps), and the
    # remaining reference tools are not in the run: no errors, said so.
    assert rows["ida"]["status"] == "failed" and "max_num_steps" in rows["ida"]["note"]
    assert rows["mbfg"]["status"] == "ok" and rows["mbfg"]["rmse_m"] == ""
    assert "no reference" in (out / "compare.md").read_text()


def test_reference_for_a_scene_file_and_its_check(tmp_path, capsys):
    scene = users_scene(tmp_path)
    args = [str(scene), "--t-end", "0.5", "--checks", "pinocchio", "--quick"]
    assert reference.main(args) == 0
    folder = scene.with_name("my-pendulum.reference")
    prov = json.loads((folder / "provenance.json").read_text())
    assert prov["generator"] == "ida" and prov["settings"]["rtol"] == 1e-14
    assert prov["cross_checks"][0]["max_m"] < 1e-9
    assert prov["scene"] == str(scene) and list(prov["files"]) == [str(scene)]
    assert str(ROOT) not in (folder / "provenance.json").read_text()
    assert tj.read(folder / "reference.csv.gz").t[-1] == 0.5
    assert reference.main(["--check", *args]) == 0
    assert "1 of 1 references reproduced" in capsys.readouterr().out


def test_reference_refuses_unknown_scenes_and_suite_settings(tmp_path):
    with pytest.raises(SystemExit):
        reference.main([str(tmp_path / "nothing.yaml")])
    with pytest.raises(SystemExit):        # would overwrite references/fourbar
        reference.main(["fourbar", "--t-end", "1"])


def test_provenance_is_relative_and_hashes_the_mbse_file(tmp_path):
    scene = ROOT / "scenes" / "pick-and-place-mbse.yaml"
    record = tj.provenance("test", scene, "-", {}, 0.0)
    assert record["scene"] == "scenes/pick-and-place-mbse.yaml"
    assert record["files"] == {
        "scenes/pick-and-place-mbse.yaml": tj.file_hash(scene),
        "scenes/mbse/pick-and-place.yaml": tj.file_hash(ROOT / "scenes/mbse/pick-and-place.yaml")}
    assert str(ROOT) not in json.dumps(record)
    if record["git"]:
        assert len(record["git"]["commit"]) == 40
    # The scene hash follows the MBSE file.
    copy = tmp_path / "pp.yaml"
    shutil.copy(scene, copy)
    shutil.copytree(ROOT / "scenes" / "mbse", tmp_path / "mbse")
    before = tj.scene_hash(copy)
    assert before == tj.scene_hash(scene)
    with open(tmp_path / "mbse" / "pick-and-place.yaml", "a") as f:
        f.write("# changed\n")
    assert tj.scene_hash(copy) != before
    # A scene without `mechanism:` keeps the plain file hash (the committed references').
    plain = ROOT / "scenes" / "fourbar.yaml"
    assert tj.scene_hash(plain) == tj.file_hash(plain)


def test_registry_matches_the_committed_reference_settings():
    for name, (_, primary, checks) in reference.SUITE.items():
        prov = json.loads((ROOT / "references" / name / "provenance.json").read_text())
        gen = generators.get(primary[0])
        expected = {**gen.reference, **primary[1]}
        assert prov["formulation"] == expected["formulation"]
        assert prov["settings"]["rtol"] == expected["rtol"], name
        for (check, _), done in zip(checks, prov["cross_checks"]):
            assert done["generator"] == check
            if "settings" in done:
                assert done["settings"]["h"] == generators.get(check).reference["h"], name


def test_registry_drives_the_timing_sweeps():
    tools = {tool for tool, *_ in timing.configurations("fourbar", "fourbar-theta", 5.0)}
    assert tools == {"mbfg", "exudyn", "IDA", "Pinocchio"}


def test_fit_step_divides_the_sample_step():
    assert generators.fit_step(1e-5, 1e-3) == 1e-5
    assert generators.fit_step(1e-4, 3e-4) == pytest.approx(1e-4)
    assert generators.fit_step(1e-3, 2e-4) == 2e-4
    assert generators.fit_step(3e-4, 1e-3) == pytest.approx(2.5e-4)


def test_exudyn_failure_is_one_line_and_nonzero(tmp_path, capfd):
    rc = exudyn_ref.main([str(ROOT / "scenes" / "hard" / "parallelogram.yaml"), "--t-end", "0.6",
                          "--dt", "1e-3", "--out", str(tmp_path / "p.csv")])
    out, err = capfd.readouterr()
    assert rc == 1
    assert err.count("\n") == 1 and err.startswith("exudyn_ref: exudyn: the generalized_alpha "
                                                   "solve of") and "failed at t = 0.52" in err
    assert out == "" and "Traceback" not in err


def test_compare_shows_the_step_mbfg_integrated_at_its_warnings_and_a_turning_crank(tmp_path):
    # At dt = 0.05 s the fast crank turns 1.5 rad a step: mbfg refines to dt/6 from the
    # first step, and says the energy drifted; the table says both.
    scene = ROOT / "scenes" / "driven" / "fast-crank.yaml"
    out = tmp_path / "out"
    p = subprocess.run([sys.executable, "-m", "harness.compare", str(scene), "--tools", "mbfg",
                        "--t-end", "1", "--dt", "0.05", "--out", str(out)], cwd=ROOT,
                       capture_output=True, text=True, timeout=120)
    assert p.returncode == 0, p.stderr
    rows = read_rows(out / "compare.csv")
    assert rows["mbfg"]["step"].startswith("0.00833 (refined ×6 from t = 0.05 s; asked 0.05)")
    assert rows["ida"]["step"] == "adaptive"
    md = (out / "compare.md").read_text()
    assert "| mbfg | ok | 0.00833 (refined ×6" in md
    assert p.stdout.startswith("# ") and md in p.stdout     # the table in one piece
    assert "wrote" not in p.stdout and "wrote" in p.stderr
    # The crank turns: its plot shows the speed, not an angle climbing to 20 rad.
    model = mbfg.load(scene)
    ida = tj.read(out / "trajectories/ida.csv.gz")
    label, (shown,) = compare.plot_series(model, "theta", ida)
    assert label == "rate(theta) (it turns)"
    assert np.array_equal(shown, ida.dq[:, model.names.index("theta")])
