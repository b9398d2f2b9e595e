"""The `mbfg` command that `pip install mbfg` puts on the PATH. The command line is a
Rust program that a wheel does not carry: this runs the installed one (`$MBFG`, the
first `mbfg` executable on the PATH that is a compiled program, or the checkout's
`target/release/mbfg` when the module is a checkout's), and where there is none, says
how to build it."""
from __future__ import annotations

import os
import pathlib
import shutil
import sys

HOW = ("mbfg: the command-line tool is not installed (pip installs the Python module "
       "only). From a checkout of the repository: `make install` (to ~/.local/bin) or "
       "`cargo install --path .`; or set MBFG to the binary's path.")


def _compiled(path: str) -> bool:
    """An executable that is not a script (a script may be another copy of this one)."""
    try:
        with open(path, "rb") as f:
            return f.read(2) != b"#!"
    except OSError:
        return False


def find() -> str | None:
    """The compiled mbfg this command runs, or None."""
    named = os.environ.get("MBFG")
    if named and os.access(named, os.X_OK) and _compiled(named):
        return named
    for folder in os.environ.get("PATH", "").split(os.pathsep):
        candidate = shutil.which("mbfg", path=folder) if folder else None
        if candidate and _compiled(candidate):
            return candidate
    # The module of a checkout (`make python`): that checkout's `make build`.
    checkout = pathlib.Path(__file__).resolve().parents[2]
    built = checkout / "target" / "release" / "mbfg"
    if (checkout / "Cargo.toml").exists() and os.access(built, os.X_OK):
        return str(built)
    return None


def main() -> int:
    exe = find()
    if exe is None:
        print(HOW, file=sys.stderr)
        return 2
    os.execv(exe, [exe, *sys.argv[1:]])
    return 0  # not reached


if __name__ == "__main__":
    sys.exit(main())
