"""Sweeps: tables of independent cells (a run each), on Dask (docs/sweeps.md).

    with Sweep() as sweep:                        # a LocalCluster: one single-threaded
        rows = sweep.map(fn, cells, "forward")    #   worker process per core
        times = sweep.one_at_a_time(fn, cells, "timing")

`Sweep(ADDRESS)`, or MBFG_SCHEDULER=ADDRESS, runs the same cells on an existing Dask
scheduler (`dask scheduler`, with `dask worker ADDRESS` on each machine); "serial" runs
them in this process, one after the other, without Dask. Every entry point that sweeps
takes `--scheduler` (add_argument, from_args).

- Results come back in the order of the cells, never in the order they finish, and a
  cell is a function of its arguments alone: the same table on 1 or 100 workers, bit
  for bit.
- A worker that dies loses only the task it was running: the scheduler gives it to
  another worker (up to distributed.scheduler.allowed-failures times), and a task that
  raises is retried RETRIES times.
- Timing cells (one_at_a_time) run as a phase of their own: one task at a time, with
  nothing else of the sweep running, all on one machine (the first worker's host), so
  that parallelism never distorts a measured time. `machine()` is that machine's line.
- `isolated` runs a call in a child process killed after a timeout (the robustness
  matrix's runaway cells), also inside a Dask worker.
"""
from __future__ import annotations

import contextlib
import datetime
import hashlib
import logging
import math
import multiprocessing
import os
import pathlib
import platform
import resource
import signal
import time
import sys
import warnings

ROOT = pathlib.Path(__file__).resolve().parent.parent

ENV = "MBFG_SCHEDULER"
SERIAL = ("serial", "none")   # in this process, without Dask
LOCAL = "local"               # a LocalCluster, whatever MBFG_SCHEDULER says
RETRIES = 2                 # re-runs of a task that raised (a worker's death: allowed-failures)
PROGRESS_EVERY = 30.0       # s between progress lines (and at every tenth of the table)


def add_argument(ap) -> None:
    """--scheduler for an entry point's parser."""
    ap.add_argument("--scheduler", metavar="ADDRESS", default=None,
                    help=f"a Dask scheduler to run the sweep on, e.g. tcp://host:8786; 'local': "
                         "a local cluster with one worker per core; 'serial': in this process, "
                         f"without Dask (default: ${ENV}, else local)")


def from_args(args) -> "Sweep":
    return Sweep(getattr(args, "scheduler", None))


