"""State estimation: the three-simulation benchmark of Sanjurjo et al. (Nonlinear
Dynamics, 2017), mbfg estimate against the peer filters of harness/kalman.py.

    python -m harness.estimation                     # reports/estimation.md, its CSVs, plots
    python -m harness.estimation --seeds 3 --sweep-seeds 1 --out-dir /tmp/est   # a quick look
    python -m harness.report --only estimation       # the same, as a part of `make report`

1. Truth: the TRUE scene (scenes/estimation/) integrated by the IDA generator
   (harness/ida.py, rtol 1e-12), sampled every 5 ms for 10 s; cached under
   target/estimation/ by the hash of the scene and the horizon (IDA is deterministic).
2. Readings: `mbfg measure TRUE --trajectory truth --seed N` for the seeds 1…10; a case
   keeps the columns of its sensors.
3. Estimates on the BAD scene from the same readings: `mbfg estimate` (fixed-lag N_w = 50,
   the default N_w = 20, batch; in dependent coordinates, and `--coords ic` at N_w = 50
   where the case says so), the error-state EKF and filterpy's UKF (errorEKF-FE for the
   unknown input).

Scores against the truth over the whole run: RMSE of z, ż, z̈ (the independent
coordinates), the force RMSE where the case estimates one, the fraction of the steps with
the truth within ±2σ of the estimate, and mbfg's mean NIS against its 95 % bounds.

The binary is $MBFG, else target/release/mbfg in the repository (`make build`).
"""
from __future__ import annotations

import argparse
import csv
import dataclasses
import functools
import hashlib
import os
import pathlib
import re
import statistics
import subprocess
import sys
import time

import numpy as np

import mbfg
from harness import sweep as sweeps
from harness import trajectory as tj
from harness.pages import REPORTS, ROOT, machine, progress, write_csv

SCENES = ROOT / "scenes" / "estimation"
CACHE = ROOT / "target" / "estimation"
DT, T_END = 0.005, 10.0
SEEDS = list(range(1, 11))
SWEEP_SEEDS = [1, 2, 3]
SWEEP_WINDOWS = [1, 2, 5, 10, 20, 50, 100, "batch"]
# The IC column of the N_w table: N_w = 100 left out (≈ 15 s a run, the page's costliest).
SWEEP_WINDOWS_IC = [1, 2, 5, 10, 20, 50, "batch"]
PLOT_SEED = 1
# The UKF (sigma points through the model in Python: 4–9 times the errorEKF's time) runs
# on the first UKF_SEEDS seeds only, to keep the page within minutes.
UKF_SEEDS = 3
IDA_SETTINGS = {"formulation": "ggl", "rtol": 1e-12}
RETRIES = 3


def binary() -> pathlib.Path:
    """The mbfg CLI: $MBFG, else target/release/mbfg of this repository."""
    return pathlib.Path(os.environ.get("MBFG") or ROOT / "target" / "release" / "mbfg")


# ---------------------------------------------------------------- the cases

# Published numbers (README of the page: where they come from), per case and estimator:
# (z, ż, z̈) as strings, and the force RMSE where there is one.
PUB_EKF_ENC = ("5.1e-3", "0.056", "0.38")
PUB_UKF_ENC = ("5.2e-3", "0.056", "0.37–0.39")
PUB_BATCH_ENC = ("2.8e-3", "0.016", "0.20")


@dataclasses.dataclass(frozen=True)
class Case:
    key: str
    title: str
    true_scene: str           # file of scenes/estimation/ the readings are measured on
    bad_scene: str            # the scene mbfg estimate runs
    peer_scene: str           # the bad model the peers run
    columns: tuple            # the readings' columns kept (a sensor subset)
    peers: tuple              # "errorEKF", "UKF", "errorEKF-FE"
    sensors_text: str
    published: dict = dataclasses.field(default_factory=dict)
    force: bool = False
    windows: tuple = (50, 20, "batch")
    peers_note: str = ""
    ic_windows: tuple = ()    # mbfg estimate --coords ic rows


CASES = [
    Case("encoder", "(a) four-bar, crank encoder", "fourbar.yaml", "fourbar-bad.yaml",
         "fourbar-bad.yaml", ("enc",), ("errorEKF", "UKF"),
         "crank encoder on θ, σ = 1°, 200 Hz",
         {"errorEKF": PUB_EKF_ENC, "UKF": PUB_UKF_ENC, "mbfg batch": PUB_BATCH_ENC,
          "open loop": ("7.2", "", "")}, ic_windows=(50,)),
    Case("gyro", "(b) four-bar, coupler gyroscope alone", "fourbar.yaml", "fourbar-bad.yaml",
         "fourbar-bad.yaml", ("gyro",), ("errorEKF", "UKF"),
         "coupler gyroscope, σ = 9.84e-4 rad/s, 200 Hz",
         {"errorEKF": ("0.046", "", ""), "mbfg batch": ("diverges (6.7)", "", "")},
         ic_windows=(50,)),
    Case("force", "(c) four-bar, coupler gyroscope, unknown torque on the crank",
         "fourbar.yaml", "fourbar-bad-input.yaml", "fourbar-bad.yaml", ("gyro",),
         ("errorEKF-FE",),
         "coupler gyroscope, σ = 9.84e-4 rad/s; mbfg with `estimation: inputs:` on θ "
         "(scenes/estimation/fourbar-bad-input.yaml, σ_rate 10 N·m/√s), errorEKF-FE beside it",
         {"errorEKF-FE": ("6.8e-3", "4.8e-3", "", "2.56")}, force=True),
    Case("fivebar", "(d) five-bar, two crank encoders", "fivebar.yaml", "fivebar-bad.yaml",
         "fivebar-bad.yaml", ("enc1", "enc2"), ("errorEKF", "UKF"),
         "encoders on both cranks (th1, th2), σ = 1°, 200 Hz",
         {"errorEKF": ("7.2e-3 / 6.9e-3", "", ""), "mbfg batch": ("3.0e-3 / 3.2e-3", "", "")}),
    Case("imu", "(e) four-bar, coupler accelerometer and a marker", "fourbar-imu.yaml",
         "fourbar-imu-bad.yaml", "fourbar-bad.yaml", ("acc.x", "acc.y", "marker.x", "marker.y"),
         (), "accelerometer on the coupler at P1 (σ 5.6e-2 m/s², 200 Hz), position marker "
             "on P2 (σ 1 mm, 20 Hz)",
         peers_note="The peers of harness/kalman.py read encoders and gyroscopes only: "
                    "mbfg alone (no published numbers for this configuration)."),
]
CASE = {c.key: c for c in CASES}


