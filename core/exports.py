"""A package's public names, imported from their modules only when first used (PEP 562).

A package lists what users import from it (``from <package> import read_episode``) without
importing every module behind those names when the package is imported: importing the package
costs its ``__init__`` alone, and a program that imports a few of its modules (the 500 Hz
acquisition loop) does not pay for the others' libraries (mcap, scipy, the exporters).
"""

from __future__ import annotations

import importlib
import sys
from collections.abc import Callable, Mapping

__all__ = ["lazy_exports"]


def lazy_exports(package: str, homes: Mapping[str, str]) -> tuple[Callable[[str], object], Callable[[], list[str]]]:
    """The ``__getattr__`` and ``__dir__`` of a package whose names are imported when first used.

    Parameters
    ----------
    package : str
        The package's dotted name (its ``__name__``).
    homes : mapping of str to str
        Each exported name and the module, relative to the package, that defines it
        (``{"read_episode": "log"}``: ``read_episode`` of the package's ``log``).

    Returns
    -------
    __getattr__ : callable
        Imports the name's module, caches the name in the package and returns it; an
        :class:`AttributeError` for any other name, as for a plain module.
    __dir__ : callable
        The package's attributes and every exported name.

    Examples
    --------
    In a package's ``__init__.py``::

        _HOMES = {"read_episode": "log", "Episode": "episode"}
        __all__ = list(_HOMES)
        __getattr__, __dir__ = lazy_exports(__name__, _HOMES)
    """

    def __getattr__(name: str) -> object:
        home = homes.get(name)
        if home is None:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        value = getattr(importlib.import_module(f"{package}.{home}"), name)
        setattr(sys.modules[package], name, value)  # the next use is a plain attribute
        return value

    def __dir__() -> list[str]:
        return sorted(set(vars(sys.modules[package])) | set(homes))

    return __getattr__, __dir__