class Sweep:
    """A context: the Dask client a sweep runs on (module doc)."""

    def __init__(self, scheduler: str | None = None, workers: int | None = None):
        address = scheduler if scheduler is not None else os.environ.get(ENV) or None
        mode = (address or "local").strip().lower()
        self.serial = mode in SERIAL
        self.address = None if self.serial or mode == LOCAL else address
        self.n_workers = workers or os.cpu_count() or 1
        self.client = self.cluster = None
        self._machine = None

    # ------------------------------------------------------------ start and stop

    def __enter__(self) -> "Sweep":
        if self.serial:
            return self
        import dask
        from distributed import Client, LocalCluster
        if self.address:
            self.client = Client(self.address, set_as_default=False)
            check_workers(self.client)
        else:
            # Worker processes (not threads: the native module holds the GIL through a
            # run), one thread each; the scheduler's web server (no dashboard without
            # bokeh) on any free port; no nanny restarts of a busy worker for
            # its memory (a long batch solve is not a leak), no sampling profiler.
            with dask.config.set({"distributed.worker.memory.terminate": False,
                                  "distributed.worker.profile.enabled": False}):
                self.cluster = LocalCluster(n_workers=self.n_workers, threads_per_worker=1,
                                            processes=True, dashboard_address=":0",
                                            silence_logs=logging.ERROR)
            self.client = Client(self.cluster, set_as_default=False)
        return self

    def start(self) -> "Sweep":
        """Started, and stopped when this process exits (for a whole entry point)."""
        import atexit
        atexit.register(self.close)
        return self.__enter__()

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        if self.client is not None:
            self.client.close()
        if self.cluster is not None:
            self.cluster.close()
        self.client = self.cluster = None

    def describe(self) -> str:
        if self.serial:
            return "in this process, one cell at a time"
        n = len(self.client.scheduler_info(n_workers=-1)["workers"])
        where = f"the Dask scheduler at {self.address}" if self.address else "a local Dask cluster"
        return f"{where}, {n} worker{'s' if n != 1 else ''}"

    # ------------------------------------------------------------ running cells

    def map(self, fn, cells: list, what: str = "cells", done=None, progress=None,
            retries: int = RETRIES, cost=None) -> list:
        """[fn(cell) for cell in cells], as tasks on the workers, in the cells' order.
        `done(cell, result)` is called as each one finishes (in the order they finish).
        `cost(cell)`, an estimate: the costliest cells start first, so that the table
        does not end on one long cell (the results keep the cells' order)."""
        cells = list(cells)
        if cost is not None and not self.serial:
            order = sorted(range(len(cells)), key=lambda i: -cost(cells[i]))
            out = self.map(fn, [cells[i] for i in order], what, done, progress, retries)
            back = [None] * len(cells)
            for i, result in zip(order, out):
                back[i] = result
            return back
        count = Counter(what, len(cells), progress)
        if self.serial or not cells:
            out = []
            for cell in cells:
                out.append(fn(cell))
                if done:
                    done(cell, out[-1])
                count.tick()
            return out
        from distributed import as_completed
        # Submitted in the cells' order, which is the order they start in.
        futures = self.client.map(fn, cells, pure=False, retries=retries)
        index = {f.key: i for i, f in enumerate(futures)}
        out = [None] * len(cells)
        try:
            for future in as_completed(futures, loop=self.client.loop):
                i = index[future.key]
                out[i] = future.result()       # raises what the task raised, after its retries
                # Its result is here now: a worker that dies later does not take it along
                # (the scheduler would run a lost result's task again).
                future.release()
                if done:
                    done(cells[i], out[i])
                count.tick()
        finally:
            for f in futures:
                f.release()
        return out

    def one_at_a_time(self, fn, cells: list, what: str = "timing", done=None,
                      progress=None, retries: int = RETRIES) -> list:
        """[fn(cell) for cell in cells], each task submitted when the one before it has
        finished, all on one machine: the timing phase. Call it when no other map of this
        sweep is running (map returns only when all its cells are done)."""
        cells = list(cells)
        count = Counter(what, len(cells), progress)
        out = []
        for cell in cells:
            if self.serial:
                out.append(fn(cell))
            else:
                future = self.client.submit(fn, cell, pure=False, retries=retries,
                                            workers=[self.timing_host()], allow_other_workers=False)
                out.append(future.result())
                future.release()
            if done:
                done(cell, out[-1])
            count.tick()
        return out

    def timing_host(self) -> str:
        """The host every timing cell runs on: the first worker's (a worker restarted
        there keeps it)."""
        # A worker that died is being restarted by its nanny: wait for one to be back.
        self.client.wait_for_workers(1)
        workers = sorted(self.client.scheduler_info(n_workers=-1)["workers"])
        from distributed.comm import get_address_host
        return get_address_host(workers[0])

    def machine(self) -> str:
        """The machine line of where the timing cells run."""
        if self._machine is None:
            self._machine = self.one_at_a_time(machine_line, [None], progress=lambda _: None)[0]
        return self._machine


def machine() -> str:
    """This machine's line for a page: processor, cores, Python, date."""
    cpu = platform.processor() or platform.machine()
    try:
        for line in open("/proc/cpuinfo"):
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return f"{cpu}, {os.cpu_count()} cores, Python {platform.python_version()}, {datetime.date.today()}"


def machine_line(_=None) -> str:
    return machine()


