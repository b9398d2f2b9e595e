"""The wheel: `maturin build` makes one (`make python` does, from the build it
installs into .venv), it installs into a fresh virtual environment and works from outside the
checkout: the module models and runs a scene given as text, the harness is a package
(`python -m harness.compare`), `mbfg.animate` without matplotlib says which extra to
install; with the harness's packages (this .venv's) it animates and compares. Its
metadata carries the licence and the `plot` and `harness` extras."""

import os
import pathlib
import subprocess
import sys
import zipfile

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[2]
MBFG = ROOT / "target/release/mbfg"
SCENE = """name: pendulum
points:
  - {name: O, x: 0, y: 0, fixed: true}
  - {name: T, x: 1, y: 0}
bodies:
  - {name: bar, points: [O, T], mass: 1}
coordinates:
  - {name: theta, type: angle, points: [O, T]}
independent: [theta]
effects:
  - {type: gravity, vector: [0, -9.81]}
"""


@pytest.fixture(scope="module")
def wheel(tmp_path_factory) -> pathlib.Path:
    """The wheel `make python` built beside the module it installed (newer than that
    module), or a new one: a build of its own would compile mbfg again after `cargo
    build` (the two builds' features differ)."""
    native = sorted((ROOT / "python/mbfg").glob("_native*.so"))
    made = sorted((ROOT / "target/wheels").glob("mbfg-*.whl"))
    if native and len(made) == 1 and made[0].stat().st_mtime >= native[0].stat().st_mtime:
        return made[0]
    out = tmp_path_factory.mktemp("wheel")
    maturin = pathlib.Path(sys.executable).parent / "maturin"
    env = dict(os.environ, VIRTUAL_ENV=str(pathlib.Path(sys.executable).parent.parent))
    r = subprocess.run([str(maturin), "build", "--release", "--out", str(out)], cwd=ROOT,
                       capture_output=True, text=True, env=env, timeout=900)
    assert r.returncode == 0, r.stderr[-2000:]
    (whl,) = out.glob("mbfg-*.whl")
    return whl


def test_the_wheel_holds_the_module_the_harness_and_its_metadata(wheel):
    with zipfile.ZipFile(wheel) as z:
        names = z.namelist()
        meta = z.read(next(n for n in names if n.endswith(".dist-info/METADATA"))).decode()
    assert any(n.startswith("mbfg/_native") for n in names)
    assert {"harness/__init__.py", "harness/compare.py", "harness/ida.py"} <= set(names)
    assert not any(n.startswith("harness/tests") for n in names)
    assert "License: MIT OR Apache-2.0" in meta
    assert "Provides-Extra: plot" in meta and "Provides-Extra: harness" in meta
    assert "Requires-Dist: matplotlib>=3.8 ; extra == 'plot'" in meta


def run(python, code, cwd, env=None):
    r = subprocess.run([str(python), "-c", code], cwd=cwd, capture_output=True, text=True,
                       env=env, timeout=300)
    return r


def test_a_fresh_venv_imports_and_runs_it_outside_the_checkout(wheel, tmp_path):
    venv = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True, timeout=300)
    python = venv / "bin/python"
    r = subprocess.run([str(python), "-m", "pip", "install", "--quiet", str(wheel)],
                       capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-2000:]
    away = tmp_path / "elsewhere"
    away.mkdir()
    code = f"""
import mbfg, harness, harness.trajectory
assert not mbfg.__file__.startswith({str(ROOT)!r}), mbfg.__file__
run = mbfg.simulate({SCENE!r}, dt=1e-3, t_end=0.5)
print(run.data.shape, mbfg.load({SCENE!r}).dof)
try:
    mbfg.animate(run, out="x.gif")
except ModuleNotFoundError as e:
    print(e)
"""
    r = run(python, code, away)
    assert r.returncode == 0, r.stderr[-2000:]
    lines = r.stdout.splitlines()
    assert lines[0] == "(501, 10) 1"
    # Without the `plot` extra (matplotlib), animate names the extra.
    assert 'pip install "mbfg[plot]"' in lines[1]
    # `mbfg` is on the venv's PATH: without a compiled command line it says how to build
    # one; with one (MBFG, or on the PATH) it runs it.
    bare = {"PATH": f"{venv / 'bin'}:/usr/bin:/bin"}
    r = subprocess.run([str(venv / "bin/mbfg"), "--version"], cwd=away, env=bare,
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 2 and "make install" in r.stderr, (r.returncode, r.stderr)
    if MBFG.exists():
        r = subprocess.run([str(venv / "bin/mbfg"), "--version"], cwd=away,
                           env=dict(bare, MBFG=str(MBFG)), capture_output=True, text=True,
                           timeout=60)
        assert r.returncode == 0 and r.stdout.startswith("mbfg "), (r.returncode, r.stderr)


def test_with_the_extras_it_animates_and_compares_outside_the_checkout(wheel, tmp_path):
    """`pip install "mbfg[plot,harness]"` into a fresh venv (the extras at the versions
    harness/requirements.txt pins, which pip's cache holds after `make python`): the
    module animates and the harness compares, from a folder outside the checkout."""
    venv = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True, timeout=300)
    python = venv / "bin/python"
    r = subprocess.run([str(python), "-m", "pip", "install", "--quiet", "--constraint",
                        str(ROOT / "harness/requirements.txt"), f"{wheel}[plot,harness]"],
                       capture_output=True, text=True, timeout=900)
    assert r.returncode == 0, r.stderr[-2000:]
    away = tmp_path / "elsewhere"
    away.mkdir()
    (away / "pendulum.yaml").write_text(SCENE)
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "VIRTUAL_ENV")}
    code = """
import mbfg, harness
assert mbfg.__file__.startswith(%r) and harness.__file__.startswith(%r)
run = mbfg.simulate("pendulum.yaml", dt=1e-2, t_end=0.3)
print(mbfg.animate(run, out="pendulum.gif"))
""" % (str(venv), str(venv))
    r = run(python, code, away, env)
    assert r.returncode == 0, r.stderr[-2000:]
    assert (away / "pendulum.gif").stat().st_size > 0
    r = subprocess.run([str(python), "-m", "harness.compare", "pendulum.yaml", "--tools",
                        "mbfg,ida,exudyn,pinocchio", "--t-end", "0.2"], cwd=away, env=env, capture_output=True,
                       text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    assert (away / "compare-pendulum" / "compare.md").exists()
    table = (away / "compare-pendulum" / "compare.md").read_text()
    for tool in ("mbfg", "ida", "exudyn", "pinocchio"):
        assert f"| {tool} | ok |" in table, table


@pytest.mark.skipif(not MBFG.exists(), reason="needs the CLI (make build)")
def test_mbfg_animate_finds_the_checkout_venv_from_elsewhere(tmp_path):
    scene = tmp_path / "pendulum.yaml"
    scene.write_text(SCENE)
    csv = tmp_path / "run.csv"
    env = {k: v for k, v in os.environ.items() if k not in ("MBFG_PYTHON", "VIRTUAL_ENV")}
    env["PATH"] = "/usr/bin:/bin"  # no python3 with mbfg on it
    for argv in (["simulate", str(scene), "--dt", "0.01", "--t-end", "0.2", "--out", str(csv)],
                 ["animate", str(csv), "--scene", str(scene), "--out", str(tmp_path / "a.gif")]):
        r = subprocess.run([str(MBFG), *argv], cwd=tmp_path, env=env, capture_output=True,
                           text=True, timeout=300)
        assert r.returncode == 0, r.stderr
    assert (tmp_path / "a.gif").stat().st_size > 0
