"""The committed references (references/): current with their scenes, as accurate as
the reference issue demands, and agreeing with their cross-checks."""
import json
import pathlib

import numpy as np
import pytest

from harness import reference as refs
from harness import trajectory as tj
from harness.tests.test_ida import fourbar_reference

ROOT = pathlib.Path(__file__).resolve().parents[2]


def provenance(name):
    return json.loads((ROOT / "references" / name / "provenance.json").read_text())


@pytest.mark.parametrize("name", list(refs.SUITE))
def test_reference_is_current_and_finite(name):
    prov = provenance(name)
    assert tj.is_current(prov, ROOT / "scenes" / f"{name}.yaml"), \
        f"references/{name} is stale: its scene changed (make reference)"
    traj = tj.read(ROOT / "references" / name / "reference.csv.gz")
    assert np.all(np.isfinite(traj.q))
    np.testing.assert_allclose(traj.t[1] - traj.t[0], refs.SAMPLE_DT)
    np.testing.assert_allclose(traj.t[-1], refs.SUITE[name][0])
    assert prov["max_abs_phi"] < 1e-9


def test_fourbar_reference_matches_the_crank_angle_ode():
    """≤ 1e-9 m max error against the minimal-coordinate ODE over the whole 5 s."""
    traj = tj.read(ROOT / "references" / "fourbar" / "reference.csv.gz")
    exact = fourbar_reference(traj.t)
    assert np.max(np.abs(traj.q - exact)) <= 1e-9


def cross_check(name, generator):
    return next(c for c in provenance(name)["cross_checks"] if c["generator"] == generator)


def test_cross_checks_agree():
    # IDA GGL against exudyn (h = 1e-5, tight Newton): ≤ 1e-7 m; against Pinocchio's
    # closed-loop constraint dynamics: ≤ 1e-9 m; the double pendulum likewise.
    assert cross_check("fourbar", "exudyn")["max_m"] <= 1e-7
    assert cross_check("fourbar", "pinocchio")["max_m"] <= 1e-9
    assert cross_check("double-pendulum", "pinocchio")["max_m"] <= 1e-9


def test_suite_stays_small():
    size = sum(f.stat().st_size for f in (ROOT / "references").rglob("*") if f.is_file())
    assert size < 20e6


PINNED = dict(line.split("==") for line in
              (ROOT / "harness" / "requirements.txt").read_text().split()
              if "==" in line and not line.startswith("#"))


@pytest.mark.parametrize("name", list(refs.SUITE))
def test_reference_was_written_by_todays_generators(name):
    """A reference's recorded request (generator, settings, the hash of the generator's
    code) and package versions are those `make reference` uses today: a generator whose
    code or settings changed without `make reference` fails here."""
    job = refs.suite_job(name)
    prov = provenance(name)
    assert prov.get("request") == refs.request(job.primary), \
        f"references/{name} was written by another version of {job.primary[0]} or other " \
        "settings (make reference)"
    assert [c.get("request") for c in prov["cross_checks"]] == \
        [refs.request(c, job.quick_checks) for c in job.checks]
    recorded = [prov["versions"]] + [c.get("versions", {}) for c in prov["cross_checks"]]
    for versions in recorded:
        for package, version in versions.items():
            if package in PINNED:
                assert version == PINNED[package], \
                    f"references/{name}: written with {package} {version}, pinned {PINNED[package]}"
