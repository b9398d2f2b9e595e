"""What every page of reports/ shares: the paths, the progress line, the committed
references and the point errors against them, the CSV writer and the machine line.
`harness.report` writes the pages with them, `harness.timing` and
`harness.robustness` theirs."""
from __future__ import annotations

import csv
import json
import pathlib
import sys

from harness import reference as refs
from harness.sweep import machine  # noqa: F401 (the pages' machine line)
from harness import trajectory as tj

ROOT = pathlib.Path(__file__).resolve().parent.parent
REPORTS = ROOT / "reports"


def progress(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


def scene_path(name: str) -> pathlib.Path:
    return ROOT / "scenes" / f"{name}.yaml"


def load_reference(name: str) -> tuple[tj.Trajectory, dict]:
    folder = ROOT / "references" / name
    return (tj.read(folder / "reference.csv.gz"),
            json.loads((folder / "provenance.json").read_text()))


errors = refs.point_errors


def window_kw(w) -> dict:
    return {"batch": True} if w == "batch" else {"window": w}


def write_csv(path: pathlib.Path, rows: list[dict]) -> None:
    keys = list(dict.fromkeys(k for r in rows for k in r))  # every key, in first-seen order
    with open(path, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=keys)
        w.writeheader()
        w.writerows(rows)


