"""`make reference`: the ground truth of the scene suite, regenerated from the scenes;
and a reference of the same kind for any scene file.

For every scene of SUITE, the most accurate generator available for it writes
`references/<scene>/reference.csv.gz` (the CSV contract, sampled every SAMPLE_DT) and
`references/<scene>/provenance.json`; other generators cross-check it and the
disagreement (max and RMSE over the point coordinates) is recorded there. Generators
come from the registry (harness/generators.py) at their reference settings.

    python -m harness.reference                     # regenerate the whole suite
    python -m harness.reference fourbar             # one scene of the suite
    python -m harness.reference --check             # regenerate into a temporary folder
                                                    # and compare with the committed ones
    python -m harness.reference my-scene.yaml --t-end 2
                                                    # your scene: my-scene.reference/
    python -m harness.reference --check my-scene.yaml --t-end 2
                                                    # is my-scene.reference/ reproduced?
    python -m harness.reference --scheduler tcp://host:8786
                                                    # the runs on a Dask cluster
                                                    # (docs/sweeps.md)
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import pathlib
import sys
import tempfile
import time

import numpy as np

import mbfg
from harness import generators
from harness import sweep as sweeps
from harness import trajectory as tj

ROOT = pathlib.Path(__file__).resolve().parent.parent
REFERENCES = ROOT / "references"
# Every report compares at multiples of this step (dt ≥ 1 ms at its own samples,
# dt < 1 ms at these).
SAMPLE_DT = 1e-3

# (generator, settings over its reference settings). IDA at rtol 1e-14: 1.6e-11 m on
# the four-bar over 5 s against a minimal-coordinate ODE (1e-12 gives 1.9e-9 m), about
# 3 s per scene; exudyn and Pinocchio at h = 1e-5.
IDA = ("ida", {})
EXUDYN = ("exudyn", {})
PINOCCHIO = ("pinocchio", {})

# scene → horizon, the generator that writes the reference, those that check it.
SUITE = {
    "fourbar": (5.0, IDA, [PINOCCHIO, EXUDYN]),
    "fourbar-theta": (5.0, IDA, [EXUDYN]),
    "pendulum": (5.0, IDA, [PINOCCHIO]),
    "double-pendulum": (5.0, IDA, [PINOCCHIO]),
    "spring-damper": (5.0, IDA, [EXUDYN]),
    "slider-crank": (5.0, IDA, [EXUDYN]),
    "slotted-lever": (5.0, IDA, [EXUDYN]),
    # Falls into a singular configuration after ~1.3 s: the reference stops before.
    # IDA's corrector fails at rtol ≤ 1e-13 on this 22-coordinate model (t ≈ 0.3 s).
    "pick-and-place": (1.0, ("ida", {"rtol": 1e-12}), [PINOCCHIO]),
    "pick-and-place-mbse": (1.0, ("ida", {"rtol": 1e-12}), [PINOCCHIO]),
    # Hard cases with a reference (the parallelogram's is its exact motion, and IDA
    # fails at its first flat configuration).
    "hard/slider-crank-dead-centres": (5.0, IDA, [EXUDYN]),
    "hard/stiff-spring": (5.0, IDA, [EXUDYN]),
    "hard/redundant-fourbar": (5.0, IDA, [PINOCCHIO]),
    "hard/fourbar-lower-branch": (5.0, IDA, [EXUDYN]),
    # The published benchmark's 0.03 s (docs/benchmarks.md): past it the motor keeps
    # speeding the crank up, to ~10⁴ rad/s by 0.4 s. IDA at rtol 1e-12 agrees with the
    # published end angles to 5e-9 rad; tighter tolerances stop before 0.03 s.
    "benchmarks/andrews-squeezer": (0.03, ("ida", {"rtol": 1e-12}), []),
}


@dataclasses.dataclass
class Job:
    """One reference to write: a scene of the suite or any scene file."""
    label: str
    scene: pathlib.Path
    t_end: float
    primary: tuple[str, dict]
    checks: list[tuple[str, dict]]
    out: pathlib.Path                  # where the reference lives
    quick_checks: bool = False         # cross-checks at their fast defaults


def suite_job(name: str) -> Job:
    t_end, primary, checks = SUITE[name]
    return Job(name, ROOT / "scenes" / f"{name}.yaml", t_end, primary, checks,
               REFERENCES / name)


def suite_name(path: pathlib.Path) -> str | None:
    """The suite's name of a scene file, if it is one of the suite's."""
    for name in SUITE:
        if (ROOT / "scenes" / f"{name}.yaml").resolve() == path.resolve():
            return name
    return None


def scene_file(arg: str) -> pathlib.Path | None:
    """A scene argument as a file: as given, or with .yaml added."""
    for p in (pathlib.Path(arg), pathlib.Path(arg + ".yaml")):
        if p.is_file():
            return p
    return None


def default_out(scene: pathlib.Path) -> pathlib.Path:
    """my-scene.yaml → my-scene.reference/ beside it."""
    return scene.with_name(scene.name.removesuffix(".yaml") + ".reference")


def point_columns(model: mbfg.Model) -> list[int]:
    """Indices in q of the free points' x and y (the coordinates RMSE is taken over)."""
    out = []
    for p in model.points:
        if p["index"] is not None:
            out += [p["index"], p["index"] + 1]
    return out


