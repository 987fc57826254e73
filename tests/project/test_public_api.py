"""The public API: what each package exports, documented; no module reaching into another's privates.

Users import from ``qube_koopman.<package>`` (docs/getting-started.md): each package's ``__all__``
lists those names, every one resolves and carries a numpydoc docstring, the tutorial imports from
nothing deeper, and a module uses only the public names of the others (a name two modules share is
public where it is defined, or lives in a shared helper module). Importing a package stays light.
"""

from __future__ import annotations

import ast
import enum
import importlib
import inspect
import subprocess
import sys
import tomllib
import warnings
from pathlib import Path

import pytest
from _public_api import PACKAGES
from numpydoc.docscrape import NumpyDocString

ROOT = Path(__file__).resolve().parents[2]
# The packages whose __all__ lists what users import (core's lists the commands' plumbing).
USER_PACKAGES = [name for name in PACKAGES if name != "qube_koopman.core"]


def _package_folders() -> list[Path]:
    package_dir = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]["package-dir"]
    return [ROOT / folder for folder in package_dir.values()]


def _constructor_parameters(obj) -> list[str]:
    """The parameters a caller passes (not self, not *args or **kwargs); none for an enum or an
    exception, whose constructors are Python's."""
    if inspect.isclass(obj) and issubclass(obj, (enum.Enum, BaseException)):
        return []
    try:
        signature = inspect.signature(obj)
    except (TypeError, ValueError):  # a builtin without a signature
        return []
    return [p.name for p in signature.parameters.values()
            if p.kind not in (p.VAR_POSITIONAL, p.VAR_KEYWORD) and p.name not in ("self", "cls")]


def docstring_problems(obj) -> list[str]:
    """What a numpydoc docstring of ``obj`` lacks: a summary line; a Parameters section when it
    takes parameters. Empty when it has both."""
    doc = inspect.getdoc(obj)
    if not doc:
        return ["no docstring"]
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # numpydoc warns of a section it cannot read
        try:
            parsed = NumpyDocString(doc)
        except Warning as warning:
            return [f"not numpydoc: {warning}"]
    problems = []
    if not " ".join(parsed["Summary"]).strip():
        problems.append("no summary line")
    if _constructor_parameters(obj) and not parsed["Parameters"]:
        problems.append(f"no Parameters section for {', '.join(_constructor_parameters(obj))}")
    return problems


@pytest.mark.parametrize("package", PACKAGES)
def test_every_name_a_package_exports_resolves(package):
    module = importlib.import_module(package)
    assert module.__all__, f"{package} exports nothing"
    assert len(set(module.__all__)) == len(module.__all__), "a name listed twice"
    missing = [name for name in module.__all__ if not hasattr(module, name)]
    assert not missing
    assert set(module.__all__) <= set(dir(module))


@pytest.mark.parametrize("package", USER_PACKAGES)
def test_every_function_and_class_a_package_exports_has_a_numpydoc_docstring(package):
    module = importlib.import_module(package)
    problems = {name: docstring_problems(obj) for name in module.__all__
                if inspect.isfunction(obj := getattr(module, name)) or inspect.isclass(obj)}
    problems = {name: found for name, found in problems.items() if found}
    assert not problems, f"{package}: {problems}"


def test_the_docstring_check_finds_what_it_is_for():
    def summary_only(a, b):
        """Add."""

    def documented(a):
        """Add one.

        Parameters
        ----------
        a : int
            The number.
        """

    def no_parameters():
        """Nothing to pass."""

    assert docstring_problems(summary_only) == ["no Parameters section for a, b"]
    assert docstring_problems(documented) == [] and docstring_problems(no_parameters) == []
    assert docstring_problems(lambda: None) == ["no docstring"]


