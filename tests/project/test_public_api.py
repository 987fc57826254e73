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
    return [
        p.name
        for p in signature.parameters.values()
        if p.kind not in (p.VAR_POSITIONAL, p.VAR_KEYWORD) and p.name not in ("self", "cls")
    ]


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
    problems = {
        name: docstring_problems(obj)
        for name in module.__all__
        if inspect.isfunction(obj := getattr(module, name)) or inspect.isclass(obj)
    }
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


@pytest.mark.parametrize(
    "package, names",
    [
        (
            "qube_koopman.identify",
            {
                "ClEdmd",
                "ClEdmdStable",
                "clone",
                "identify_and_score",
                "search_liftings",
                "regularization_sweep",
                "load_logs",
                "twin_probes",
                "save_model",
                "load_model",
                "IdentifiedModel",
                "Lifting",
                "Delay",
                "KoopmanModel",
                "Trajectory",
            },
        ),
        ("qube_koopman.daq", {"read_episode", "write_episode", "Episode", "run_episodes", "plan_episodes"}),
        ("qube_koopman.sim", {"PendulumParameters", "simulate_closed_loop", "PendulumSimulator"}),
        (
            "qube_koopman.core",
            {
                "DiscreteStateSpace",
                "replay_controller",
                "spectral_radius",
                "atomic_path",
                "load_controller",
                "ControllerInfo",
                "pd_controller",
                "PdGains",
                "write_controller_file",
            },
        ),
        ("qube_koopman.design", {"design_lq", "linear_plant", "design_from_model"}),
    ],
)
def test_the_packages_export_what_users_import(package, names):
    assert names <= set(importlib.import_module(package).__all__)


@pytest.mark.parametrize(
    "package", ["qube_koopman.daq", "qube_koopman.sim", "qube_koopman.identify", "qube_koopman.design"]
)
def test_importing_a_package_imports_none_of_the_modules_it_exports_from(package):
    """The names are imported when first used (PEP 562): ``import qube_koopman.daq`` does not load
    the episode log's mcap or scipy, and the 500 Hz loop pays only for the modules it imports."""
    code = f"import sys; import {package}; print(','.join(m for m in sys.modules if m.startswith('{package}.')))"
    loaded = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.strip()
    assert loaded == ""


def _imported_module(path: Path, node: ast.ImportFrom) -> str:
    """The absolute name of the module ``from M import ...`` names (a relative import resolved)."""
    if not node.level:
        return node.module or ""
    package = ["qube_koopman", *path.relative_to(ROOT).parent.parts]
    base = package[: len(package) - (node.level - 1)]
    return ".".join(base + ([node.module] if node.module else []))


def _private_imports(path: Path) -> list[str]:
    """``from M import _x`` (a private name of another module), and imports of a private module from
    outside the package that holds it (``qube_koopman.identify.estimators._base`` from outside identify,
    or from identify/uncertainty: only identify/estimators may import it)."""
    relative = path.relative_to(ROOT)
    here = ("qube_koopman", *relative.parent.parts)
    top = relative.parts[0]
    found = []
    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        if isinstance(node, ast.ImportFrom):
            found += [
                f"{relative}:{node.lineno}: from {'.' * node.level}{node.module or ''} import {alias.name}"
                for alias in node.names
                if alias.name.startswith("_") and not alias.name.startswith("__")
            ]
            modules = [_imported_module(path, node)]
        elif isinstance(node, ast.Import):
            modules = [alias.name for alias in node.names]
        else:
            continue
        for module in modules:
            parts = module.split(".")
            if parts[0] != "qube_koopman" or len(parts) < 3:
                continue
            private = [
                i for i, part in enumerate(parts) if i >= 2 and part.startswith("_") and not part.startswith("__")
            ]
            if not private:
                continue
            owner = tuple(parts[: private[0]])  # the package holding the private module
            if parts[1] != top:
                found.append(f"{relative}:{node.lineno}: import of {module}, private to {parts[1]}")
            elif here[: len(owner)] != owner:
                found.append(f"{relative}:{node.lineno}: import of {module}, private to {'/'.join(owner[1:])}")
    return found


def test_no_module_imports_a_private_name_of_another_module():
    offenders = [
        hit for folder in _package_folders() for path in sorted(folder.rglob("*.py")) for hit in _private_imports(path)
    ]
    assert not offenders, "\n".join(offenders)


def test_the_private_import_scan_finds_what_it_is_for(tmp_path, monkeypatch):
    folder = tmp_path / "daq"
    folder.mkdir()
    source = folder / "mod.py"
    source.write_text(
        "from qube_koopman.core.lti import _helper, DiscreteStateSpace\n"
        "from .sibling import _thing as thing\n"
        "from qube_koopman.identify.estimators._base import Estimator\n"
        "from qube_koopman.daq._own import fine\n"
        "from qube_koopman.sim import __version__\n"
    )
    monkeypatch.setattr(sys.modules[__name__], "ROOT", tmp_path)
    assert _private_imports(source) == [
        "daq/mod.py:1: from qube_koopman.core.lti import _helper",
        "daq/mod.py:2: from .sibling import _thing",
        "daq/mod.py:3: import of qube_koopman.identify.estimators._base, private to identify",
    ]


