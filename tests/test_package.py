"""Inspect the packages: documented public API, no heavy imports at import time."""

import importlib
import inspect
import pkgutil
import subprocess
import sys

import pytest

PACKAGES = ["identify", "sim", "daq", "firmware_protocol"]


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


@pytest.mark.parametrize("module", ["identify", "sim", "daq", "identify.cli.reproduce"])
def test_import_has_no_heavy_side_effects(module):
    code = (f"import sys, {module}; heavy = [m for m in ('cvxpy', 'control', 'matplotlib', 'rerun', 'mcap')"
            " if m in sys.modules]; print(','.join(heavy))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == ""


def test_estimators_follow_the_constructor_contract():
    from identify import Arx, ClArx, ClEdmd, ClEdmdLstsq, ClEdmdSdp, Edmd

    for cls in (Edmd, ClEdmd, ClEdmdLstsq, ClEdmdSdp, Arx, ClArx):
        params = [p for p in inspect.signature(cls.__init__).parameters if p != "self"]
        est = cls(controller=None) if "controller" in params else cls()
        # every constructor argument is stored unchanged under its own name
        assert set(est.get_params()) == set(params)