def mbfg_est(w, coords: str = "dc") -> str:
    """The estimator's name of an mbfg run: "mbfg N_w=50", "mbfg batch" (DC, the default
    coordinates), "mbfg IC N_w=50", "mbfg IC batch"."""
    return "mbfg " + ("IC " if coords == "ic" else "") + ("batch" if w == "batch" else f"N_w={w}")


def estimators(case: Case) -> list[str]:
    return ([mbfg_est(w) for w in case.windows] + [mbfg_est(w, "ic") for w in case.ic_windows]
            + list(case.peers))


def label(est: str) -> str:
    if est.startswith(("mbfg N_w=", "mbfg IC N_w=")):
        w = est.split("=")[1]
        return (f"mbfg {'IC ' if ' IC ' in est else ''}fixed-lag N_w = {w}"
                + (" (default)" if w == "20" and " IC " not in est else ""))
    return est


def short_failure(status: str) -> str:
    """A failed run's reason, short: "step 1 (t = 0.005 s) did not converge (iteration
    limit)" rather than mbfg's whole message."""
    m = re.search(r"at step (\d+) \(t = ([^)]*)\) did not converge: ([^,;]+)", status)
    if m:
        return f"step {m[1]} (t = {m[2]}) did not converge ({m[3].strip()})"
    s = re.sub(r"^mbfg \w+ failed \(\d+\): (error: )?", "", status)
    return s if len(s) <= 80 else s[:80].rsplit(" ", 1)[0] + "…"


# ---------------------------------------------------------------- scenes, truth, readings

def model_scene(scene) -> str:
    """A path the mbfg Python module loads for the scene's model: the scene itself, or,
    where the module predates the scene's `sensors:`/`estimation:` sections, a copy
    without them in target/estimation/models/ (the model is the same)."""
    scene = str(scene)
    try:
        mbfg.load(scene)
        return scene
    except mbfg.SceneError as e:
        if "sensors" not in str(e) and "estimation" not in str(e):
            raise
    out, skip = [], False
    for line in pathlib.Path(scene).read_text().splitlines(keepends=True):
        if line[:1] not in (" ", "\t", "#", "-", "\n", "\r", ""):
            skip = re.match(r"(sensors|estimation)\s*:", line) is not None
        if not skip:
            out.append(line)
    path = CACHE / "models" / pathlib.Path(scene).name
    atomic_write(path, "".join(out).encode())
    return str(path)


def atomic_write(path: pathlib.Path, data: bytes) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}")
    tmp.write_bytes(data)
    os.replace(tmp, path)


def truth_path(true_scene: str, t_end: float = T_END, dt: float = DT) -> pathlib.Path:
    """The cached IDA truth of a TRUE scene of scenes/estimation/ (generated if absent)."""
    scene = SCENES / true_scene
    model = model_scene(scene)
    key = hashlib.sha256(pathlib.Path(model).read_bytes()
                         + repr((t_end, dt, sorted(IDA_SETTINGS.items()))).encode()).hexdigest()[:12]
    path = CACHE / f"truth-{scene.stem}-{t_end:g}s-{key}.csv.gz"
    if not path.exists():
        from harness import generators
        progress(f"estimation: truth of {true_scene} by IDA ({t_end:g} s at {dt * 1e3:g} ms)")
        traj, _ = generators.get("ida").generate(model, t_end, dt, IDA_SETTINGS)
        tmp = path.with_name(f".{path.name}.{os.getpid()}.csv.gz")
        tj.write(tmp, traj)
        os.replace(tmp, path)
    return path


@functools.lru_cache(maxsize=None)
def truth(path: str) -> tj.Trajectory:
    return tj.read(pathlib.Path(path))


def snapshot() -> pathlib.Path:
    """A copy of the binary for one page's runs, target/estimation/bin/mbfg-<sha256>: a
    rebuild while the page runs does not mix two builds in its tables."""
    exe = binary()
    if not exe.exists():
        raise FileNotFoundError(f"no mbfg binary at {exe} (`make build`, or set MBFG)")
    data = exe.read_bytes()
    path = CACHE / "bin" / f"mbfg-{hashlib.sha256(data).hexdigest()[:12]}"
    if not path.exists():
        atomic_write(path, data)
        path.chmod(0o755)
    return path


def cli(*args, exe=None, retries: int = RETRIES) -> str:
    """Runs the mbfg CLI (`exe`, default `binary()`); its stdout. Retries a failure a few
    times (the binary may be rebuilt under us), then raises RuntimeError with its stderr."""
    exe = pathlib.Path(exe) if exe else binary()
    if not exe.exists():
        raise FileNotFoundError(f"no mbfg binary at {exe} (`make build`, or set MBFG)")
    for attempt in range(retries):
        r = subprocess.run([str(exe), *map(str, args)], capture_output=True, text=True)
        if r.returncode == 0:
            return r.stdout
        if attempt + 1 < retries:
            time.sleep(2.0)
    raise RuntimeError(f"mbfg {args[0]} failed ({r.returncode}): {' '.join(r.stderr.split())[:400]}")


def readings_path(case: Case, seed: int, t_end: float = T_END, folder: pathlib.Path = CACHE,
                  exe=None) -> pathlib.Path:
    """The case's readings for a seed: `mbfg measure` on the TRUE scene, then the case's
    columns."""
    tpath = truth_path(case.true_scene, t_end)
    tag = tpath.name.removesuffix(".csv.gz").removeprefix("truth-")
    full = folder / "readings" / f"{tag}-seed{seed}.csv"
    if not full.exists():
        full.parent.mkdir(parents=True, exist_ok=True)
        tmp = full.with_name(f".{full.name}.{os.getpid()}.csv")
        cli("measure", SCENES / case.true_scene, "--trajectory", tpath, "--seed", seed,
            "--out", tmp, exe=exe)
        os.replace(tmp, full)
    out = folder / "readings" / f"{tag}-seed{seed}-{'+'.join(case.columns)}.csv"
    if not out.exists():
        with open(full, newline="") as f:
            rows = list(csv.reader(f))
        keep = [rows[0].index("t")] + [rows[0].index(c) for c in case.columns]
        buf = "".join(",".join(r[i] for i in keep) + "\n" for r in rows if r)
        atomic_write(out, buf.encode())
    return out