def stderr_line(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


class Counter:
    """'what: k of n done (s)' at every tenth of the table and every PROGRESS_EVERY s."""

    def __init__(self, what: str, total: int, progress):
        self.what, self.total, self.progress = what, total, progress or stderr_line
        self.n, self.start = 0, time.perf_counter()
        self.last = self.start

    def tick(self) -> None:
        self.n += 1
        now = time.perf_counter()
        tenth = max(1, self.total // 10)
        if self.n == self.total or self.n % tenth == 0 or now - self.last >= PROGRESS_EVERY:
            self.last = now
            self.progress(f"{self.what}: {self.n} of {self.total} done ({now - self.start:.0f} s)")


# ---------------------------------------------------------------- the workers' files

def fingerprint() -> str:
    """sha256 of what a cell's result depends on besides its arguments: the mbfg module
    (its compiled library), the harness, the scenes and the references."""
    import mbfg
    root = ROOT
    files = sorted(p for p in pathlib.Path(mbfg.__file__).parent.rglob("*")
                   if p.is_file() and p.suffix in (".so", ".pyd", ".py"))
    for folder in ("harness", "scenes", "references"):
        files += sorted(p for p in (root / folder).rglob("*")
                        if p.is_file() and "__pycache__" not in p.parts and "tests" not in p.parts)
    h = hashlib.sha256()
    for p in files:
        h.update(p.name.encode())
        h.update(p.read_bytes())
    return h.hexdigest()


def check_workers(client) -> None:
    """Refuses a cluster whose workers run another mbfg build or other repository
    files than this process: their cells would not be this sweep's."""
    mine = fingerprint()
    try:
        theirs = client.run(fingerprint)
    except Exception as e:  # noqa: BLE001 (a worker that cannot import the harness)
        raise RuntimeError(f"the workers cannot run the harness ({type(e).__name__}: {e}); "
                           "start them from the repository root with its .venv "
                           "(docs/sweeps.md)") from e
    if not theirs:
        raise RuntimeError("the Dask scheduler has no workers")
    other = sorted(w for w, f in theirs.items() if f != mine)
    if other:
        raise RuntimeError(f"{len(other)} of {len(theirs)} workers ({', '.join(other[:3])}) have "
                           "another mbfg build or other harness, scene or reference files than "
                           "this checkout: rebuild and sync them (docs/sweeps.md)")


# ---------------------------------------------------------------- a call in a child

@contextlib.contextmanager
def children_allowed():
    """A Dask worker process is daemonic, and multiprocessing refuses children to a
    daemonic process (they would be orphaned when it exits). `isolated` waits for or
    kills its child before returning, so it may have one."""
    me = multiprocessing.current_process()
    was = me._config.get("daemon")
    me._config["daemon"] = False
    try:
        yield
    finally:
        if was is not None:
            me._config["daemon"] = was


def isolated(fn, args: tuple, timeout: float, cpu_seconds: float | None = None):
    """fn(*args) in a child process forked from this one (it shares what this one has
    loaded), killed after `timeout` s of wall time or, given `cpu_seconds`, once it has
    used that much CPU time (RLIMIT_CPU: a limit that does not move with the machine's
    load, where a wall-time limit kills a run that only waited for a busy core):
    ("ok", its result), ("died", exit code) or ("timeout", None). A crash in the native
    module ends the child alone."""
    ctx = multiprocessing.get_context("fork")
    receive, send = ctx.Pipe(duplex=False)
    with children_allowed(), warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)   # fork in a threaded worker
        child = ctx.Process(target=_child, args=(send, fn, args, os.getpid(), cpu_seconds),
                            daemon=True)
        child.start()
    send.close()
    try:
        if receive.poll(timeout):
            try:
                return "ok", receive.recv()
            except EOFError:   # it died without an answer
                child.join()
                if child.exitcode == -signal.SIGXCPU:
                    return "timeout", None
                return "died", child.exitcode
        child.kill()
        return "timeout", None
    finally:
        child.join()
        receive.close()


def _child(conn, fn, args, parent: int, cpu_seconds: float | None) -> None:
    die_with_parent(parent)
    if cpu_seconds is not None:
        limit = max(1, math.ceil(cpu_seconds))
        resource.setrlimit(resource.RLIMIT_CPU, (limit, limit + 5))
    conn.send(fn(*args))
    conn.close()


def die_with_parent(parent: int) -> None:
    """On Linux, this process is killed when its parent dies (a worker killed while its
    child runs a cell leaves no orphan running on)."""
    try:
        import ctypes
        import signal
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(1, signal.SIGKILL)        # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        return
    if os.getppid() != parent:               # it died before the line above
        os._exit(1)
