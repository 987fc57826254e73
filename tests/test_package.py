"""Inspect the packages: documented public API, no heavy imports at import time."""

import importlib
import inspect
import pkgutil
import subprocess
import sys

import pytest

PACKAGES = ["qube_koopman.identify", "qube_koopman.sim", "qube_koopman.daq", "qube_koopman.firmware_protocol",
            "qube_koopman.design"]


def public_modules():
    for name in PACKAGES:
        pkg = importlib.import_module(name)
        yield pkg
        for info in pkgutil.walk_packages(pkg.__path__, prefix=f"{name}."):
            if any(part.startswith("_") for part in info.name.split(".")):
                continue
            yield importlib.import_module(info.name)


def test_every_public_function_and_class_is_documented():
    missing = []
    for module in public_modules():
        if not module.__doc__:
            missing.append(module.__name__)
        for name, obj in vars(module).items():
            if name.startswith("_") or getattr(obj, "__module__", None) != module.__name__:
                continue
            if inspect.isfunction(obj) or inspect.isclass(obj):
                if not inspect.getdoc(obj):
                    missing.append(f"{module.__name__}.{name}")
                if inspect.isclass(obj):
                    for meth_name, meth in vars(obj).items():
                        if (not meth_name.startswith("_") and inspect.isfunction(meth)
                                and not inspect.getdoc(meth)):
                            missing.append(f"{module.__name__}.{name}.{meth_name}")
    assert not missing, f"undocumented: {missing}"


@pytest.mark.parametrize("module", ["qube_koopman.identify", "qube_koopman.sim", "qube_koopman.daq", "qube_koopman.identify.cli.reproduce",
                                    "qube_koopman.design", "qube_koopman.design.cli.design"])
def test_import_has_no_heavy_side_effects(module):
    code = (f"import sys, {module}; heavy = [m for m in ('cvxpy', 'control', 'matplotlib', 'rerun', 'mcap')"
            " if m in sys.modules]; print(','.join(heavy))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == ""


def test_estimators_follow_the_constructor_contract():
    from qube_koopman.identify import Arx, ClArx, ClEdmd, ClEdmdLstsq, ClEdmdSdp, Edmd

    for cls in (Edmd, ClEdmd, ClEdmdLstsq, ClEdmdSdp, Arx, ClArx):
        params = [p for p in inspect.signature(cls.__init__).parameters if p != "self"]
        est = cls(controller=None) if "controller" in params else cls()
        # every constructor argument is stored unchanged under its own name
        assert set(est.get_params()) == set(params)


def test_the_installed_package_list_covers_every_source_folder():
    """pyproject.toml lists the packages under the `qube_koopman` namespace by hand (package-dir
    maps the top-level folders): a new sub-package left out would be missing from the wheel."""
    import tomllib
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    tool = tomllib.loads((root / "pyproject.toml").read_text())["tool"]["setuptools"]
    folders = {"qube_koopman." + str(init.parent.relative_to(root)).replace("/", ".")
               for top in tool["package-dir"].values() for init in (root / top).rglob("__init__.py")}
    assert set(tool["packages"]) == folders
    for name, folder in tool["package-dir"].items():
        assert name == f"qube_koopman.{folder}"
        assert importlib.import_module(name).__file__ == str(root / folder / "__init__.py")


def test_imports_point_one_way_nothing_below_design_imports_it():
    """DESIGN.md: firmware_protocol <- sim <- daq <- identify <- design; design consumes models and
    writes controllers, so no package below it may import it (not even lazily, inside a function)."""
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    offenders = [str(path.relative_to(root)) for top in ("firmware_protocol", "sim", "daq", "identify")
                 for path in (root / top).rglob("*.py") if "qube_koopman.design" in path.read_text()]
    assert not offenders