def point_errors(model: mbfg.Model, t: np.ndarray, q: np.ndarray, truth: tj.Trajectory):
    """(RMSE, max) of the moving points' x, y against `truth`, at the times of t that
    fall on truth's samples (every run is compared this way)."""
    step = truth.t[1] - truth.t[0]
    k = np.rint(t / step).astype(int)
    on_grid = (np.abs(k * step - t) < 1e-9) & (k < len(truth.t))
    if not np.any(on_grid):
        raise ValueError("no common samples with the reference")
    cols = point_columns(model)
    d = q[on_grid][:, cols] - truth.q[k[on_grid]][:, cols]
    return float(np.sqrt(np.mean(d ** 2))), float(np.max(np.abs(d)))


def disagreement(model: mbfg.Model, a: tj.Trajectory, b: tj.Trajectory) -> dict:
    """Max and RMSE difference of the point coordinates of two references."""
    if len(a.t) != len(b.t) or np.max(np.abs(a.t - b.t)) > 1e-9:
        raise ValueError("the two trajectories are not sampled at the same times")
    rmse, mx = point_errors(model, b.t, b.q, a)
    return {"max_m": mx, "rmse_m": rmse}


class GeneratorFailed(RuntimeError):
    """The primary generator refused or failed: no reference."""


def run(generator: tuple[str, dict], scene: pathlib.Path, t_end: float, quick: bool = False):
    """(trajectory, provenance, wall time) of one generator at its reference settings
    (its fast defaults with quick) updated by the tuple's."""
    name, settings = generator
    gen = generators.get(name)
    why = gen.refusal(mbfg.load(str(scene)))
    if why:
        raise tj.Unsupported(why)
    start = time.perf_counter()
    traj, prov = gen.generate(scene, t_end, SAMPLE_DT, settings, accurate=not quick)
    return traj, prov, time.perf_counter() - start


def request(generator: tuple[str, dict], quick: bool = False) -> dict:
    """What `make reference` asks of a generator for a job (run at its reference
    settings, or its fast defaults with quick): recorded in the provenance, and checked
    against today's by the tests."""
    return generators.get(generator[0]).request(generator[1], accurate=not quick)


def label(generator: tuple[str, dict]) -> str:
    return generator[0] + (f" {generator[1]}" if generator[1] else "")


def portable(path: pathlib.Path):
    """A scene path as a task carries it: relative to the repository when inside it (a
    worker resolves it in its own checkout), else as it is."""
    try:
        return ("repo", path.resolve().relative_to(ROOT).as_posix())
    except ValueError:
        return ("path", str(path))


