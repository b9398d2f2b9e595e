"""Sweeps on Dask (harness/sweep.py, docs/sweeps.md): a small sweep of real runs on a
local cluster of 1 and of 2 workers, and in this process, gives the same results bit
for bit and in the cells' order; a worker that dies loses only its task, which runs
again; timing cells run one at a time; a runaway or crashing call in a worker's child
process is killed or reported."""
import functools
import os
import json
import time

import pytest

from harness import report
from harness import robustness as rb
from harness import sweep as sw


@pytest.fixture(scope="module")
def one():
    with sw.Sweep("local", workers=1) as s:
        yield s


@pytest.fixture(scope="module")
def two():
    with sw.Sweep("local", workers=2) as s:
        yield s


# Forward runs of the pendulum against its reference, and fast robustness cells (each
# in a child process of its worker).
FORWARD = [("pendulum", "pendulum", "pendulum", c, integrator, w, 0.5)
           for integrator in ("trapezoidal", "hermite-simpson") for w in (1, 3, "batch")
           for c in ("dc", "ic")]
CELLS = [rb.Cell("pendulum", c, w, dt) for c in ("dc", "ic") for w in (1, "batch")
         for dt in (1e-2, 2e-2)] + [rb.Cell("hard/parallelogram", "ic", 1, 1e-2)]


def small_sweep(sweep):
    rows = sweep.map(report.forward_run, FORWARD, "forward", progress=lambda _: None)
    outcomes = sweep.map(functools.partial(rb.isolated_cell, fast=True), CELLS, "robustness",
                         progress=lambda _: None)
    return rows, outcomes


def without_times(rows, outcomes) -> bytes:
    """The results serialized (floats as their exact shortest repr), less the measured
    wall times (which no two runs share)."""
    rows = [{k: v for k, v in r.items() if k != "wall_time_s"} for r in rows]
    outcomes = [{k: v for k, v in o.__dict__.items() if k != "wall_time"} for o in outcomes]
    return json.dumps([rows, outcomes]).encode()


def test_results_do_not_depend_on_the_number_of_workers(one, two):
    a, b = small_sweep(one), small_sweep(two)
    serial = small_sweep(sw.Sweep("serial"))
    rows, outcomes = b
    # In the cells' order, whatever order they finished in; real runs, not all alike.
    assert [(r["coords"], r["integrator"], r["window"]) for r in rows] == [
        (c, i, w) for _, _, _, c, i, w, _ in FORWARD]
    assert [o.cell for o in outcomes] == CELLS
    assert all(r["status"] == "converged" and r["rmse_m"] > 0 for r in rows)
    # Real runs, not copies: the general solver's windows (Hermite-Simpson in IC) each
    # give their own RMSE; trapezoidal steps, and Hermite-Simpson's in DC, are solved
    # one at a time as the square systems they are, so that every window has N_w = 1's
    # solution.
    by_pair = {}
    for r in rows:
        by_pair.setdefault((r["coords"], r["integrator"]), []).append(r["rmse_m"])
    for (c, i), values in by_pair.items():
        expected = len(values) if (c, i) == ("ic", "hermite-simpson") else 1
        assert len(set(values)) == expected, (c, i, values)
    assert len({values[0] for values in by_pair.values()}) == len(by_pair)
    assert outcomes[-1].status == "ill-posed" and outcomes[0].status == "converged"
    assert without_times(*a) == without_times(*b) == without_times(*serial)


def dies_once(cell):
    """Ends its worker process the first time it runs (the marker file says so)."""
    marker, log, x = cell
    with open(log, "a") as f:
        f.write("run\n")
    if x == 0 and not marker.exists():
        marker.write_text("died")
        time.sleep(1.0)     # the other cells' results reach the client meanwhile
        os._exit(1)
    return x * x


def test_a_worker_that_dies_loses_only_its_task(two, tmp_path):
    marker = tmp_path / "died"
    cells = [(marker, tmp_path / f"log-{x}", x) for x in range(6)]
    assert two.map(dies_once, cells, "squares", progress=lambda _: None) == [0, 1, 4, 9, 16, 25]
    assert marker.exists()
    runs = [len((tmp_path / f"log-{x}").read_text().splitlines()) for x in range(6)]
    assert runs == [2, 1, 1, 1, 1, 1]


