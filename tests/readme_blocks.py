"""The command blocks of the README and of the documentation's pages, read for tests/test_readme*.py.

Every ``bash`` block of README.md and docs/*.md runs as written from a clone's root, each command
line ending with a comment ``# exit N: ...``: its exit status, then what it prints. The tests run
each line and compare both: the status, and every number the comment quotes against the numbers
the command printed (:func:`figure_problems`).

Three test files share the blocks so that pytest-xdist (``--dist loadfile``, a file to a worker)
can run the long ones (the design cycles, the calibration) on other workers than the rest.
"""

from __future__ import annotations

import os
import re
import shlex
import shutil
import subprocess
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
EXIT = re.compile(r"#.*?\bexit (\d+)\b")
INSTALL = re.compile(r"^(pip install [^&]*|tools/install_system_deps\.sh)\s*&&\s*")
#: A number as a comment quotes it or a command prints it; not the 2 of R^2, nor digits inside a
#: word (a file name's date, a flag such as --rerun-episodes).
NUMBER = re.compile(r"(?<![\w^])[-+]?\d+(?:\.\d+)?(?:[eE][-+]?\d+)?(?![\w])")
#: The documents whose blocks are run: the README first (its first block holds the test command
#: that .ci/run runs), then the documentation's pages.
DOCUMENTS = [REPO / "README.md", *sorted((REPO / "docs").glob("*.md"))]


def bash_blocks(text: str) -> list[list[tuple[int, str]]]:
    """A Markdown text's ``bash`` blocks: lists of (line number, command line), continuations joined."""
    blocks, current, pending = [], None, ""
    for number, line in enumerate(text.splitlines(), start=1):
        if current is None:
            if line.strip() == "```bash":
                current = []
            continue
        if line.strip() == "```":
            blocks.append(current)
            current = None
            continue
        if line.rstrip().endswith("\\"):
            pending += line.rstrip()[:-1] + " "
            continue
        if (pending + line).strip():
            current.append((number, pending + line))
        pending = ""
    return blocks


def markdown_blocks(path: Path) -> list[list[tuple[int, str]]]:
    """The ``bash`` blocks of the Markdown file ``path``."""
    return bash_blocks(path.read_text())


def expected_exit(line: str) -> int | None:
    match = EXIT.search(line)
    return None if match is None else int(match.group(1))


def quoted_text(line: str) -> str:
    """What a command line's comment says after its ``exit N``: the output it quotes."""
    match = EXIT.search(line)
    return "" if match is None else line[match.end() :]


def runnable(line: str) -> str | None:
    """The part of a block's line that the test runs (None: the suite's own command)."""
    command = line
    while INSTALL.match(command):
        command = INSTALL.sub("", command, count=1)
    return None if command.lstrip().startswith("python -m pytest") else command


def _unit(text: str) -> float:
    """One unit in the last digit of a number as written: 1 for 48, 1e-4 for 0.9633, 1e-6 for 5.848e-03."""
    mantissa, _, exponent = text.lower().partition("e")
    decimals = len(mantissa.partition(".")[2])
    return 10.0 ** (int(exponent or 0) - decimals)


def _is_count(text: str) -> bool:
    return "." not in text and "e" not in text.lower()


def figure_matches(quoted: str, printed: str) -> bool:
    """Whether a number a comment quotes is one a command printed.

    A count (an integer) must be printed as the same integer. A decimal figure must be quoted no
    finer than printed, and within one unit of its last quoted digit of the printed value: 0.9633
    or 0.963 for a printed 0.9633, not 0.973; -60.4 for a printed -60.4.
    """
    if _is_count(quoted):
        return _is_count(printed) and int(quoted) == int(printed)
    unit = _unit(quoted)
    return _unit(printed) <= unit * (1 + 1e-9) and abs(float(quoted) - float(printed)) <= unit * (1 + 1e-9)


def figure_problems(line: str, output: str) -> list[str]:
    """The numbers ``line``'s comment quotes that ``output`` does not print (see :func:`figure_matches`)."""
    printed = NUMBER.findall(output)
    return [
        quoted
        for quoted in NUMBER.findall(quoted_text(line))
        if not any(figure_matches(quoted, number) for number in printed)
    ]


def _all_blocks() -> tuple[list[list[tuple[int, str]]], list[Path]]:
    blocks, sources = [], []
    for document in DOCUMENTS:
        for block in markdown_blocks(document):
            blocks.append(block)
            sources.append(document)
    return blocks, sources


#: Every block of every document, the README's first; BLOCK_SOURCES[i] is the file of BLOCKS[i].
BLOCKS, BLOCK_SOURCES = _all_blocks()


def blocks_running(command: str) -> list[int]:
    """The indices of the blocks with a line that runs ``command``."""
    return [i for i, block in enumerate(BLOCKS) if any(command in line for _, line in block)]


def blocks_of(path: Path) -> list[int]:
    """The indices of the blocks of the document ``path``."""
    return [i for i, source in enumerate(BLOCK_SOURCES) if source == path]