def read_table(path) -> dict:
    """A CSV of numbers as {column: array}."""
    with open(path) as f:
        header = f.readline().strip().split(",")
        data = np.loadtxt(f, delimiter=",", ndmin=2)
    return {h: data[:, i] for i, h in enumerate(header)}


@functools.lru_cache(maxsize=None)
def force_truth(true_scene: str, bad_scene: str, tpath: str) -> np.ndarray:
    """The generalized force on z the bad model lacks along the truth: Rᵀ(Q_true − Q_bad)
    (rows, f)."""
    from harness import kalman
    tr = truth(tpath)
    true = kalman.Independent(model_scene(SCENES / true_scene))
    bad = kalman.Independent(model_scene(SCENES / bad_scene))
    return np.array([true.R(q).T @ (true.model.generalized_forces(q, dq, t)
                                    - bad.model.generalized_forces(q, dq, t))
                     for t, q, dq in zip(tr.t, tr.q, tr.dq)])


@functools.lru_cache(maxsize=None)
def independent(bad_scene: str) -> list[str]:
    return list(mbfg.load(model_scene(SCENES / bad_scene)).independent)


def peer_sensors(case: Case):
    """The peers' sensors: the BAD scene's `sensors:` entries the case reads."""
    import yaml
    from harness import kalman
    spec = yaml.safe_load((SCENES / case.bad_scene).read_text())["sensors"]
    return [kalman.Sensor.from_mapping(s) for s in spec if s["name"] in case.columns]


# ---------------------------------------------------------------- one run

SUMMARY = re.compile(r"(?P<steps>\d+) steps .*? in (?P<wall>[\d.]+) s \((?P<us>[\d.]+) µs a step\)")
MODE = re.compile(r"\(dt = [^,]+, (?:(?P<coords>DC|IC), )?(?:(?P<integrator>hermite-simpson), )?"
                  r"(?:window (?P<window>\d+)|(?P<batch>batch))\)")
NIS = re.compile(r"mean NIS (?P<nis>[\d.eE+-]+|NaN|inf) against (?P<exp>[\d.]+) expected, "
                 r"95 % bounds \[(?P<lo>[\d.]+), (?P<hi>[\d.]+)\]")
PROCESS = re.compile(r"process σ (?P<sigma>[\d.eE+-]+)(?: \((?P<how>[^)]*)\))?")


def parse_summary(line: str) -> dict:
    """Wall time, µs per step, the coordinates and window, the NIS and the process σ of
    `mbfg estimate`'s summary line."""
    out = {}
    m = SUMMARY.search(line)
    if m:
        out.update(steps=int(m["steps"]), wall_s=float(m["wall"]), us_per_step=float(m["us"]))
    m = MODE.search(line)
    if m:
        out.update(coords=m["coords"] or "DC", window="batch" if m["batch"] else int(m["window"]),
                   integrator=m["integrator"] or "trapezoidal")
    m = NIS.search(line)
    if m:
        nis, lo, hi = float(m["nis"]), float(m["lo"]), float(m["hi"])
        out.update(nis=nis, nis_expected=float(m["exp"]), nis_lo=lo, nis_hi=hi,
                   nis_ok=bool(lo <= nis <= hi))
    m = PROCESS.search(line)
    if m:
        how = m["how"] or "as given"
        if how.startswith("from the readings"):
            how = "from the readings"
        elif how.startswith("the default"):
            how = "the default"
        elif how.startswith("lowered after identification"):
            how = "lowered after identification"
        out.update(process_sigma=float(m["sigma"]), process_sigma_how=how)
    return out


def run_task(task: tuple) -> dict:
    """One estimate and its scores: (case key, seed, estimator, t_end, readings path,
    truth path, keep the series for the plots[, the mbfg binary])."""
    key, seed, est, t_end, rpath, tpath, keep, *exe = task
    exe = exe[0] if exe else None
    case = CASE[key]
    tr = truth(tpath)
    names = independent(case.bad_scene)
    iz = [tr.names.index(c) for c in names]
    row = {"case": key, "seed": seed, "estimator": est, "t_end_s": t_end}
    start = time.perf_counter()
    try:
        if est.startswith("mbfg"):
            out = CACHE / "estimates" / f"{key}-{est.replace(' ', '').replace('=', '')}-seed{seed}-{t_end:g}s-{os.getpid()}.csv"
            out.parent.mkdir(parents=True, exist_ok=True)
            args = ["--batch"] if est.endswith("batch") else ["--window", est.split("=")[1]]
            if " IC " in est:
                args += ["--coords", "ic"]
            # The page's copy of the binary is not rebuilt under us: a failure is the
            # estimate's (IC stops at step 1 on the gyroscope alone), not worth retrying.
            line = cli("estimate", SCENES / case.bad_scene, "--measurements", rpath, *args,
                       "--out", out, exe=exe, retries=1 if exe else RETRIES)
            row.update(parse_summary(line))
            d = read_table(out)
            out.unlink()
            z = np.column_stack([d[f"q:{c}"] for c in names])
            dz = np.column_stack([d[f"dq:{c}"] for c in names])
            ddz = np.column_stack([d[f"ddq:{c}"] for c in names])
            sz = np.column_stack([d[f"sd:q:{c}"] for c in names])
            force = (np.column_stack([d[f"Q:{c}"] for c in names]) if f"Q:{names[0]}" in d else None)
            sforce = (np.column_stack([d[f"sd:Q:{c}"] for c in names]) if force is not None else None)
            t = d["t"]
        else:
            from harness import kalman
            peer = model_scene(SCENES / case.peer_scene)
            sensors = peer_sensors(case)
            filt = (kalman.UKF(peer, sensors) if est == "UKF" else
                    kalman.ErrorEKF(peer, sensors, force_estimation=est == "errorEKF-FE"))
            e = filt.run(kalman.read_readings(rpath))
            t, z, dz, ddz, sz, force, sforce = e.t, e.z, e.dz, e.ddz, e.sz, e.force, e.sforce
            row.update(steps=len(t), wall_s=e.wall_time_s, us_per_step=e.wall_time_s / len(t) * 1e6)
    except (RuntimeError, OSError, ValueError, KeyError, np.linalg.LinAlgError) as e:
        row.update(status=" ".join(str(e).split())[:300])
        return row
    if len(t) != len(tr.t) or np.max(np.abs(t - tr.t)) > 1e-9:
        row.update(status=f"the estimate's {len(t)} rows are not the truth's {len(tr.t)} times")
        return row
    row["status"] = "ok"
    row["process_s"] = time.perf_counter() - start
    err = {"z": z - tr.q[:, iz], "dz": dz - tr.dq[:, iz], "ddz": ddz - tr.ddq[:, iz]}
    for k, e in err.items():
        for j, c in enumerate(names):
            row[f"rmse_{k}:{c}"] = float(np.sqrt(np.mean(e[:, j] ** 2)))
    finite = np.isfinite(err["z"]).all()
    row["within_2sd"] = float(np.mean(np.abs(err["z"]) <= 2 * sz)) if finite else 0.0
    if case.force:
        ftrue = force_truth(case.true_scene, case.peer_scene, tpath)
        row["force_rms"] = float(np.sqrt(np.mean(ftrue ** 2)))
        if force is None:
            row["status"] = "no force estimate in the output"
        else:
            ferr = force - ftrue
            row["force_rmse"] = float(np.sqrt(np.mean(ferr ** 2)))
            row["force_within_2sd"] = float(np.mean(np.abs(ferr) <= 2 * sforce))
    if keep:
        row["series"] = {"t": t, "z": z, "sz": sz, "err_z": err["z"],
                         "truth_z": tr.q[:, iz],
                         "force": force, "sforce": sforce,
                         "force_truth": force_truth(case.true_scene, case.peer_scene, tpath)
                         if case.force else None}
    return row