def interval(x):
    start = time.time()
    time.sleep(0.2)
    return x, start, time.time()


def test_timing_cells_run_one_at_a_time_in_order(two):
    seen = []
    out = two.one_at_a_time(interval, list(range(4)), "timing", progress=seen.append)
    assert [x for x, _, _ in out] == [0, 1, 2, 3]
    for (_, _, end), (_, start, _) in zip(out, out[1:]):
        assert start >= end
    assert seen[-1].startswith("timing: 4 of 4 done")


def in_child(what):
    if what == "sleep":
        return sw.isolated(time.sleep, (60,), 0.5)
    if what == "crash":
        return sw.isolated(os._exit, (3,), 10.0)
    return sw.isolated(pow, (2, 10), 10.0)


def test_a_worker_runs_calls_in_child_processes_it_can_kill(two):
    # A Dask worker process is daemonic: multiprocessing would refuse it children.
    assert two.map(in_child, ["sleep", "crash", "fine"], progress=lambda _: None) == [
        ("timeout", None), ("died", 3), ("ok", 1024)]


def spin():
    while True:
        pass


def test_a_cpu_time_limit_stops_a_busy_run_and_spares_a_waiting_one():
    # Busy: stopped by its 1 s of CPU time, far inside its 60 s of wall time.
    began = time.perf_counter()
    assert sw.isolated(spin, (), 60.0, cpu_seconds=1.0) == ("timeout", None)
    assert time.perf_counter() - began < 30.0
    # Waiting (as a run does for a busy core) costs no CPU time: not stopped.
    assert sw.isolated(time.sleep, (2.0,), 60.0, cpu_seconds=1.0) == ("ok", None)


def test_progress_counts_cells():
    seen = []
    assert sw.Sweep("serial").map(abs, [-1, 2, -3], "abs", progress=seen.append) == [1, 2, 3]
    assert seen[-1].startswith("abs: 3 of 3 done")


def test_workers_with_other_files_are_refused():
    class Client:
        def __init__(self, prints):
            self.prints = prints

        def run(self, fn):
            return self.prints
    sw.check_workers(Client({"tcp://a:1": sw.fingerprint()}))
    with pytest.raises(RuntimeError, match="1 of 2 workers"):
        sw.check_workers(Client({"tcp://a:1": sw.fingerprint(), "tcp://b:1": "another"}))
    with pytest.raises(RuntimeError, match="no workers"):
        sw.check_workers(Client({}))


def test_scheduler_address_comes_from_the_environment(monkeypatch):
    monkeypatch.setenv(sw.ENV, "tcp://somewhere:8786")
    assert sw.Sweep().address == "tcp://somewhere:8786"
    assert sw.Sweep("local").address is None and not sw.Sweep("local").serial
    assert sw.Sweep("serial").serial
    monkeypatch.delenv(sw.ENV)
    assert sw.Sweep().address is None


def pid_then_sleep(path):
    path.write_text(str(os.getpid()))
    time.sleep(60)


def isolated_pid_then_sleep(path):
    sw.isolated(pid_then_sleep, (path,), 60.0)


def alive(pid: int) -> bool:
    try:
        state = open(f"/proc/{pid}/status").read().split("State:")[1].split()[0]
    except (FileNotFoundError, IndexError):
        return False
    return state != "Z"


@pytest.mark.skipif(not os.path.isdir("/proc"), reason="reads /proc")
def test_a_child_dies_with_the_process_that_runs_it(tmp_path):
    import multiprocessing
    path = tmp_path / "pid"
    parent = multiprocessing.get_context("spawn").Process(target=isolated_pid_then_sleep,
                                                          args=(path,))
    parent.start()
    deadline = time.time() + 30
    while not path.exists() or not path.read_text():
        assert time.time() < deadline, "the child never started"
        time.sleep(0.05)
    child = int(path.read_text())
    assert alive(child)
    parent.kill()
    parent.join()
    deadline = time.time() + 10
    while alive(child):
        assert time.time() < deadline, "the child outlived the process that ran it"
        time.sleep(0.05)