def produce(task: tuple) -> dict:
    """One generator's run of a job, a task of a sweep: (generator, portable scene path,
    t_end, quick) → {"run": (trajectory, provenance, wall time)}, {"refused": why} or
    {"failed": why}."""
    generator, (kind, where), t_end, quick = task
    scene = ROOT / where if kind == "repo" else pathlib.Path(where)
    try:
        return {"run": run(generator, scene, t_end, quick)}
    except tj.Unsupported as e:
        return {"refused": str(e)}
    except Exception as e:  # noqa: BLE001 (reported with the job)
        return {"failed": generators.one_line(e)}


def tasks_of(job: Job) -> list[tuple]:
    """The runs of a job: its primary generator's, then each cross-check's."""
    scene = portable(job.scene)
    return ([(job.primary, scene, job.t_end, False)]
            + [(check, scene, job.t_end, job.quick_checks) for check in job.checks])


def generate(job: Job | str, out_dir: pathlib.Path | None = None, runs: list[dict] | None = None) -> dict:
    """Writes one reference and its provenance into out_dir (default: the job's);
    returns the provenance. A suite name stands for its job. `runs`: the results of
    produce for tasks_of(job), if they were run elsewhere (generate_all)."""
    if isinstance(job, str):
        job = suite_job(job)
    out_dir = job.out if out_dir is None else out_dir
    if runs is None:
        runs = [produce(task) for task in tasks_of(job)]
    name, scene, t_end, primary = job.label, job.scene, job.t_end, job.primary
    model = mbfg.load(str(scene))
    print(f"{name}: {label(primary)} over {t_end} s …", flush=True)
    first = runs[0]
    if "run" not in first:  # refused or failed: one line, no reference
        why = " ".join((first.get("refused") or first.get("failed")).split())[:300]
        raise GeneratorFailed(f"{name}: {primary[0]} cannot make the reference: {why} (another "
                              "--generator, or looser settings with --set, may)")
    truth, prov, wall = first["run"]
    print(f"{name}:   done in {wall:.1f} s", flush=True)
    prov["request"] = request(primary)
    prov["cross_checks"] = []
    for check, result in zip(job.checks, runs[1:]):
        print(f"{name}:   cross-check with {label(check)} …", flush=True)
        if "refused" in result:
            prov["cross_checks"].append({"generator": check[0], "refused": result["refused"],
                                         "request": request(check, job.quick_checks)})
            print(f"{name}:   {check[0]} refuses the scene: {result['refused']}", flush=True)
            continue
        try:
            if "failed" in result:
                raise RuntimeError(result["failed"])
            other, other_prov, other_wall = result["run"]
            diff = disagreement(model, truth, other)
            prov["cross_checks"].append({
                "generator": other_prov.get("generator", check[0]),
                "formulation": other_prov.get("formulation"),
                "settings": other_prov.get("settings", check[1]),
                "request": request(check, job.quick_checks),
                "versions": other_prov.get("versions", {}),
                "wall_time_s": other_wall, **diff})
            print(f"{name}:   done in {other_wall:.1f} s; disagreement max {diff['max_m']:.2e} m, "
                  f"RMSE {diff['rmse_m']:.2e} m", flush=True)
        except Exception as e:  # a cross-check's failure is recorded, not fatal
            prov["cross_checks"].append({"generator": check[0],
                                         "failed": generators.one_line(e),
                                         "request": request(check, job.quick_checks)})
            print(f"{name}:   {check[0]} failed: {generators.one_line(e)}", flush=True)
    prov["sample_dt"] = SAMPLE_DT
    prov["t_end"] = t_end
    out_dir.mkdir(parents=True, exist_ok=True)
    tj.write(out_dir / "reference.csv.gz", truth)
    tj.write_provenance(out_dir / "provenance.json", prov)
    return prov