def task_cost(task: tuple) -> float:
    """Rough seconds of a task (for the order: the longest first)."""
    key, _, est, t_end, *_ = task
    base = {"UKF": 6.5, "errorEKF": 1.7, "errorEKF-FE": 2.6, "mbfg batch": 1.0,
            "mbfg IC batch": 1.3}.get(est)
    if base is None:
        w = int(est.split("=")[1])
        base = (0.2 + 0.045 * w) * (2 if " IC " in est else 1)
    return base * (2.4 if key == "fivebar" else 1) * t_end / T_END


def open_loop(case: Case, tpath: str) -> dict:
    """The bad model alone (no readings): the reference with no estimation."""
    from harness import kalman
    tr = truth(tpath)
    ic = kalman.Independent(model_scene(SCENES / case.peer_scene))
    e = kalman.simulate(ic, tr.t)
    iz = [tr.names.index(c) for c in ic.names]
    row = {"case": case.key, "seed": "", "estimator": "open loop", "status": "ok"}
    for k, est, ref in (("z", e.z, tr.q), ("dz", e.dz, tr.dq), ("ddz", e.ddz, tr.ddq)):
        for j, c in enumerate(ic.names):
            row[f"rmse_{k}:{c}"] = float(np.sqrt(np.mean((est[:, j] - ref[:, iz[j]]) ** 2)))
    return row


# ---------------------------------------------------------------- the whole benchmark

def run(cases=CASES, seeds=SEEDS, sweep_seeds=SWEEP_SEEDS, sweep_windows=SWEEP_WINDOWS,
        t_end: float = T_END, sweep=None, ukf_seeds: int | None = UKF_SEEDS,
        sweep_windows_ic=SWEEP_WINDOWS_IC) -> dict:
    """Every (case, seed, estimator) run, the N_w sweep on the crank encoder, the open
    loops. `sweep`: harness/sweep.py's Sweep (None: in this process)."""
    began = time.perf_counter()
    exe = str(snapshot())
    tasks, rpaths = [], {}
    for case in cases:
        tpath = str(truth_path(case.true_scene, t_end))
        for seed in seeds:
            rpath = str(readings_path(case, seed, t_end, exe=exe))
            rpaths[(case.key, seed)] = rpath
            for est in estimators(case):
                if est == "UKF" and ukf_seeds and seed not in seeds[:ukf_seeds]:
                    continue
                tasks.append((case.key, seed, est, t_end, rpath, tpath, seed == PLOT_SEED, exe))
    enc = next((c for c in cases if c.key == "encoder"), None)
    done = {(t[0], t[1], t[2]) for t in tasks}
    if enc is not None and (sweep_windows or sweep_windows_ic):
        tpath = str(truth_path(enc.true_scene, t_end))
        for seed in sweep_seeds:
            rpath = rpaths.get((enc.key, seed)) or str(readings_path(enc, seed, t_end, exe=exe))
            ests = [mbfg_est(w) for w in sweep_windows]
            ests += [mbfg_est(w, "ic") for w in sweep_windows_ic]
            for est in ests:
                if ("encoder", seed, est) not in done:
                    tasks.append(("encoder", seed, est, t_end, rpath, tpath, False, exe))
    progress(f"estimation: {len(tasks)} runs "
             f"({sweep.describe() if sweep is not None else 'in this process'})")
    rows = (sweep.map(run_task, tasks, "estimation runs", cost=task_cost) if sweep is not None
            else [run_task(t) for t in tasks])
    loops = [open_loop(c, str(truth_path(c.true_scene, t_end))) for c in cases]
    return {"rows": rows, "open_loop": loops, "seeds": list(seeds),
            "sweep_seeds": list(sweep_seeds), "sweep_windows": list(sweep_windows),
            "sweep_windows_ic": list(sweep_windows_ic), "t_end": t_end, "cases": [c.key for c in cases],
            "ukf_seeds": list(seeds[:ukf_seeds]) if ukf_seeds else list(seeds),
            "seconds": time.perf_counter() - began,
            "binary": str(binary()), "binary_sha256": pathlib.Path(exe).name.removeprefix("mbfg-")}


# ---------------------------------------------------------------- scores and targets

def ok_rows(rows, case, est, seeds=None):
    return [r for r in rows if r["case"] == case and r["estimator"] == est
            and r.get("status") == "ok" and (seeds is None or r["seed"] in seeds)]


def med(rows, key):
    vals = [r[key] for r in rows if r.get(key) is not None]
    return statistics.median(vals) if vals else None


def worst(rows, key, low_is_bad=False):
    vals = [r[key] for r in rows if r.get(key) is not None]
    if not vals:
        return None
    return min(vals) if low_is_bad else max(vals)


