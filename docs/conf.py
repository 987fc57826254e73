"""Sphinx configuration of the qube-koopman documentation.

Why Sphinx rather than MkDocs + mkdocstrings: the project's docstrings are numpydoc, which
Sphinx renders natively (the numpydoc extension), and the libraries our users already know,
python-control and scikit-learn, build their documentation with Sphinx + numpydoc +
autodoc/autosummary, so the API pages look and link as theirs do. Pages are Markdown (MyST,
myst-parser); the format documents kept beside the code (identify/MODEL_FORMAT.md, ...) are
included, not copied, so there is one source for each fact. A page may also pull a part of the
README with a ``% readme "START" "END"`` line (docs/_ext/readme_slices.py).

Build: ``python -m sphinx -W --keep-going -b html docs docs/_build/html`` (tests/docs/test_docs.py
runs the same). No network: intersphinx is not used (CI reaches only package registries).
"""

from __future__ import annotations

import importlib
import pkgutil
import shutil
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "docs" / "_ext"))

project = "qube-koopman"
author = "qube-koopman contributors"
copyright = "qube-koopman contributors, MIT licence"  # noqa: A001 (Sphinx's name)
try:
    from importlib.metadata import version as _version

    release = _version("qube-koopman")
except Exception:  # noqa: BLE001 (the docs build from a checkout that is not installed)
    release = "unknown"

extensions = [
    "sphinx.ext.autodoc",
    "sphinx.ext.autosummary",
    "numpydoc",
    "myst_parser",
    "readme_slices",  # docs/_ext: the README's sections in the pages
]

source_suffix = {".rst": "restructuredtext", ".md": "markdown"}
exclude_patterns = ["_build"]
templates_path = ["_templates"]
html_theme = "alabaster"
html_static_path: list[str] = []

myst_enable_extensions = ["colon_fence"]

# API reference: one page per public module, generated (autosummary :recursive:) so a new module
# appears without editing the docs. Each name is documented once, in the module that defines it
# (autodoc's default: imported names are skipped, and packages' __all__ is ignored so their
# re-exports are not described twice); a package's page lists its re-exports as links to those
# (`reexports` below, used by _templates/autosummary/module.rst).
autosummary_generate = True
# The stubs are derived from the code: start afresh, so a module removed or renamed leaves no
# stale page behind that would fail to import.
shutil.rmtree(ROOT / "docs" / "api" / "generated", ignore_errors=True)
autosummary_ignore_module_all = True
autosummary_imported_members = False
autodoc_default_options = {
    "members": True,
    "show-inheritance": True,
    "ignore-module-all": True,
    "member-order": "bysource",
}
autodoc_typehints = "none"  # the numpydoc Parameters sections give the types
# The code annotates; it has no type comments, and looking for them re-read and re-parsed the
# source of every documented function (a sixth of the build's time).
autodoc_use_type_comments = False
autodoc_class_signature = "mixed"

# numpydoc: no per-class member tables (autodoc lists the members; the tables would need stub
# pages of their own); type names are not turned into cross-references (the project's types are
# often "array (n_samples, n_states)", which would not resolve).
numpydoc_show_class_members = False
numpydoc_class_members_toctree = False
numpydoc_xref_param_type = False

PACKAGES = [
    "qube_koopman.sim",
    "qube_koopman.firmware_protocol",
    "qube_koopman.daq",
    "qube_koopman.identify",
    "qube_koopman.design",
    "qube_koopman.core",
]


def _reexports() -> dict[str, list[str]]:
    """For each package (and sub-package): the names its ``__all__`` re-exports, as paths to
    their defining modules (functions and classes; constants are described in the package)."""
    found = {}
    for top in PACKAGES:
        package = importlib.import_module(top)
        names = [top] + [info.name for info in pkgutil.walk_packages(package.__path__, prefix=f"{top}.") if info.ispkg]
        for name in names:
            module = importlib.import_module(name)
            targets = []
            for attr in getattr(module, "__all__", []):
                obj = getattr(module, attr)
                home = getattr(obj, "__module__", None)
                if home and home != name and hasattr(obj, "__qualname__"):
                    # relative to the package: autosummary refuses the package's own prefix
                    targets.append(f"{home.removeprefix(name + '.')}.{obj.__qualname__}")
            found[name] = targets
    return found


autosummary_context = {"reexports": _reexports()}


# numpydoc (1.x) builds a Jinja environment and compiles its docstring template anew for every
# docstring (docscrape_sphinx.get_doc_object): a third of this build's time. The environments it
# makes share this subclass, whose one compiled template serves them all (the template cannot
# change within a build). Skipped if a later numpydoc does without that environment.
from numpydoc import docscrape_sphinx  # noqa: E402

if hasattr(docscrape_sphinx, "SandboxedEnvironment"):

    class _TemplateOnce(docscrape_sphinx.SandboxedEnvironment):
        _compiled: dict = {}

        def get_template(self, name, *args, **kwargs):
            if name not in self._compiled:
                self._compiled[name] = super().get_template(name, *args, **kwargs)
            return self._compiled[name]

    docscrape_sphinx.SandboxedEnvironment = _TemplateOnce