#: Commands whose blocks are long and tested in files of their own (tests/test_readme_<name>.py).
OWN_FILES = ("qube-design", "qube-calibrate")
#: The other blocks (tests/docs/test_readme.py).
OTHER_BLOCKS = [i for i in range(len(BLOCKS)) if not any(i in blocks_running(c) for c in OWN_FILES)]


def block_id(index: int) -> str:
    """A test id naming the block's file, the block and its first line."""
    source = BLOCK_SOURCES[index]
    number = blocks_of(source).index(index) + 1
    return f"{source.relative_to(REPO)}-block{number}-line{BLOCKS[index][0][0]}"


@pytest.fixture
def clone(tmp_path, qube_dataset, monkeypatch, tmp_path_factory):
    """A fresh folder to work in, as a clone's root; the paper's dataset named by $QUBE_DATASET_DIR,
    as the documentation's commands read it."""
    monkeypatch.setenv("QUBE_DATASET_DIR", str(qube_dataset.resolve()))
    if not _IMPORT_CACHE:  # where this worker keeps the folders of its real imports (run_block)
        _IMPORT_CACHE[None] = tmp_path_factory.mktemp("readme-imports")
    (tmp_path / "main").mkdir()
    return tmp_path / "main"


#: This worker's runs of the dataset's import: (the command's words, the dataset's files) -> (the
#: command's result, the folder it wrote), and under None the folder that keeps those folders.
#: Several pages start their block with the same ``qube-import "$QUBE_DATASET_DIR"/*.csv --out
#: qube_logs`` (6 s each on the 48 files), which the suite ran again for each block. Within one
#: worker (pytest-xdist gives each its own process, so each its own cache) the first block runs it;
#: a later block with the same words on the same files gets a copy of the folder it wrote, and its
#: line is checked as written against the exit status and output that run printed. Every worker
#: that runs such a block still runs the import once, and a block whose output folder exists, or
#: that reads anything but $QUBE_DATASET_DIR, runs it as written.
_IMPORT_CACHE: dict = {}
_IMPORT = re.compile(r"qube-import\s")


def _import_key(command: str, clone: Path) -> tuple | None:
    """The cache key of a ``qube-import`` of the dataset into a fresh folder, or None: run it."""
    if not _IMPORT.match(command.lstrip()):
        return None
    words = shlex.split(command, comments=True)
    if any(c in command.split("#")[0] for c in ";&|<>`()") or words.count("--out") != 1:
        return None
    out = words[words.index("--out") + 1]
    sources = [w for w in words[1:] if w not in ("--out", out)]
    if (
        not re.fullmatch(r"[\w.-]+", out)
        or (clone / out).exists()
        or not sources
        or not all(w.startswith("$QUBE_DATASET_DIR/") for w in sources)
    ):
        return None
    dataset = Path(os.environ["QUBE_DATASET_DIR"])
    files = tuple((p.name, p.stat().st_size, p.stat().st_mtime_ns) for p in sorted(dataset.iterdir()))
    return (tuple(words), str(dataset), files)


def _run(command: str, clone: Path, env: dict) -> subprocess.CompletedProcess:
    """Run one line in ``clone`` (a repeated import of the dataset from this worker's cache: above)."""
    key = _import_key(command, clone) if None in _IMPORT_CACHE else None
    if key is not None and key in _IMPORT_CACHE:
        done, folder = _IMPORT_CACHE[key]
        if folder is not None:
            shutil.copytree(folder, clone / folder.name)
        return done
    done = subprocess.run(
        ["bash", "-c", command],
        check=False,
        cwd=clone,
        env=env,
        capture_output=True,
        text=True,
        timeout=600,
        stdin=subprocess.DEVNULL,
    )
    if key is not None:
        out = key[0][key[0].index("--out") + 1]
        kept = None
        if (clone / out).is_dir():
            kept = _IMPORT_CACHE[None] / str(len(_IMPORT_CACHE)) / out
            shutil.copytree(clone / out, kept)
        _IMPORT_CACHE[key] = (done, kept)
    return done


def run_block(index: int, clone: Path) -> None:
    """Run block ``index`` line by line in ``clone``; each line must exit as its comment shows and
    print every number the comment quotes."""
    env = {**os.environ, "PYTHONWARNINGS": "ignore"}
    where = BLOCK_SOURCES[index].relative_to(REPO)
    for number, line in BLOCKS[index]:
        command = runnable(line)
        if command is None:
            continue
        done = _run(command, clone, env)
        shown = f"\n--- stdout\n{done.stdout[-3000:]}\n--- stderr\n{done.stderr[-3000:]}"
        assert done.returncode == expected_exit(line), (
            f"{where} line {number}: {command!r} exited {done.returncode}, the text shows {expected_exit(line)}{shown}"
        )
        missing = figure_problems(line, done.stdout + done.stderr)
        assert not missing, (
            f"{where} line {number}: its comment quotes {missing}, which {command.split()[0]} did not print "
            f"(a count exactly, a decimal to one unit of its last quoted digit){shown}"
        )