def test_the_private_import_scan_finds_a_private_module_of_another_subpackage(tmp_path, monkeypatch):
    """Inside a package too: a private module is private to the folder holding it."""
    (tmp_path / "identify" / "uncertainty").mkdir(parents=True)
    (tmp_path / "identify" / "estimators").mkdir()
    outside = tmp_path / "identify" / "uncertainty" / "mod.py"
    outside.write_text(
        "from qube_koopman.identify.estimators._base import episode_statistics\n"
        "import qube_koopman.identify.estimators._base\n"
        "from ..estimators._base import FitSetup\n"
        "from qube_koopman.identify._checks import check_alpha\n"
        "from qube_koopman.identify.uncertainty._own import fine\n"
        "from ._own import fine_too\n"
    )
    inside = tmp_path / "identify" / "estimators" / "mod.py"
    inside.write_text("from qube_koopman.identify.estimators._base import FitSetup\nfrom ._base import Estimator\n")
    monkeypatch.setattr(sys.modules[__name__], "ROOT", tmp_path)
    private = "private to identify/estimators"
    assert _private_imports(outside) == [
        f"identify/uncertainty/mod.py:1: import of qube_koopman.identify.estimators._base, {private}",
        f"identify/uncertainty/mod.py:2: import of qube_koopman.identify.estimators._base, {private}",
        f"identify/uncertainty/mod.py:3: import of qube_koopman.identify.estimators._base, {private}",
    ]
    assert _private_imports(inside) == []


def _private_members(tree: ast.AST) -> set[str]:
    """The private methods and instance attributes (``self._x = ...``) the classes of a module define."""
    names = set()
    for cls in (node for node in ast.walk(tree) if isinstance(node, ast.ClassDef)):
        names |= {node.name for node in cls.body if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef))}
        names |= {
            node.attr
            for node in ast.walk(cls)
            if isinstance(node, ast.Attribute)
            and isinstance(node.ctx, ast.Store)
            and isinstance(node.value, ast.Name)
            and node.value.id == "self"
        }
    return {name for name in names if name.startswith("_") and not name.startswith("__")}


def _foreign_private_uses(files: list[Path]) -> list[str]:
    """``obj._x`` where ``_x`` is a private method or attribute that classes of other modules define
    and this module's classes do not (``self._x``, ``cls._x`` and ``super()._x`` are the object's
    own). Static, so by name: a module defining a member of the same name is not checked for it."""
    trees = {path: ast.parse(path.read_text(), filename=str(path)) for path in files}
    own = {path: _private_members(tree) for path, tree in trees.items()}
    defined_in: dict[str, list[Path]] = {}
    for path, names in own.items():
        for name in names:
            defined_in.setdefault(name, []).append(path)
    found = []
    for path, tree in trees.items():
        for node in ast.walk(tree):
            if not isinstance(node, ast.Attribute) or node.attr not in defined_in or node.attr in own[path]:
                continue
            value = node.value
            if isinstance(value, ast.Name) and value.id in ("self", "cls"):
                continue
            if isinstance(value, ast.Call) and isinstance(value.func, ast.Name) and value.func.id == "super":
                continue
            homes = ", ".join(sorted(str(home.relative_to(ROOT)) for home in defined_in[node.attr]))
            found.append(f"{path.relative_to(ROOT)}:{node.lineno}: .{node.attr}, private to {homes}")
    return sorted(found)


def test_no_module_uses_a_private_method_or_attribute_of_another_modules_objects():
    """The estimators' statistics protocol (setup_fit, episode_snapshots, statistics_fold, finish_fit)
    is public; the sweep, the search, the bootstrap and the cluster runner use nothing private of them."""
    files = [path for folder in _package_folders() for path in sorted(folder.rglob("*.py"))]
    offenders = _foreign_private_uses(files)
    assert not offenders, "\n".join(offenders)


def test_the_private_member_scan_finds_what_it_is_for(tmp_path, monkeypatch):
    (tmp_path / "identify").mkdir()
    estimator = tmp_path / "identify" / "estimator.py"
    estimator.write_text(
        "class Estimator:\n"
        "    def __init__(self):\n        self._cache = None\n"
        "    def _setup(self, data):\n        return self._cache\n"
        "    def setup_fit(self, data):\n        return self._setup(data)\n"
        "class Child(Estimator):\n"
        "    def _setup(self, data):\n        return super()._setup(data)\n"
    )
    sweep = tmp_path / "identify" / "sweep.py"
    sweep.write_text(
        "def sweep(estimator, data):\n"
        "    estimator._setup(data)\n"
        "    print(estimator._cache)\n"
        "    return estimator.setup_fit(data)\n"
    )
    monkeypatch.setattr(sys.modules[__name__], "ROOT", tmp_path)
    assert _foreign_private_uses([estimator, sweep]) == [
        "identify/sweep.py:2: ._setup, private to identify/estimator.py",
        "identify/sweep.py:3: ._cache, private to identify/estimator.py",
    ]


def test_the_tutorial_imports_from_the_packages_only():
    """examples/tutorial.py is what a user copies: it imports ``qube_koopman.<package>``, never a module."""
    tree = ast.parse((ROOT / "examples" / "tutorial.py").read_text())
    modules = [node.module for node in ast.walk(tree) if isinstance(node, ast.ImportFrom)]
    modules += [alias.name for node in ast.walk(tree) if isinstance(node, ast.Import) for alias in node.names]
    ours = [module for module in modules if module.split(".")[0] == "qube_koopman"]
    assert ours, "the tutorial imports nothing of the toolkit"
    deep = [module for module in ours if module not in PACKAGES]
    assert not deep, f"the tutorial imports from modules: {deep}"