def generate_all(jobs: list[Job], sweep=None, out_dirs: list | None = None) -> list[dict]:
    """generate for every job, their generators' runs as the cells of `sweep`
    (harness/sweep.py; None: in this process), written in the jobs' order."""
    tasks = [tasks_of(job) for job in jobs]
    flat = [t for ts in tasks for t in ts]
    done = (sweep.map(produce, flat, "references") if sweep is not None
            else [produce(t) for t in flat])
    out, k = [], 0
    for job, ts, out_dir in zip(jobs, tasks, out_dirs or [None] * len(jobs)):
        out.append(generate(job, out_dir, done[k:k + len(ts)]))
        k += len(ts)
    return out


def check(jobs: list[Job | str], sweep=None) -> int:
    """Regenerates into a temporary folder and compares with the stored references."""
    bad = 0
    jobs = [suite_job(job) if isinstance(job, str) else job for job in jobs]
    with tempfile.TemporaryDirectory() as tmp:
        fresh_dirs = [pathlib.Path(tmp) / job.label.replace("/", "_") for job in jobs]
        generate_all(jobs, sweep, fresh_dirs)
        for job, fresh_dir in zip(jobs, fresh_dirs):
            committed = tj.read(job.out / "reference.csv.gz")
            stated = json.loads((job.out / "provenance.json").read_text())
            fresh = tj.read(fresh_dir / "reference.csv.gz")
            model = mbfg.load(str(job.scene))
            if len(fresh.t) != len(committed.t):
                print(f"{job.label}: fresh has {len(fresh.t)} samples, the stored one "
                      f"{len(committed.t)} (another --t-end?): DIFFERS")
                bad += 1
                continue
            diff = disagreement(model, committed, fresh)
            tol = tolerance(stated)
            ok = diff["max_m"] <= tol
            if not tj.is_current(stated, job.scene):
                print(f"{job.label}: the scene's files changed since the stored reference was written")
            bad += not ok
            print(f"{job.label}: fresh vs stored max {diff['max_m']:.2e} m "
                  f"(stated tolerance {tol:.1e}): {'ok' if ok else 'DIFFERS'}")
    return bad


def tolerance(prov: dict) -> float:
    """What a reference claims: its closest cross-check's disagreement, at least 1e-10 m."""
    found = [c["max_m"] for c in prov.get("cross_checks", []) if "max_m" in c]
    return max(min(found, default=1e-10), 1e-10)


def tool_list(text: str, ap: argparse.ArgumentParser) -> list[str]:
    names = [n.strip() for n in text.split(",") if n.strip()]
    for n in names:
        if n not in generators.REGISTRY:
            ap.error(f"unknown generator {n!r}; registered: {', '.join(generators.REGISTRY)}")
    return names