@pytest.mark.parametrize("package, names", [
    ("qube_koopman.identify", {"ClEdmd", "ClEdmdStable", "clone", "identify_and_score", "search_liftings",
                               "regularization_sweep", "load_logs", "twin_probes", "save_model", "load_model",
                               "Lifting", "Delay", "KoopmanModel", "Trajectory"}),
    ("qube_koopman.daq", {"read_episode", "write_episode", "Episode", "run_episodes", "plan_episodes"}),
    ("qube_koopman.sim", {"PendulumParameters", "simulate_closed_loop", "PendulumSimulator"}),
    ("qube_koopman.core", {"DiscreteStateSpace", "replay_controller", "spectral_radius", "atomic_path",
                           "load_controller", "ControllerInfo", "pd_controller", "PdGains", "write_controller_file"}),
    ("qube_koopman.design", {"design_lq", "linear_plant", "design_from_model"}),
])
def test_the_packages_export_what_users_import(package, names):
    assert names <= set(importlib.import_module(package).__all__)


@pytest.mark.parametrize("package", ["qube_koopman.daq", "qube_koopman.sim", "qube_koopman.identify",
                                     "qube_koopman.design"])
def test_importing_a_package_imports_none_of_the_modules_it_exports_from(package):
    """The names are imported when first used (PEP 562): ``import qube_koopman.daq`` does not load
    the episode log's mcap or scipy, and the 500 Hz loop pays only for the modules it imports."""
    code = (f"import sys; import {package}; "
            f"print(','.join(m for m in sys.modules if m.startswith('{package}.')))")
    loaded = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.strip()
    assert loaded == ""


def _private_imports(path: Path) -> list[str]:
    """``from M import _x`` (a private name of another module), and imports of another package's
    private module (``qube_koopman.identify.estimators._base`` from outside identify)."""
    top = path.relative_to(ROOT).parts[0]
    found = []
    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        if isinstance(node, ast.ImportFrom):
            found += [f"{path.relative_to(ROOT)}:{node.lineno}: from {'.' * node.level}{node.module or ''} "
                      f"import {alias.name}" for alias in node.names
                      if alias.name.startswith("_") and not alias.name.startswith("__")]
            modules = [node.module or ""]
        elif isinstance(node, ast.Import):
            modules = [alias.name for alias in node.names]
        else:
            continue
        for module in modules:
            parts = module.split(".")
            if parts[0] == "qube_koopman" and len(parts) > 1 and parts[1] != top \
                    and any(part.startswith("_") for part in parts[2:]):
                found.append(f"{path.relative_to(ROOT)}:{node.lineno}: import of {module}, private to {parts[1]}")
    return found


def test_no_module_imports_a_private_name_of_another_module():
    offenders = [hit for folder in _package_folders() for path in sorted(folder.rglob("*.py"))
                 for hit in _private_imports(path)]
    assert not offenders, "\n".join(offenders)


def test_the_private_import_scan_finds_what_it_is_for(tmp_path, monkeypatch):
    folder = tmp_path / "daq"
    folder.mkdir()
    source = folder / "mod.py"
    source.write_text("from qube_koopman.core.lti import _helper, DiscreteStateSpace\n"
                      "from .sibling import _thing as thing\n"
                      "from qube_koopman.identify.estimators._base import Estimator\n"
                      "from qube_koopman.daq._own import fine\n"
                      "from qube_koopman.sim import __version__\n")
    monkeypatch.setattr(sys.modules[__name__], "ROOT", tmp_path)
    assert _private_imports(source) == ["daq/mod.py:1: from qube_koopman.core.lti import _helper",
                                        "daq/mod.py:2: from .sibling import _thing",
                                        "daq/mod.py:3: import of qube_koopman.identify.estimators._base, private to identify"]


def test_the_tutorial_imports_from_the_packages_only():
    """examples/tutorial.py is what a user copies: it imports ``qube_koopman.<package>``, never a module."""
    tree = ast.parse((ROOT / "examples" / "tutorial.py").read_text())
    modules = [node.module for node in ast.walk(tree) if isinstance(node, ast.ImportFrom)]
    modules += [alias.name for node in ast.walk(tree) if isinstance(node, ast.Import) for alias in node.names]
    ours = [module for module in modules if module.split(".")[0] == "qube_koopman"]
    assert ours, "the tutorial imports nothing of the toolkit"
    deep = [module for module in ours if module not in PACKAGES]
    assert not deep, f"the tutorial imports from modules: {deep}"