def worst_seed(rows, key):
    best = max((r for r in rows if r.get(key) is not None), key=lambda r: r[key], default=None)
    return None if best is None else best["seed"]


def g(v, spec=".2e"):
    if v is None:
        return "—"
    if isinstance(v, float) and not np.isfinite(v):
        return str(v)
    return format(v, spec)


# The targets for mbfg (medians over the seeds): (case, estimators, metric, bound, what).
TARGETS = [
    ("encoder", ("mbfg N_w=50", "mbfg N_w=20"), "rmse_z:theta", 3.0e-3, "z ≤ 3.0e-3 rad"),
    ("encoder", ("mbfg N_w=50", "mbfg N_w=20"), "rmse_dz:theta", 0.025, "ż ≤ 0.025 rad/s"),
    ("encoder", ("mbfg N_w=50", "mbfg N_w=20"), "rmse_ddz:theta", 0.25, "z̈ ≤ 0.25 rad/s²"),
    ("encoder", ("mbfg batch",), "rmse_z:theta", 2.8e-3, "z ≤ 2.8e-3 rad"),
    ("encoder", ("mbfg batch",), "rmse_dz:theta", 0.016, "ż ≤ 0.016 rad/s"),
    ("encoder", ("mbfg batch",), "rmse_ddz:theta", 0.20, "z̈ ≤ 0.20 rad/s²"),
    ("gyro", ("mbfg N_w=50", "mbfg N_w=20", "mbfg batch"), "rmse_z:theta", 0.046, "z ≤ 0.046 rad"),
    ("force", ("mbfg N_w=50", "mbfg N_w=20", "mbfg batch"), "force_rmse", 1.3, "force ≤ 1.3 N·m"),
    ("force", ("mbfg N_w=50", "mbfg N_w=20", "mbfg batch"), "rmse_z:theta", 3.4e-3, "z ≤ 3.4e-3 rad"),
    ("force", ("mbfg N_w=50", "mbfg N_w=20", "mbfg batch"), "rmse_dz:theta", 2.4e-3, "ż ≤ 2.4e-3 rad/s"),
]


def verdicts(res) -> list[tuple[str, bool]]:
    """(line, met) per target, on the medians over the seeds."""
    rows, out = res["rows"], []
    for case, ests, key, bound, what in TARGETS:
        if case not in res["cases"]:
            continue
        for est in ests:
            v = med(ok_rows(rows, case, est), key)
            if v is None:
                continue
            met = v <= bound
            out.append((f"{CASE[case].title}, {label(est)}: {what}: median {g(v)}", met))
    if "fivebar" in res["cases"]:
        for est in ("mbfg N_w=50", "mbfg N_w=20", "mbfg batch"):
            for c in independent(CASE["fivebar"].bad_scene):
                m, e = (med(ok_rows(rows, "fivebar", x), f"rmse_z:{c}") for x in (est, "errorEKF"))
                if m is None or e is None:
                    continue
                out.append((f"{CASE['fivebar'].title}, {label(est)}: z of {c} ≤ errorEKF's / 2 "
                            f"({g(e / 2)}): median {g(m)}", m <= e / 2))
    return out


# ---------------------------------------------------------------- the page

def headline(res) -> str:
    """One line: the targets met, and the crank-encoder case against the errorEKF."""
    v = verdicts(res)
    out = f"Summary: mbfg meets {sum(m for _, m in v)} of {len(v)} targets"
    rows = res["rows"]
    if "encoder" in res["cases"]:
        m = med(ok_rows(rows, "encoder", "mbfg N_w=50", res["seeds"]), "rmse_z:theta")
        e = med(ok_rows(rows, "encoder", "errorEKF", res["seeds"]), "rmse_z:theta")
        out += (f"; crank encoder, θ RMSE {g(m)} rad at N_w = 50 against the errorEKF's "
                f"{g(e)} (medians over {len(res['seeds'])} seed{'s' if len(res['seeds']) != 1 else ''})")
    return out + "."


INTRO = """# State estimation: the three-simulation benchmark

The field's benchmark for state estimators of mechanisms (Sanjurjo, Naya, Blanco-Claraco,
Torres-Moreno, Giménez-Fernández, *Accuracy and efficiency comparison of various nonlinear
Kalman filters applied to multibody models*, Nonlinear Dynamics, 2017,
doi:10.1007/s11071-017-3354-z): three simulations of one mechanism.

1. **Truth.** The TRUE model is simulated (here by the IDA generator, `harness/ida.py`,
   rtol 1e-12, sampled every 5 ms), and its sensors read with Gaussian noise
   (`mbfg measure --seed N`, one noise draw per seed).
2. **Bad model.** The same mechanism with deliberate modelling errors — gravity 9 m/s²
   instead of 10, and the initial crank angle(s) π/16 off — run alone (the *open loop*
   row: what the model predicts with no readings).
3. **Estimator.** The bad model corrected by the noisy readings: `mbfg estimate` (the
   fixed-lag smoother over the N_w newest steps, and the batch over the whole record),
   and, on the same readings and the same bad model, the peers of `harness/kalman.py`:
   the error-state EKF (errorEKF; errorEKF-FE with a force state), and filterpy's UKF.

mbfg's rows are its default graph in dependent coordinates (DC: every q, the process
noise on every q̈) unless marked **IC**: `mbfg estimate --coords ic`, the graph in the
scene's independent coordinates (the process noise on z̈ alone). IC costs about twice
DC per step here and is less robust from a bad start (on the gyroscope alone it stops
at step 1); its rows report a failure as such.

The scenes are in `scenes/estimation/` (`fourbar.yaml` and `fourbar-bad.yaml`, …).
Every estimator starts from the bad model's initial state and knows nothing of the truth;
mbfg and the peers run their tunings as committed (the scenes' `estimation:` sections and
the module docstring of `harness/kalman.py`), not tuned on this truth.

## How to read the tables

- **z, ż, z̈**: RMSE of the independent coordinate(s) (the four-bar's crank angle θ; the
  five-bar's th1 / th2), its rate and its acceleration, against the truth over the whole
  run (the first steps, where the estimate still converges from the bad start, included).
  Each cell is the **median over the seeds**, with the **worst seed** in parentheses.
- **within ±2σ**: the fraction of the steps whose true z lies within ±2 of the estimator's
  own reported standard deviation (`sd:q:theta` for mbfg) — about 95 % for an honest σ;
  far below it, the estimator is overconfident. Median (worst seed).
- **mean NIS**: mbfg's normalized innovation squared averaged over the run, from its
  summary line, against the expected value (the readings per step) and its 95 % bounds;
  *in bounds* counts the seeds where it lies inside them. **process σ**: the σ of mbfg's
  process (dynamics) factor the run used, as its summary line reports it (the scene's
  `estimation: process_sigma`, mbfg's default, or the σ mbfg chose from the readings
  where a filter pass with the default left the mean NIS outside its bounds), median
  over the seeds, with how many seeds took each.
- **µs/step**: the run's wall time per step (median over the seeds): mbfg's from its
  summary line (the solve, without the process start), the peers' measured around
  `run()` in Python. Runs share the machine's cores with each other, so compare orders of
  magnitude, not percent.
- **published**: the numbers of Sanjurjo et al. 2017's benchmark for the same
  configuration, from the authors' toolbox (GitHub MBDS/mbde-matlab at commit 9072204,
  "State used for the paper of Nonlinear Dynamics", run with GNU Octave on one noise
  draw): they rank the methods; they are not the paper's own table, and one draw is not
  our median. The toolbox's "batch MAP smoother" is beside mbfg batch (a factor graph in
  all but name); the gyroscope has the later, realistic σ of 9.84e-4 rad/s.

Reproduce: `make build`, then `.venv/bin/python -m harness.estimation` (or
`.venv/bin/python -m harness.report --only estimation`); `--seeds N`, `--sweep-seeds N`,
`--t-end S` for a quicker look, `MBFG=path/to/mbfg` for another binary. The truths are
cached in `target/estimation/`.
"""


