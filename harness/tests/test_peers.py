"""mbfg on everyday mechanisms, checked by exudyn and Pinocchio (harness/crosscheck.py),
and the check catching mistakes planted in what mbfg is given."""
from __future__ import annotations

import pathlib
import re

import pytest

from harness import crosscheck as cc

ROOT = pathlib.Path(__file__).resolve().parents[2]
EVERYDAY = ROOT / "examples" / "everyday"
# Short horizons, Pinocchio at a coarser RK4 step (its error stays below 1e-9 m there):
# seconds per scene.
FAST = {"pinocchio": {"h": 5e-4}}


@pytest.mark.parametrize("name", ["wiper", "stephenson-six-bar", "crank-shaper", "cart-pole",
                                  "engine", "arm-pd"])
def test_everyday_mechanisms_are_taken_by_both_peers_and_agree_with_mbfg(name):
    checks = cc.check(EVERYDAY / f"{name}.yaml", t_end=0.3, dt=1e-3, settings=FAST)
    assert [c.tool for c in checks] == ["exudyn", "pinocchio"]
    for c in checks:
        assert c.status == "agrees", c.line()


def planted(tmp_path, scene: str, old: str, new: str) -> pathlib.Path:
    text = (EVERYDAY / scene).read_text()
    assert text.count(old) == 1, old
    out = tmp_path / scene
    out.write_text(text.replace(old, new))
    return out


MISTAKES = {
    "a force 1 % larger": ("engine.yaml", 'value: ["-p0*', 'value: ["-1.01*p0*'),
    "a guide turned by a milliradian": ("crank-shaper.yaml", "{name: G2, x: 2, y: yr,",
                                        "{name: G2, x: -2 + 4*cos(1e-3), y: yr + 4*sin(1e-3),"),
    "one sign flipped in a load expression": ("cart-pole.yaml", "- kw*rate(phi)", "+ kw*rate(phi)"),
}


@pytest.mark.parametrize("mistake", list(MISTAKES))
def test_a_planted_mistake_is_caught_and_the_scene_named(tmp_path, mistake):
    scene, old, new = MISTAKES[mistake]
    wrong = planted(tmp_path, scene, old, new)
    with pytest.raises(cc.Disagreement, match=re.escape(scene)) as info:
        cc.require_agreement(EVERYDAY / scene, t_end=0.3, dt=5e-4, mbfg_scene=wrong,
                             settings=FAST)
    assert "disagrees with mbfg" in str(info.value)
    # The unaltered scene passes the same check.
    cc.require_agreement(EVERYDAY / scene, t_end=0.3, dt=5e-4, settings=FAST)


PEER_SCENES = sorted((pathlib.Path(__file__).resolve().parent / "scenes" / "peers").glob("*.yaml"))


@pytest.mark.parametrize("scene", PEER_SCENES, ids=lambda p: p.stem)
def test_scenes_like_a_users_are_taken_by_both_peers_and_agree_with_mbfg(scene):
    # A block of two points in a slot, torques and a motor on the angle of a distance
    # tie, a tie rod between two wipers, a free particle, a plank on a spring, a pin in
    # two slots, a bead on a rotating rod, a motor on a relative angle.
    checks = cc.check(scene, t_end=0.1, dt=1e-3, settings={**FAST, "exudyn": {"h": 2e-4}})
    assert [c.tool for c in checks] == ["exudyn", "pinocchio"]
    for c in checks:
        assert c.status == "agrees", c.line()
