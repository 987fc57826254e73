"""The documentation site builds without a warning, covers the API, and its examples run; the text a
user reads names no tracker issue and no file outside the repository.

The build is the one a user runs (docs/conf.py; the development page): Sphinx, warnings as
errors, one process, no network. The API reference is generated, so the test checks it against
the packages' public names as tests/project/test_package.py counts them (tests/_public_api.py). Every
``>>>`` example of every docstring, private modules included, runs as a doctest through the
standard library's doctest (what pytest's --doctest-modules runs, here in-process on the
installed ``qube_koopman.*`` modules: no second interpreter, no import by file path).
"""

from __future__ import annotations

import json
import logging
import re
import subprocess
import sys
from pathlib import Path

import pytest
from _public_api import public_names

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "docs" / "_ext"))
import readme_slices  # the docs' own extension, docs/_ext

PAGES = [
    "index",
    "getting-started",
    "collecting",
    "identification",
    "transfer",
    "lifting-search",
    "cluster",
    "calibration",
    "design",
    "formats",
    "NAMING",
    "daq/log/FORMAT",
    "core/CONTROLLER_FORMAT",
    "identify/MODEL_FORMAT",
    "firmware_protocol/PROTOCOL",
    "api/index",
    "development",
]


README = """# Title

- `cmd-a ARGS`: first item,
  continued; see [the codec](firmware_protocol/frame.py) and [LICENSE](LICENSE).
  - `--flag`: a nested item
    over two lines.
- `cmd-b`: the next item.
"""


def test_a_readme_slice_is_whole_lines_from_its_start_marker_to_its_end_marker():
    text = readme_slices.expand('intro\n% readme "  - `--flag`" "- `cmd-b`"\noutro\n', README, "page")
    assert text == "intro\n- `--flag`: a nested item\n  over two lines.\n\noutro\n"
    whole = readme_slices.readme_slice(README, "- `cmd-a", "", "page")
    assert whole.startswith("- `cmd-a ARGS`") and whole.endswith("the next item.\n")
    assert "{py:mod}`the codec <qube_koopman.firmware_protocol.frame>`" in whole
    assert "{download}`LICENSE </../LICENSE>`" in whole


@pytest.mark.parametrize(
    "start, end, problem",
    [("no such text", "", "not found"), ("item", "", "not unique"), ("- `cmd-a", "no such end", "not found after")],
)
def test_a_readme_marker_that_does_not_fit_is_a_warning(start, end, problem, caplog):
    with caplog.at_level(logging.WARNING):
        assert readme_slices.readme_slice(README, start, end, "page") == ""
    assert "page: README marker" in caplog.text and problem in caplog.text


