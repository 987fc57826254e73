"""The README is a landing page, and the figures its commands' comments quote are checked as they
should be (tests/readme_blocks.py); quick checks, without the dataset, of what tests/test_readme*.py
run in full."""

from __future__ import annotations

import re

import pytest
from readme_blocks import (
    BLOCK_SOURCES,
    BLOCKS,
    DOCUMENTS,
    REPO,
    expected_exit,
    figure_matches,
    figure_problems,
    markdown_blocks,
    quoted_text,
)


def test_the_readme_is_short_enough_to_read_in_five_minutes():
    # what it is, its first two commands, one example end to end, where the documentation is
    size = len((REPO / "README.md").read_text())
    assert size < 8000, f"README.md is {size} characters: its details belong in the documentation's pages"


def test_the_readme_links_every_page_of_the_documentation():
    readme = (REPO / "README.md").read_text()
    index = (REPO / "docs" / "index.md").read_text()
    toctree = index[index.index("```{toctree}") :]
    pages = [line.strip() for line in toctree.splitlines()[1:] if line.strip() and not line.startswith((":", "```"))]
    assert "getting-started" in pages
    missing = [page for page in pages if page != "api/index" and f"(docs/{page}.md)" not in readme]
    assert not missing, f"docs pages the README does not link: {missing}"


def test_the_blocks_come_from_the_readme_and_the_pages_and_each_line_shows_its_exit_code():
    assert DOCUMENTS[0] == REPO / "README.md" and BLOCK_SOURCES[0] == REPO / "README.md"
    assert {path.name for path in BLOCK_SOURCES} >= {"README.md", "getting-started.md", "design.md", "calibration.md"}
    missing = [
        f"{BLOCK_SOURCES[i].relative_to(REPO)}:{number}"
        for i, block in enumerate(BLOCKS)
        for number, line in block
        if expected_exit(line) is None
    ]
    assert not missing, f"command lines without '# exit N' in their comment: {missing}"


def test_markdown_blocks_reads_any_page(tmp_path):
    page = tmp_path / "page.md"
    page.write_text("text\n\n```bash\nqube-run \\\n  --seed 1   # exit 0: 3 complete\n```\n\n```text\nnot run\n```\n")
    assert markdown_blocks(page) == [[(5, "qube-run    --seed 1   # exit 0: 3 complete")]]


@pytest.mark.parametrize(
    "quoted, printed, matches",
    [
        ("0.9633", "0.9633", True),
        ("0.9633", "0.9634", True),  # one unit of the last quoted digit
        ("0.9633", "0.9635", False),
        ("0.963", "0.9633", True),  # quoted coarser than printed: to its own last digit
        ("0.973", "0.9715", False),  # the figure a re-run no longer prints
        ("0.96331", "0.9633", False),  # quoted finer than printed
        ("-60.4", "-60.4", True),
        ("60.4", "-60.4", False),
        ("48", "48", True),
        ("48", "47", False),  # a count exactly
        ("48", "48.0", False),
        ("5.85e-3", "5.848e-03", True),
        ("5.85e-3", "5.838e-03", False),
    ],
)
def test_a_quoted_figure_matches_a_printed_one_to_its_precision(quoted, printed, matches):
    assert figure_matches(quoted, printed) is matches


def test_figure_problems_names_what_the_output_does_not_print():
    line = "qube-identify --train a --test b --delays 35 --out back  # exit 0: R^2 0.973 over 20 episodes"
    assert quoted_text(line) == ": R^2 0.973 over 20 episodes"
    printed = "cl-edmd, alpha 0.001: test R^2 0.9715 +- 0.0054, NRMSE 5.11 +- 0.64 % over 20 episodes (cl)\n"
    assert figure_problems(line, printed) == ["0.973"]
    assert figure_problems(line.replace("0.973", "0.9715"), printed) == []
    # neither the 2 of R^2 nor digits inside names count as quoted figures
    assert figure_problems("x  # exit 0: R^2 on qube_20230828 logs; --rerun-episodes", "") == []
    # ranges as the calibration prints them
    assert figure_problems("x  # exit 0: theta 0.973..0.997", "theta 0.973..0.997 (0.985)") == []


def test_every_figure_the_readme_quotes_is_in_a_command_comment():
    """Outside its command blocks the README quotes no measured figure (an R^2, a cost, a time):
    those come with the command that prints them, where the tests check them."""
    text = (REPO / "README.md").read_text()
    prose = re.sub(r"```bash\n.*?```", "", text, flags=re.DOTALL)
    figures = re.findall(r"(?<![\w^.])\d+\.\d+(?![\w.])|\d+(?:\.\d+)? ?%", prose)
    assert figures == ["3.11"], figures  # the Python version it needs
