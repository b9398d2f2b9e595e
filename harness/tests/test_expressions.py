"""The harness's own reading of expressions (harness/expressions.py) against mbfg's
evaluator: on the fuzz corpus of expressions, and on every load of the repository's
scenes at random states."""
from __future__ import annotations

import json
import math
import pathlib
import re

import numpy as np
import pytest
import yaml

import mbfg
from harness import expressions as ex
from harness.scene_file import SceneFile, load_yaml

ROOT = pathlib.Path(__file__).resolve().parents[2]
CORPUS = sorted((ROOT / "fuzz" / "corpus" / "expr").iterdir())
# The fuzz target's names: t, L, mass, zero, and any name whose length is a multiple of 3.
FIXED = {"t": 0.5, "L": 2.0, "mass": 3.0, "zero": 0.0}


def _scene_with_torque(tmp_path, text: str, params: dict) -> pathlib.Path:
    body = {"name": "probe", "parameters": params,
            "points": [{"name": "A", "x": 0, "y": 0, "fixed": True}, {"name": "B", "x": 1, "y": 0}],
            "bodies": [{"name": "bar", "points": ["A", "B"], "mass": 1}],
            "coordinates": [{"name": "theta", "type": "angle", "points": ["A", "B"]}],
            "effects": [{"name": "probe", "type": "torque", "coordinate": "theta", "value": text}]}
    path = tmp_path / "probe.yaml"
    path.write_text(json.dumps(body))       # JSON is YAML
    return path


def _names(text: str) -> set[str]:
    return set(re.findall(r"[A-Za-z_][A-Za-z0-9_]*", text))


@pytest.mark.parametrize("path", CORPUS, ids=lambda p: p.name[:10])
def test_the_fuzz_corpus_reads_as_mbfg_reads_it(path, tmp_path):
    raw = path.read_bytes()
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError:
        pytest.skip("not UTF-8: no scene can hold it")
    if any(ord(c) < 32 and c not in "\t\n\r" for c in text):
        pytest.skip("control characters: YAML cannot hold them")
    if not text.strip():
        pytest.skip("empty: a scene reads it as no value")
    params = {"L": 2.0, "mass": 3.0, "zero": 0.0}
    for n in _names(text):
        if len(n) % 3 == 0 and n not in ex.FUNCTIONS and n not in ex.STATE_ACCESSORS \
                and n not in ("t", "pi", "theta"):
            params[n] = float(len(n))
    scene = _scene_with_torque(tmp_path, text, params)
    try:
        model = mbfg.load(str(scene))
        theirs = [model.effect_value(0, t) for t in (0.0, 0.5)]
    except (mbfg.SceneError, ValueError) as e:
        theirs = e
    try:
        e = ex.parse(text)
        env = dict(params)
        mine = [e({**env, "t": t}) for t in (0.0, 0.5)]
    except ex.ExpressionError as err:
        mine = err
    if isinstance(theirs, Exception):
        assert isinstance(mine, Exception), f"mbfg refuses {text[:80]!r} ({theirs}), the harness reads {mine}"
    else:
        assert not isinstance(mine, Exception), f"mbfg reads {text[:80]!r} as {theirs}, the harness refuses: {mine}"
        np.testing.assert_allclose(mine, theirs, rtol=1e-13, atol=1e-300)


def test_the_grammar_by_example():
    cases = {"-2^2": -4.0, "2^3^2": 512.0, "2^-1": 0.5, "1e-3": 1e-3, ".5": 0.5, "1.5E+2": 150.0,
             "atan2(1, -1)": 3 * math.pi / 4, "sign(-0.3) + sign(0)": -1.0,
             "min(2, 3) * max(2, 3)": 6.0, "log(exp(2)) + ln(1)": 2.0, "pow(2, 10)": 1024.0,
             "10 - 4 - 3": 3.0, "12 / 3 / 2": 2.0, "pi": math.pi}
    for text, want in cases.items():
        assert ex.parse(text)({}) == pytest.approx(want, rel=1e-15), text
    for bad, why in {"2*(3": "missing ')'", "foo(1)": "unknown function", "min(1)": "argument",
                     "sqrt(-1)": "non-finite", "1/0": "non-finite", "q + 1": "undefined"}.items():
        with pytest.raises(ex.ExpressionError, match=re.escape(why)):
            ex.parse(bad)({})


def _scenes_with_loads():
    out = []
    for path in sorted(ROOT.glob("**/*.yaml")):
        rel = path.relative_to(ROOT)
        if rel.parts[0] not in ("scenes", "examples", "harness") or "trajectories" in rel.parts:
            continue
        try:
            doc = load_yaml(path)
        except Exception:
            continue
        if any(isinstance(e, dict) and e.get("type") in ("torque", "force")
               for e in doc.get("effects") or []):
            out.append(path)
    return out


@pytest.mark.parametrize("path", _scenes_with_loads(), ids=lambda p: str(p.relative_to(ROOT)))
def test_every_load_of_the_scenes_reads_as_mbfg_reads_it(path, tmp_path):
    """Each torque or force of the scene alone, as generalized forces at random states:
    mbfg's Q against the harness's value placed on the coordinate or point."""
    doc = load_yaml(path)
    if "mechanism" in doc:
        doc["mechanism"] = str((path.parent / doc["mechanism"]).resolve())
    scene = SceneFile(path)
    rng = np.random.default_rng(7)
    checked = 0
    for k, e in enumerate(doc["effects"]):
        if e.get("type") not in ("torque", "force"):
            continue
        alone = dict(doc, effects=[e])
        one = tmp_path / f"{k}.yaml"
        one.write_text(yaml.safe_dump(alone))
        model = mbfg.load(str(one))
        names = list(model.names)
        mine_e = scene.effects[k]
        for _ in range(5):
            q = np.asarray(model.initial_q) + 0.05 * rng.standard_normal(model.n)
            dq = rng.standard_normal(model.n)
            t = float(rng.uniform(0, 3))
            Q = np.asarray(model.generalized_forces(q, dq, t))
            env = state_env(scene, names, q, dq, t)
            vals = [v(env) for v in mine_e.spec["value"]]
            if e["type"] == "torque":
                k_c = names.index(mine_e.spec["coordinate"])
                assert vals[0] == pytest.approx(Q[k_c], rel=1e-12, abs=1e-12)
            else:
                p = mine_e.spec["point"]
                i = names.index(f"{p}.x")
                np.testing.assert_allclose(vals, Q[i:i + 2], rtol=1e-12, atol=1e-12)
            checked += 1
    assert checked


def state_env(scene: SceneFile, names, q, dq, t) -> dict:
    """The expression variables at an arbitrary (q, q̇), read off the coordinates."""
    env = {"t": t}
    r, v = scene.positions(q), scene.positions(dq)
    for n, p in scene.points.items():
        if p.fixed:
            v[n] = np.zeros(2)
        env[f"x({n})"], env[f"y({n})"] = r[n]
        env[f"vx({n})"], env[f"vy({n})"] = v[n]
    for c in scene.coordinates:
        k = names.index(c["name"])
        env[c["name"]], env[f"rate({c['name']})"] = q[k], dq[k]
    for b in scene.bodies:
        d, dd = r[b.points[1]] - r[b.points[0]], v[b.points[1]] - v[b.points[0]]
        env[f"angle({b.name})"] = math.atan2(d[1], d[0])
        env[f"omega({b.name})"] = (d[0] * dd[1] - d[1] * dd[0]) / (d @ d)
    return env
