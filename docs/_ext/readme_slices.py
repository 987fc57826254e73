"""Sphinx extension: the README's sections in the documentation's pages (docs/conf.py).

A page line ``% readme "START" "END"`` (a MyST comment, so it shows nothing by itself) becomes
the README's text from the line holding START (which must occur once) up to the line holding
END (its first occurrence after START; END "" is the end of the README), dedented, so a fact the
README states need not be copied into a page. A marker that is not found is a warning, which
fails the build under -W, and tests/docs/test_docs.py checks every directive against the README as it
is. The README being a short landing page, the pages hold their own text and pull none of it.

Written here because Sphinx's and MyST's include directives start a part only at a line number
or *after* a marker line (our markers are the first lines of README list items, which must be
kept), and line numbers move with every README edit.
"""

from __future__ import annotations

import re
import textwrap
from pathlib import Path

from sphinx.util import logging

README = Path(__file__).resolve().parents[2] / "README.md"
SLICE = re.compile(r'^% readme "([^"]+)" "([^"]*)"$', re.MULTILINE)
# Links in the README point at files beside it: a module's source becomes its API page, other
# files a download; format documents resolve as pages (docs/ mirrors their paths).
_SOURCE_LINK = re.compile(r"\[([^\]]+)\]\(((?:[a-z_]+/)*[a-z_]+)\.py\)")
_FILE_LINK = re.compile(r"\[([^\]]+)\]\((LICENSE)\)")
_logger = logging.getLogger(__name__)


def readme_slice(readme: str, start: str, end: str, where: str) -> str:
    """The README's lines from the one holding ``start`` to the one holding ``end``, dedented,
    with links to source files made API links; ``""`` and a warning if a marker is missing."""
    begin = readme.find(start)
    if begin < 0 or readme.find(start, begin + 1) >= 0:
        _logger.warning("%s: README marker %r %s", where, start, "not found" if begin < 0 else "is not unique")
        return ""
    begin = readme.rfind("\n", 0, begin) + 1
    stop = len(readme) if not end else readme.find(end, begin + 1)
    if stop < 0:
        _logger.warning("%s: README marker %r not found after %r", where, end, start)
        return ""
    stop = readme.rfind("\n", 0, stop) + 1 if end else stop
    text = textwrap.dedent(readme[begin:stop])
    text = _SOURCE_LINK.sub(lambda m: f"{{py:mod}}`{m[1]} <qube_koopman.{m[2].replace('/', '.')}>`", text)
    return _FILE_LINK.sub(lambda m: f"{{download}}`{m[1]} </../{m[2]}>`", text)


def expand(page: str, readme: str, where: str) -> str:
    """``page`` with each ``% readme`` line replaced by its README slice."""
    return SLICE.sub(lambda m: readme_slice(readme, m[1], m[2], where), page)


def _source_read(app, docname: str, source: list[str]) -> None:
    source[0] = expand(source[0], README.read_text(), docname)


def setup(app) -> dict:
    app.connect("source-read", _source_read)
    return {"parallel_read_safe": True, "parallel_write_safe": True}