def case_table(res, case: Case, loop: dict) -> str:
    rows = res["rows"]
    names = independent(case.bad_scene)
    head = "| estimator | z (rad) | ż (rad/s) | z̈ (rad/s²) |"
    if case.force:
        head += " force (N·m) | force within ±2σ |"
    head += " within ±2σ | mean NIS (in bounds) | process σ | µs/step | published z / ż / z̈" + (" / force" if case.force else "") + " |"
    lines = [head, "|" + "---|" * (head.count("|") - 1)]

    def cell(rs, k, spec=".2e"):
        vals = [format(v, spec) if v is not None else "—" for v in (med(rs, k), worst(rs, k))]
        return "—" if vals[0] == "—" else f"{vals[0]} ({vals[1]})"

    def coords(rs, k):
        return " / ".join(cell(rs, f"rmse_{k}:{c}") for c in names)

    for est in estimators(case):
        rs = ok_rows(rows, case.key, est, res["seeds"])
        failed = [r for r in rows if r["case"] == case.key and r["estimator"] == est
                  and r["seed"] in res["seeds"] and r.get("status") != "ok"]
        pub = case.published.get(est, ())
        pub_txt = " / ".join(p for p in pub if p) if pub else "—"
        if not rs:
            why = f"failed: {short_failure(failed[0]['status'])}" if failed else "not run"
            lines.append(f"| {label(est)} | {why} |" + " |" * (head.count("|") - 4)
                         + f" {pub_txt} |")
            continue
        line = f"| {label(est)} | {coords(rs, 'z')} | {coords(rs, 'dz')} | {coords(rs, 'ddz')} |"
        if case.force:
            line += f" {cell(rs, 'force_rmse')} | {pct(rs, 'force_within_2sd')} |"
        nis = "—"
        if any(r.get("nis") is not None for r in rs):
            k = sum(bool(r.get("nis_ok")) for r in rs)
            nis = (f"{g(med(rs, 'nis'), '.3g')} ({g(worst(rs, 'nis'), '.3g')}) vs "
                   f"{g(rs[0]['nis_expected'], 'g')} [{g(rs[0]['nis_lo'], '.3g')}, "
                   f"{g(rs[0]['nis_hi'], '.3g')}]; {k}/{len(rs)}")
        ps = g(med(rs, "process_sigma"), ".3g")
        hows = [r.get("process_sigma_how") for r in rs if r.get("process_sigma_how")
                not in (None, "as given")]
        if ps != "—" and len(set(hows)) == 1:
            ps += f" ({hows[0]})"
        elif ps != "—" and hows:
            ps += " (" + ", ".join(f"{h} on {hows.count(h)}" for h in sorted(set(hows))) + ")"
        line += (f" {pct(rs, 'within_2sd')} | {nis} | {ps} | {g(med(rs, 'us_per_step'), '.0f')} |"
                 f" {pub_txt} |")
        if failed:
            line += f" ({len(failed)} seed(s) failed: {short_failure(failed[0]['status'])})"
        lines.append(line)
    pub = case.published.get("open loop", ())
    lines.append(f"| open loop (bad model alone) | {' / '.join(g(loop[f'rmse_z:{c}']) for c in names)} |"
                 f" {' / '.join(g(loop[f'rmse_dz:{c}']) for c in names)} |"
                 f" {' / '.join(g(loop[f'rmse_ddz:{c}']) for c in names)} |"
                 + (" — | — |" if case.force else "")
                 + f" — | — | — | — | {' / '.join(p for p in pub if p) or '—'} |")
    worst_z = {label(e): worst_seed(ok_rows(rows, case.key, e, res["seeds"]), f"rmse_z:{names[0]}")
               for e in estimators(case)}
    note = ", ".join(f"{k} seed {v}" for k, v in worst_z.items() if v is not None)
    return "\n".join(lines) + (f"\n\nWorst seed by z{' of ' + names[0] if len(names) > 1 else ''}: {note}." if note else "")


def pct(rs, key):
    m, w = med(rs, key), worst(rs, key, low_is_bad=True)
    return "—" if m is None else f"{m * 100:.1f} % ({w * 100:.1f} %)"


