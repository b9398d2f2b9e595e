"""The snippets users copy from README.md and docs/ run as printed: every ```python
block (in a fresh interpreter, from the repository's root), every `$ mbfg …` command
line (with its output file moved to a temporary directory), and the scene format's
complete example (through `mbfg check` and a short run). A block preceded by the
comment `<!-- snippet: not run (why) -->` is skipped, and says why. A python block
followed by a line `prints:` and a ```text block must print exactly that."""

import pathlib
import re
import shlex
import subprocess
import sys

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[2]
MBFG = ROOT / "target/release/mbfg"
DOCS = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
SKIP = "<!-- snippet: not run"


def printed_after(lines, end):
    """The ```text block after `prints:` that follows line `end` (a block's closing
    fence), or None."""
    rest = [line for line in lines[end + 1:end + 4]]
    if len(rest) < 3 or rest[0].strip() or rest[1].strip() != "prints:":
        return None
    start = end + 3
    while start < len(lines) and not lines[start].strip():
        start += 1
    if start >= len(lines) or lines[start].strip() != "```text":
        return None
    stop = start + 1
    while stop < len(lines) and lines[stop].strip() != "```":
        stop += 1
    return "\n".join(lines[start + 1:stop])


def blocks(lang):
    """(file, line, code, printed) of every fenced block in `lang` not marked as not
    run; `printed` is what it must print, or None."""
    out = []
    for doc in DOCS:
        lines = doc.read_text().splitlines()
        i = 0
        while i < len(lines):
            if lines[i].strip() == f"```{lang}":
                start = i
                j = i + 1
                while j < len(lines) and lines[j].strip() != "```":
                    j += 1
                marked = start > 0 and lines[start - 1].startswith(SKIP)
                if not marked:
                    out.append((doc.relative_to(ROOT), start + 1, "\n".join(lines[i + 1:j]),
                                printed_after(lines, j)))
                i = j
            i += 1
    return out


def commands():
    """(file, line, argv) of every `$ mbfg …` line."""
    out = []
    for doc in DOCS:
        for n, line in enumerate(doc.read_text().splitlines(), 1):
            if line.startswith("$ mbfg "):
                out.append((doc.relative_to(ROOT), n, shlex.split(line[2:])))
    return out


PYTHON = blocks("python")
COMMANDS = commands()


def test_the_docs_hold_snippets():
    assert len(PYTHON) >= 3 and len(COMMANDS) >= 3


def workdir(tmp_path):
    """A folder that looks like the repository's root to a snippet (its data folders
    linked in), so that what a snippet writes lands outside the repository."""
    tmp_path.mkdir(parents=True, exist_ok=True)
    for name in ("scenes", "examples", "harness", "references", "tests", "target"):
        (tmp_path / name).symlink_to(ROOT / name)
    return tmp_path


@pytest.mark.parametrize("doc, line, code, printed", PYTHON,
                         ids=[f"{d}:{n}" for d, n, _, _ in PYTHON])
def test_python_snippet_runs(doc, line, code, printed, tmp_path):
    r = subprocess.run([sys.executable, "-c", code], cwd=workdir(tmp_path), capture_output=True,
                       text=True, timeout=120)
    assert r.returncode == 0, f"{doc}:{line}:\n{r.stderr[-2000:]}"
    if printed is not None:
        assert r.stdout.strip() == printed.strip(), f"{doc}:{line}: the page says it prints"


def test_a_printed_output_is_found():
    assert any(printed for _, _, _, printed in PYTHON)


@pytest.mark.parametrize("doc, line, argv", COMMANDS, ids=[f"{d}:{n}" for d, n, _ in COMMANDS])
def test_command_runs(doc, line, argv, tmp_path):
    argv = [str(MBFG), *argv[1:]]
    if "--out" in argv:
        i = argv.index("--out") + 1
        argv[i] = str(tmp_path / pathlib.Path(argv[i]).name)
    r = subprocess.run(argv, cwd=workdir(tmp_path / "root"), capture_output=True, text=True,
                       timeout=120)
    assert r.returncode == 0, f"{doc}:{line}: {' '.join(argv)}\n{r.stderr[-2000:]}"


def test_the_complete_scene_example_checks_and_runs(tmp_path):
    text = (ROOT / "docs/scene-format.md").read_text()
    section = text[text.index("## 11. A complete example"):]
    example = re.search(r"```yaml\n(.*?)```", section, re.S).group(1)
    scene = tmp_path / "example.yaml"
    scene.write_text(example)
    for argv in (["check", str(scene)],
                 ["simulate", str(scene), "--dt", "1e-3", "--t-end", "0.5"]):
        r = subprocess.run([str(MBFG), *argv], capture_output=True, text=True, timeout=120)
        assert r.returncode == 0, f"{argv}: {r.stderr[-1000:]}"