@pytest.fixture(scope="module")
def built_docs(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("docs") / "html"
    done = subprocess.run(
        [
            sys.executable,
            "-m",
            "sphinx",
            "-W",
            "--keep-going",
            "-b",
            "html",
            "-j",
            "1",
            "-q",
            str(ROOT / "docs"),
            str(out),
        ],
        check=False,
        capture_output=True,
        text=True,
        timeout=600,
        stdin=subprocess.DEVNULL,
    )
    assert done.returncode == 0, f"sphinx-build failed:\n{done.stdout[-3000:]}\n{done.stderr[-6000:]}"
    return out


@pytest.mark.slow
def test_the_docs_build_without_warnings_and_have_every_page(built_docs):
    missing = [page for page in PAGES if not (built_docs / f"{page}.html").is_file()]
    assert not missing
    # the README's sections and the format documents were pulled in, not left as markers
    for page in PAGES:
        text = (built_docs / f"{page}.html").read_text()
        assert "% readme" not in text and "{include}" not in text, page
    assert "chip select (SS)" in (built_docs / "collecting.html").read_text()  # the wiring table
    assert "Episode log format" in (built_docs / "daq/log/FORMAT.html").read_text()


@pytest.mark.slow
def test_every_public_name_is_in_the_api_reference(built_docs):
    anchors = set()
    for page in (built_docs / "api" / "generated").glob("*.html"):
        anchors |= set(re.findall(r'id="([^"]+)"', page.read_text()))
    names = [name for name, _ in public_names()]
    assert len(names) > 300
    missing = [name for name in names if name not in anchors]
    assert not missing, f"not in the API reference: {missing}"


@pytest.mark.slow
def test_each_package_page_lists_the_names_the_package_exports(built_docs):
    """The public API is package-level (``from qube_koopman.daq import read_episode``): each package's
    page links every function and class of its ``__all__`` to where it is described."""
    import importlib
    import inspect

    from _public_api import PACKAGES

    missing = []
    for package in PACKAGES:
        module = importlib.import_module(package)
        page = (built_docs / "api" / "generated" / f"{package}.html").read_text()
        missing += [
            f"{package}.{name}"
            for name in module.__all__
            if (inspect.isclass(obj := getattr(module, name)) or inspect.isfunction(obj))
            and f'href="{obj.__module__}.html#{obj.__module__}.{obj.__qualname__}"' not in page
        ]
    assert not missing, f"not linked from their package's page: {missing}"


# Run in a fresh interpreter outside the checkout (-P, another working folder), so an example
# can import only what a user's install provides: `from firmware_protocol import ...` would
# pass from the repository's root and fail for every user.
DOCTESTS = """
import doctest, json, sys
sys.path.insert(0, sys.argv[1])
from _public_api import all_modules
finder = doctest.DocTestFinder()
runner = doctest.DocTestRunner(verbose=False, optionflags=doctest.ELLIPSIS)
failed, attempted, examples = [], 0, 0
for module in all_modules(private=True):
    for test in finder.find(module):
        report = []
        result = runner.run(test, out=report.append)
        examples += len(test.examples)
        attempted += result.attempted
        if result.failed:
            failed.append(test.name + ":\\n" + "".join(report))
print(json.dumps({"failed": failed, "attempted": attempted, "examples": examples}))
"""


def test_every_docstring_example_runs(tmp_path):
    done = subprocess.run(
        [sys.executable, "-P", "-c", DOCTESTS, str(ROOT / "tests")],
        check=False,
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=300,
        stdin=subprocess.DEVNULL,
    )
    assert done.returncode == 0, done.stderr[-3000:]
    result = json.loads(done.stdout.strip().splitlines()[-1])
    assert not result["failed"], "\n".join(result["failed"])
    # examples marked `# doctest: +SKIP` count in examples, not in attempted
    print(f"doctests: {result['attempted']} examples run ({result['examples']} in all)")
    assert result["attempted"] >= 6


def _pycon_blocks(text: str) -> list[str]:
    """The ``pycon`` blocks of a page: Python sessions (``>>>``) a reader can paste."""
    return re.findall(r"^```pycon\n(.*?)^```", text, re.S | re.M)


def test_every_python_session_of_the_pages_runs():
    """A page's ``pycon`` blocks run as doctests (the statistics protocol's on the identification page)."""
    import doctest

    parser, runner = doctest.DocTestParser(), doctest.DocTestRunner(optionflags=doctest.ELLIPSIS)
    pages = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
    blocks = [(page, block) for page in pages for block in _pycon_blocks(page.read_text())]
    assert any(page.name == "identification.md" for page, _ in blocks)
    for i, (page, block) in enumerate(blocks):
        runner.run(parser.get_doctest(block, {}, f"{page.name}[{i}]", str(page), 0))
    result = runner.summarize(verbose=False)
    assert result.failed == 0 and result.attempted > 0


def test_the_session_blocks_are_found_whole():
    text = "# Page\n\n```pycon\n>>> 1 + 1\n2\n```\n\n```python\nx = 1\n```\n"
    assert _pycon_blocks(text) == [">>> 1 + 1\n2\n"]


def test_every_readme_directive_of_the_pages_finds_its_text(caplog):
    """A page's ``% readme "START" "END"`` line must find its text in the README as it is now: text
    moved out of the README goes into the page itself, not a directive left pointing at nothing."""
    readme = (ROOT / "README.md").read_text()
    for page in sorted((ROOT / "docs").rglob("*.md")):
        if "_build" in page.parts:
            continue
        for match in readme_slices.SLICE.finditer(page.read_text()):
            with caplog.at_level(logging.WARNING):
                text = readme_slices.readme_slice(readme, match[1], match[2], str(page.relative_to(ROOT)))
            assert text and "README marker" not in caplog.text, caplog.text


# Folders whose files users read: the packages (code, docstrings, --help texts and messages, the
# format documents and the firmware beside them), the examples, benchmarks and tools.
USER_FACING_FOLDERS = ("core", "daq", "design", "firmware_protocol", "identify", "sim", "examples", "bench", "tools")
TEXT_SUFFIXES = {".py", ".md", ".rst", ".txt", ".toml", ".json", ".c", ".h", ".ino", ".sh", ".cfg"}
#: A pointer instead of a fact: to the project's tracker (issue 27, #27) or to notes outside the
#: repository that users do not have (FACTS.md, DESIGN.md).
OUTSIDE_POINTER = re.compile(r"\bFACTS\b|\bDESIGN\.md\b|\b[Ii]ssues? \d+|(?<![&\w])#\d+\b")


def _user_facing_files() -> list[Path]:
    files = [ROOT / "README.md", ROOT / "NAMING.md", *(ROOT / "docs").rglob("*")]
    for folder in USER_FACING_FOLDERS:
        files += (ROOT / folder).rglob("*")
    skipped = {"_build", "generated", "__pycache__", ".ipynb_checkpoints"}
    return sorted(
        path
        for path in files
        if path.is_file() and path.suffix in TEXT_SUFFIXES and not skipped & set(path.relative_to(ROOT).parts)
    )


def test_user_facing_text_states_facts_instead_of_pointing_outside_the_repository():
    files = _user_facing_files()
    assert (
        ROOT / "README.md" in files and ROOT / "identify" / "estimators" / "regression.py" in files and len(files) > 100
    )
    found = [
        f"{path.relative_to(ROOT)}:{number}: {match[0]!r}"
        for path in files
        for number, line in enumerate(path.read_text(errors="replace").splitlines(), start=1)
        for match in OUTSIDE_POINTER.finditer(line)
    ]
    assert not found, "pointers to issues or to notes outside the repository:\n" + "\n".join(found)


def test_the_pointer_pattern_catches_what_it_is_for():
    assert OUTSIDE_POINTER.search("memory does not grow (issue 29)")
    assert OUTSIDE_POINTER.search("Issues 27 and 28")
    assert OUTSIDE_POINTER.search("as asked in #31.")
    assert OUTSIDE_POINTER.search("(FACTS section 5)") and OUTSIDE_POINTER.search("see DESIGN.md, Real time")
    assert not OUTSIDE_POINTER.search("an issue with 3 episodes") and not OUTSIDE_POINTER.search("&#39;")


def test_the_readme_docs_and_tutorial_do_not_send_users_to_the_test_layout():
    """The datasets are found through $QUBE_DATASET_DIR (or an argument), never through the folder
    beside the clone that the test suite and CI happen to use."""
    files = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md")), ROOT / "examples" / "tutorial.py"]
    found = [str(path.relative_to(ROOT)) for path in files if "../shared" in path.read_text()]
    assert not found