def sweep_table(res) -> str:
    """The N_w table: DC and IC side by side, medians over the sweep's seeds."""
    rows, seeds = res["rows"], res["sweep_seeds"]
    dc_ws, ic_ws = res["sweep_windows"], res.get("sweep_windows_ic", [])
    head = ("| N_w | DC z (rad) | DC ż (rad/s) | DC z̈ (rad/s²) | DC µs/step "
            "| IC z (rad) | IC ż (rad/s) | IC z̈ (rad/s²) | IC µs/step |")
    lines = [head, "|" + "---|" * 9]

    def cells(est, ran):
        if not ran:
            return ["not run", "", "", ""]
        rs = ok_rows(rows, "encoder", est, seeds)
        bad = [r for r in rows if r["case"] == "encoder" and r["estimator"] == est
               and r["seed"] in seeds and r.get("status") != "ok"]
        if not rs:
            return [f"failed: {short_failure(bad[0]['status']) if bad else 'not run'}", "", "", ""]
        us = g(med(rs, "us_per_step"), ".0f")
        if bad:
            us += f" ({len(bad)} of {len(rs) + len(bad)} seeds failed: {short_failure(bad[0]['status'])})"
        return [g(med(rs, "rmse_z:theta")), g(med(rs, "rmse_dz:theta")),
                g(med(rs, "rmse_ddz:theta")), us]

    for w in sorted(set(dc_ws) | set(ic_ws), key=lambda w: (w == "batch", 0 if w == "batch" else w)):
        row = cells(mbfg_est(w), w in dc_ws) + cells(mbfg_est(w, "ic"), w in ic_ws)
        lines.append(f"| {w} | " + " | ".join(row) + " |")
    for name, pub in (("published batch MAP smoother", PUB_BATCH_ENC),
                      ("published errorEKF", PUB_EKF_ENC)):
        lines.append(f"| {name} | {pub[0]} | {pub[1]} | {pub[2]} | — | — | — | — | — |")
    return "\n".join(lines)


def write_page(res, out_dir: pathlib.Path = REPORTS, plots: bool = True) -> str:
    """Writes estimation.md into out_dir, estimation/runs.csv, estimation/summary.csv and
    the plots into out_dir/estimation/; returns the markdown."""
    folder = out_dir / "estimation"
    folder.mkdir(parents=True, exist_ok=True)
    rows = res["rows"]
    loops = {r["case"]: r for r in res["open_loop"]}
    seeds, sweep_seeds = res["seeds"], res["sweep_seeds"]
    title, rest = INTRO.split("\n", 1)
    md = [title + "\n", headline(res) + "\n" + rest]
    ukf = res.get("ukf_seeds", seeds)
    md.append(f"Machine: {machine()}. {len(seeds)} noise seeds ({seeds[0]}…{seeds[-1]}) of "
              f"{res['t_end']:g} s at 5 ms per case"
              + (f" (the UKF, the slowest peer, on the first {len(ukf)} only: its median and "
                 f"worst are over those)" if len(ukf) < len(seeds) else "")
              + f"; the page took {res['seconds']:.0f} s (runs in parallel, one per core). "
              f"mbfg: `{display(res.get('binary', binary()))}` (sha256 "
              f"{res.get('binary_sha256', '?')}…, copied for the page's runs).\n")
    md.append("## Targets for mbfg\n")
    md.append("On the medians over the seeds; the published batch MAP numbers are the "
              "batch's targets, the published errorEKF's set the others.\n")
    for line, met in verdicts(res):
        md.append(f"- {'met' if met else '**missed**'}: {line}")
    md.append("")
    for key in res["cases"]:
        case = CASE[key]
        md.append(f"## {case.title}\n")
        md.append(f"Sensors: {case.sensors_text}. mbfg runs `scenes/estimation/{case.bad_scene}`"
                  + (f", the peers `scenes/estimation/{case.peer_scene}`" if case.peers else "")
                  + f"; readings measured on `scenes/estimation/{case.true_scene}`.\n")
        if case.peers_note:
            md.append(case.peers_note + "\n")
        if case.force:
            fr = med(ok_rows(rows, key, estimators(case)[0]), "force_rms")
            md.append("The force truth is the generalized force on θ the bad model lacks "
                      "along the true motion, Rᵀ(Q_true − Q_bad) (R = ∂q/∂z): its RMS is "
                      f"{g(fr, '.2f')} N·m (published: 9.6). mbfg's input is the `Q:theta` "
                      "column, the errorEKF-FE's its force state.\n")
        md.append(case_table(res, case, loops[key]) + "\n")
        if plots:
            for kind in ("estimate", "error"):
                p = folder / f"{key}-{kind}.png"
                if p.exists():
                    md.append(f"![{case.title}: {kind}](estimation/{p.name})\n")
    if "encoder" in res["cases"] and res["sweep_windows"]:
        md.append("## RMSE over the window size (the paper's table for estimation)\n")
        md.append(f"The crank-encoder case (a), mbfg's fixed-lag smoother over N_w steps and "
                  f"the batch; medians over {len(sweep_seeds)} seed"
                  f"{'s' if len(sweep_seeds) != 1 else ''} ({', '.join(map(str, sweep_seeds))}"
                  f"{': fewer than the tables above, to keep the page short' if len(sweep_seeds) < len(seeds) else ''}), "
                  "with the cost per step from mbfg's summary line (µs, the solve alone): "
                  "the dependent-coordinate graph (DC, the default) beside `--coords ic` (IC)"
                  + (f"; IC not run at N_w = "
                     f"{', '.join(str(w) for w in res['sweep_windows'] if w not in res.get('sweep_windows_ic', []))}"
                     f" (the costliest runs)" if any(w not in res.get("sweep_windows_ic", [])
                                                         for w in res["sweep_windows"]) else "")
                  + ".\n")
        md.append(sweep_table(res) + "\n")
    text = "\n".join(md)
    (out_dir / "estimation.md").write_text(text)
    flat = [{k: v for k, v in r.items() if k != "series"} for r in rows]
    write_csv(folder / "runs.csv", flat + res["open_loop"])
    write_csv(folder / "summary.csv", summary_rows(res))
    return text


def display(path) -> str:
    try:
        return pathlib.Path(path).resolve().relative_to(ROOT).as_posix()
    except ValueError:
        return str(path)


def summary_rows(res) -> list[dict]:
    out = []
    for key in res["cases"]:
        case = CASE[key]
        for est in estimators(case):
            rs = ok_rows(res["rows"], key, est, res["seeds"])
            row = {"case": key, "estimator": est, "seeds_ok": len(rs)}
            for k in sorted({k for r in rs for k in r if k.startswith("rmse_") or k in
                             ("force_rmse", "within_2sd", "nis", "us_per_step")}):
                row[f"median {k}"] = med(rs, k)
                row[f"worst {k}"] = worst(rs, k, low_is_bad=k == "within_2sd")
            out.append(row)
    return out


