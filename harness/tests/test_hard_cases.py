"""The hard-case suite in its fast form (make test); `make report` runs it in full.
Every run of a case must meet the case's criteria (harness/hard_cases.py)."""
import pytest

from harness import hard_cases as hc

# Cases that do not pass yet, with the reason; strict, so a fix shows up as XPASS and
# the mark must go.
KNOWN: dict[str, str] = {}

CASES = {
    "parallelogram-dc-1ms": lambda: hc.parallelogram([1e-3], ["dc"]),
    "parallelogram-ic-1ms-ill-posed": lambda: hc.parallelogram([1e-3], ["ic"]),
    "slider-crank-dead-centres": lambda: hc.dead_centres(["dc", "ic"]),
    "fourbar-60s": lambda: hc.long_run(60.0, ["dc", "ic"]),
    "stiff-spring": hc.stiff_spring,
    "large-steps": lambda: hc.large_steps(["dc", "ic"]),
    "redundant-constraints": hc.redundant,
    "ic-branch-ambiguity": hc.branch,
}


@pytest.mark.parametrize("case", [
    pytest.param(name, marks=pytest.mark.xfail(reason=KNOWN[name], strict=True)) if name in KNOWN
    else name for name in CASES])
def test_hard_case(case):
    outcomes = list(CASES[case]())
    assert outcomes
    failed = [f"{o.setting}: {o.figures}" for o in outcomes if not o.passed]
    assert not failed, "\n".join(failed)