def jobs_from(args, ap: argparse.ArgumentParser) -> list[Job]:
    try:
        settings = generators.parse_settings(args.set)
    except ValueError as e:
        ap.error(f"--set: {e}")
    if args.t_end is not None and (round(args.t_end / SAMPLE_DT) < 1 or
                                   abs(round(args.t_end / SAMPLE_DT) * SAMPLE_DT - args.t_end) > 1e-9):
        ap.error(f"--t-end must be a positive multiple of {SAMPLE_DT} s")
    other_settings = (args.t_end is not None or args.generator or args.checks is not None
                      or args.set or args.quick)
    jobs = []
    for arg in args.scenes or list(SUITE):
        name, path = (arg, None) if arg in SUITE else (None, scene_file(arg))
        if name is None:
            if path is None:
                ap.error(f"unknown scene {arg!r}: neither a scene of the suite "
                         f"({', '.join(SUITE)}) nor a scene file")
            name = suite_name(path)
        if name is not None:
            job = suite_job(name)
            if other_settings and args.out is None and not args.check:
                # The committed references are made with the suite's settings only.
                ap.error(f"{arg} is a scene of the suite: its reference in references/ takes "
                         "the suite's settings; give --out DIR to write one with others")
        else:
            job = Job(path.name.removesuffix(".yaml"), path, 5.0, ("ida", {}), [],
                      default_out(path))
            job.checks = [(g.name, {}) for g in generators.REGISTRY.values() if g.accuracy > 0]
        if args.t_end is not None:
            job.t_end = args.t_end
        if args.generator:
            job.primary = (args.generator, {})
        if settings:
            job.primary = (job.primary[0], {**job.primary[1], **settings})
        if args.checks is not None:
            job.checks = [(c, {}) for c in tool_list(args.checks, ap)]
        job.checks = [c for c in job.checks if c[0] != job.primary[0]]
        job.quick_checks = args.quick
        if args.out is not None:
            job.out = args.out
        jobs.append(job)
    if args.out is not None and len(jobs) > 1:
        ap.error("--out takes one scene")
    return jobs


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(
        prog="python -m harness.reference", description=__doc__.split("\n\n")[0],
        formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog="A scene outside the suite gets --t-end (default 5 s), the primary generator "
               "(--generator, default ida at its reference settings) and cross-checks by every "
               "other registered simulator that models it (--checks). Options for scenes outside "
               "the suite: --t-end, --out, --generator, --checks, --set, --quick.")
    ap.add_argument("scenes", nargs="*", metavar="SCENE",
                    help=f"a scene of the suite ({', '.join(SUITE)}; default: all) or a path "
                    "to a scene file")
    ap.add_argument("--check", action="store_true",
                    help="regenerate into a temporary folder and compare with the stored ones")
    ap.add_argument("--t-end", type=float, help="horizon in s (scenes outside the suite; default 5)")
    ap.add_argument("--out", type=pathlib.Path,
                    help="folder of the reference (default: SCENE.reference/ beside the scene file)")
    ap.add_argument("--generator", metavar="NAME",
                    help=f"the generator that writes it (default ida; one of {', '.join(generators.REGISTRY)})")
    ap.add_argument("--checks", metavar="A,B",
                    help="cross-checking generators (default: every other registered one but mbfg; '' for none)")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="a setting of the primary generator over its reference settings, e.g. rtol=1e-12")
    ap.add_argument("--quick", action="store_true",
                    help="cross-checks at their fast defaults instead of their reference settings")
    sweeps.add_argument(ap)
    args = ap.parse_args(argv)
    if args.generator:
        tool_list(args.generator, ap)
    jobs = jobs_from(args, ap)
    start = time.perf_counter()
    if args.check:
        missing = [j for j in jobs if not (j.out / "reference.csv.gz").is_file()]
        if missing:
            print(f"reference: no stored reference to check at {missing[0].out} "
                  "(make one without --check first)", file=sys.stderr)
            return 2
    # Every generator's run of every job is a cell of one sweep (harness/sweep.py).
    try:
        with sweeps.from_args(args) as sweep:
            if args.check:
                bad = check(jobs, sweep)
                print(f"{len(jobs) - bad} of {len(jobs)} references reproduced "
                      f"in {time.perf_counter() - start:.0f} s")
                return 1 if bad else 0
            tasks = [tasks_of(job) for job in jobs]
            flat = [t for ts in tasks for t in ts]
            done = sweep.map(produce, flat, "references")
        k = 0
        for job, ts in zip(jobs, tasks):
            generate(job, runs=done[k:k + len(ts)])
            k += len(ts)
            print(f"{job.label}: wrote {tj.display_path(job.out)}/reference.csv.gz, provenance.json")
    except (GeneratorFailed, mbfg.SceneError) as e:
        print(f"reference: {generators.one_line(e)}", file=sys.stderr)
        return 1
    print(f"wrote {len(jobs)} references in {time.perf_counter() - start:.0f} s")
    return 0


if __name__ == "__main__":
    # As harness.reference, not __main__: the sweep's tasks name its functions, which the
    # Dask scheduler and workers import.
    from harness import reference
    sys.exit(reference.main())