# ---------------------------------------------------------------- plots

def plot(res, out_dir: pathlib.Path = REPORTS) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    folder = out_dir / "estimation"
    folder.mkdir(parents=True, exist_ok=True)
    for key in res["cases"]:
        case = CASE[key]
        series = {r["estimator"]: r["series"] for r in res["rows"]
                  if r["case"] == key and r.get("series") is not None}
        if not series:
            continue
        names = independent(case.bad_scene)
        shown = [e for e in ("mbfg N_w=50", "errorEKF", "errorEKF-FE") if e in series]
        # Estimate against truth with its ±2σ band, and the same as an error.
        fig, axes = plt.subplots(2, len(names), figsize=(6.5 * len(names), 6.5), squeeze=False,
                                 sharex=True)
        for j, c in enumerate(names):
            ax, ax2 = axes[0, j], axes[1, j]
            first = series[shown[0]] if shown else next(iter(series.values()))
            ax.plot(first["t"], first["truth_z"][:, j], color="k", lw=1.0, label="truth")
            for e, color in zip(shown, ("C0", "C3", "C3")):
                s = series[e]
                ax.plot(s["t"], s["z"][:, j], color=color, lw=0.8, ls="--", label=label(e))
                ax.fill_between(s["t"], s["z"][:, j] - 2 * s["sz"][:, j],
                                s["z"][:, j] + 2 * s["sz"][:, j], color=color, alpha=0.25)
                ax2.plot(s["t"], s["err_z"][:, j], color=color, lw=0.7, label=f"{label(e)} error")
                ax2.fill_between(s["t"], -2 * s["sz"][:, j], 2 * s["sz"][:, j], color=color,
                                 alpha=0.2, label=f"{label(e)} ±2σ")
            ax.set_ylabel(f"{c} (rad)")
            ax.set_title(f"{case.title}, seed {PLOT_SEED}", fontsize=9)
            ax.legend(fontsize=7)
            ax2.set_ylabel(f"estimate − truth, {c} (rad)")
            ax2.set_xlabel("t (s)")
            lim = max(np.percentile(np.abs(series[e]["err_z"][len(series[e]["t"]) // 10:, j]), 99.5)
                      for e in shown) * 3 if shown else None
            if lim:
                ax2.set_ylim(-lim, lim)
            ax2.legend(fontsize=7)
        fig.tight_layout()
        fig.savefig(folder / f"{key}-estimate.png", dpi=110)
        plt.close(fig)
        # Error against time, every estimator.
        rows_n = len(names) + (1 if case.force else 0)
        fig, axes = plt.subplots(rows_n, 1, figsize=(9, 3.2 * rows_n), squeeze=False, sharex=True)
        for j, c in enumerate(names):
            ax = axes[j, 0]
            for e, s in series.items():
                ax.plot(s["t"], np.abs(s["err_z"][:, j]), lw=0.7, label=label(e))
            ax.set_yscale("log")
            ax.set_ylabel(f"|error| of {c} (rad)")
            ax.legend(fontsize=7, ncol=2)
        if case.force:
            ax = axes[-1, 0]
            for e, s in series.items():
                if s.get("force") is not None:
                    ax.plot(s["t"], s["force"][:, 0], lw=0.7, label=label(e))
            ft = next(s["force_truth"] for s in series.values())
            ax.plot(next(iter(series.values()))["t"], ft[:, 0], color="k", lw=1.0, label="truth")
            ax.set_ylabel("force on θ (N·m)")
            lim = 3 * np.max(np.abs(ft))
            ax.set_ylim(-lim, lim)
            ax.legend(fontsize=7)
        axes[0, 0].set_title(f"{case.title}: error against time, seed {PLOT_SEED}", fontsize=9)
        axes[-1, 0].set_xlabel("t (s)")
        fig.tight_layout()
        fig.savefig(folder / f"{key}-error.png", dpi=110)
        plt.close(fig)


# ---------------------------------------------------------------- entry point

def write(out_dir: pathlib.Path = REPORTS, sweep=None, seeds=SEEDS, sweep_seeds=SWEEP_SEEDS,
          t_end: float = T_END, cases=None, ukf_seeds: int | None = UKF_SEEDS) -> dict:
    """The whole page: runs, plots, markdown and CSVs into out_dir."""
    began = time.perf_counter()
    res = run([CASE[k] for k in cases] if cases else CASES, seeds, sweep_seeds,
              SWEEP_WINDOWS, t_end, sweep, ukf_seeds, SWEEP_WINDOWS_IC)
    plot(res, out_dir)
    res["seconds"] = time.perf_counter() - began
    write_page(res, out_dir)
    progress(f"wrote {display(out_dir / 'estimation.md')} and {display(out_dir / 'estimation')}/ "
             f"in {res['seconds']:.0f} s")
    for line, met in verdicts(res):
        progress(f"  {'met' if met else 'MISSED'}: {line}")
    return res


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m harness.estimation",
                                 description=__doc__.split("\n\n")[0])
    ap.add_argument("--out-dir", type=pathlib.Path, default=REPORTS)
    ap.add_argument("--seeds", type=int, default=len(SEEDS), help="seeds 1…N (default 10)")
    ap.add_argument("--sweep-seeds", type=int, default=len(SWEEP_SEEDS),
                    help="seeds of the N_w table (default 3)")
    ap.add_argument("--t-end", type=float, default=T_END)
    ap.add_argument("--ukf-seeds", type=int, default=UKF_SEEDS,
                    help=f"the UKF on the first N seeds only (default {UKF_SEEDS}; 0: all)")
    ap.add_argument("--cases", default=None,
                    help=f"comma-separated subset of {', '.join(CASE)} (default: all)")
    sweeps.add_argument(ap)
    args = ap.parse_args(argv)
    if not binary().exists():
        print(f"estimation: no mbfg binary at {binary()} (`make build`, or set MBFG)",
              file=sys.stderr)
        return 1
    cases = args.cases.split(",") if args.cases else None
    with sweeps.from_args(args) as sweep:
        write(args.out_dir, sweep, list(range(1, args.seeds + 1)),
              list(range(1, args.sweep_seeds + 1)), args.t_end, cases, args.ukf_seeds)
    return 0


if __name__ == "__main__":
    # As harness.estimation, not __main__: the sweep's tasks name its functions.
    from harness import estimation
    sys.exit(estimation.main())
