"""The packages' public names, as the project counts them (tests/project/test_package.py, tests/docs/test_docs.py).

A public module is one whose dotted name has no part starting with ``_``; its public names are
the functions and classes it defines (not those it imports) whose names do not start with
``_``, and the public methods (plain functions in the class body) of those classes.
"""

from __future__ import annotations

import importlib
import inspect
import pkgutil
from collections.abc import Iterator
from types import ModuleType

PACKAGES = [
    "qube_koopman.identify",
    "qube_koopman.sim",
    "qube_koopman.daq",
    "qube_koopman.firmware_protocol",
    "qube_koopman.design",
    "qube_koopman.core",
]


def all_modules(private: bool = False) -> Iterator[ModuleType]:
    """Every module of the packages, imported; private ones (a part starting with ``_``) too
    when ``private``."""
    for name in PACKAGES:
        pkg = importlib.import_module(name)
        yield pkg
        for info in pkgutil.walk_packages(pkg.__path__, prefix=f"{name}."):
            if private or not any(part.startswith("_") for part in info.name.split(".")):
                yield importlib.import_module(info.name)


def public_modules() -> Iterator[ModuleType]:
    """The public modules of the packages, imported."""
    return all_modules(private=False)


def public_names() -> Iterator[tuple[str, object]]:
    """(full dotted name, object) of every public function, class and method."""
    for module in public_modules():
        for name, obj in vars(module).items():
            if name.startswith("_") or getattr(obj, "__module__", None) != module.__name__:
                continue
            if inspect.isfunction(obj) or inspect.isclass(obj):
                yield f"{module.__name__}.{name}", obj
                if inspect.isclass(obj):
                    for meth_name, meth in vars(obj).items():
                        if not meth_name.startswith("_") and inspect.isfunction(meth):
                            yield f"{module.__name__}.{name}.{meth_name}", meth
