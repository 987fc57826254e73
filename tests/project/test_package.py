"""Inspect the packages: documented public API, no heavy imports at import time."""

import importlib
import inspect
import subprocess
import sys

import pytest
from _public_api import public_modules, public_names


def test_every_public_function_and_class_is_documented():
    missing = [module.__name__ for module in public_modules() if not module.__doc__]
    missing += [name for name, obj in public_names() if not inspect.getdoc(obj)]
    assert not missing, f"undocumented: {missing}"


@pytest.mark.parametrize(
    "module",
    [
        "qube_koopman.identify",
        "qube_koopman.sim",
        "qube_koopman.daq",
        "qube_koopman.reproduce.cli.reproduce",
        "qube_koopman.design",
        "qube_koopman.design.cli.design",
    ],
)
def test_import_has_no_heavy_side_effects(module):
    code = (
        f"import sys, {module}; heavy = [m for m in ('cvxpy', 'control', 'matplotlib', 'rerun', 'mcap')"
        " if m in sys.modules]; print(','.join(heavy))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == ""


def test_the_installed_package_list_covers_every_source_folder():
    """pyproject.toml lists the packages under the `qube_koopman` namespace by hand (package-dir
    maps the top-level folders): a new sub-package left out would be missing from the wheel."""
    import tomllib
    from pathlib import Path

    root = Path(__file__).resolve().parents[2]
    tool = tomllib.loads((root / "pyproject.toml").read_text())["tool"]["setuptools"]
    folders = {
        "qube_koopman." + str(init.parent.relative_to(root)).replace("/", ".")
        for top in tool["package-dir"].values()
        for init in (root / top).rglob("__init__.py")
    }
    assert set(tool["packages"]) == folders
    for name, folder in tool["package-dir"].items():
        assert name == f"qube_koopman.{folder}"
        assert importlib.import_module(name).__file__ == str(root / folder / "__init__.py")


def test_imports_point_one_way_nothing_below_design_imports_it():
    """Dependencies point one way, firmware_protocol <- sim <- daq <- identify <- design; design consumes models and
    writes controllers, so no package below it may import it (not even lazily, inside a function)."""
    from pathlib import Path

    root = Path(__file__).resolve().parents[2]
    offenders = [
        str(path.relative_to(root))
        for top in ("firmware_protocol", "sim", "daq", "identify")
        for path in (root / top).rglob("*.py")
        if "qube_koopman.design" in path.read_text()
    ]
    assert not offenders


def test_core_imports_no_other_package_of_the_toolkit():
    """core is the lowest layer: every package may import it, it imports none of them."""
    from pathlib import Path

    root = Path(__file__).resolve().parents[2]
    offenders = [
        str(path.relative_to(root))
        for path in (root / "core").rglob("*.py")
        if any(
            f"qube_koopman.{top}" in path.read_text()
            for top in ("firmware_protocol", "sim", "daq", "identify", "design", "reproduce")
        )
    ]
    assert not offenders


# The packages from the lowest layer up: each may import those before it, none after it.
LAYERS = ("core", "firmware_protocol", "sim", "daq", "identify", "design")
# Applications above identify, beside design: they import the layers, and nothing imports them.
APPLICATIONS = ("reproduce",)


def _modules(*tops):
    """(path, parsed module) of every source file of the packages ``tops``."""
    import ast
    from pathlib import Path

    root = Path(__file__).resolve().parents[2]
    return [
        (path.relative_to(root), ast.parse(path.read_text()))
        for top in tops
        for path in sorted((root / top).rglob("*.py"))
    ]


def test_every_import_points_down_the_layers():
    """core imports none of the other packages, firmware_protocol only core, ... design any (imports inside
    functions count: a lazy import upward is still a cycle)."""
    import ast

    offenders = []
    for path, tree in _modules(*LAYERS, *APPLICATIONS):
        top = path.parts[0]
        above = (LAYERS[LAYERS.index(top) + 1 :] if top in LAYERS else ("design",)) + APPLICATIONS
        for node in ast.walk(tree):
            names = (
                [a.name for a in node.names]
                if isinstance(node, ast.Import)
                else [node.module]
                if isinstance(node, ast.ImportFrom) and node.module
                else []
            )
            for name in names:
                parts = name.split(".")
                if parts[0] == "qube_koopman" and len(parts) > 1 and parts[1] in above and parts[1] != top:
                    offenders.append(f"{path}:{node.lineno} imports {name}")
    assert not offenders


def test_the_applications_share_no_command_helper_of_identify_cli():
    """identify.cli is identify's own commands; what design and reproduce share with them lives in the lowest
    package that owns it (identify.command_warnings, identify.report.figure_options; core for the toolkit)."""
    import ast

    offenders = []
    for path, tree in _modules(*(top for top in LAYERS + APPLICATIONS if top != "identify")):
        for node in ast.walk(tree):
            names = (
                [a.name for a in node.names]
                if isinstance(node, ast.Import)
                else [node.module]
                if isinstance(node, ast.ImportFrom) and node.module
                else []
            )
            offenders += [
                f"{path}:{node.lineno} imports {name}"
                for name in names
                if name == "qube_koopman.identify.cli" or name.startswith("qube_koopman.identify.cli.")
            ]
    assert not offenders


#: Base names two modules may share (each with its reason; at most two): none today.
SHARED_MODULE_NAMES: dict[str, str] = {}


def _shared_module_names(root, tops) -> list[str]:
    """Base names that two modules of the packages ``tops`` under ``root`` share, ``__init__.py`` aside: a
    search by name would land in the wrong one. A command (``cli/<x>.py``) may share the name of its
    concept's module (``<x>.py``), not another command's."""
    from collections import defaultdict

    found: dict[tuple[str, bool], list[str]] = defaultdict(list)
    for top in tops:
        for path in sorted((root / top).rglob("*.py")):
            if path.name != "__init__.py":
                found[path.name, path.parent.name == "cli"].append(path.relative_to(root).as_posix())
    return [
        f"{name}: {', '.join(paths)}"
        for (name, _), paths in sorted(found.items())
        if len(paths) > 1 and name not in SHARED_MODULE_NAMES
    ]


def test_no_two_modules_share_a_name():
    from pathlib import Path

    assert len(SHARED_MODULE_NAMES) <= 2
    assert not _shared_module_names(Path(__file__).resolve().parents[2], LAYERS + APPLICATIONS)


def test_the_module_name_check_finds_what_it_is_for(tmp_path):
    for module in (
        "a/qube.py",
        "b/sub/qube.py",  # two modules of one name: found
        "a/export.py",
        "a/cli/export.py",  # a command beside its concept: the convention
        "a/cli/run.py",
        "b/cli/run.py",  # two commands of one name: found
        "a/__init__.py",
        "b/__init__.py",
    ):
        (tmp_path / module).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / module).write_text("")
    assert _shared_module_names(tmp_path, ("a", "b")) == [
        "qube.py: a/qube.py, b/sub/qube.py",
        "run.py: a/cli/run.py, b/cli/run.py",
    ]


#: The most lines a package's __init__.py holds: it lists and re-exports, the code lives in modules.
MAX_INIT_LINES = 100


def _long_inits(root) -> list[str]:
    """Every __init__.py under ``root`` (hidden folders and build output aside) longer than MAX_INIT_LINES."""
    found = []
    for path in sorted(root.rglob("__init__.py")):
        relative = path.relative_to(root)
        if relative.parts[0] in ("build", "dist") or any(
            part.startswith((".", "_build")) or part.endswith(".egg-info") for part in relative.parts[:-1]
        ):
            continue
        n = len(path.read_text().splitlines())
        if n > MAX_INIT_LINES:
            found.append(f"{relative}: {n} lines")
    return found


def test_no_package_init_is_over_100_lines():
    from pathlib import Path

    offenders = _long_inits(Path(__file__).resolve().parents[2])
    assert not offenders, f"an __init__.py only re-exports (at most {MAX_INIT_LINES} lines): {offenders}"


def test_the_init_length_check_finds_what_it_is_for(tmp_path):
    (tmp_path / "pkg" / "sub").mkdir(parents=True)
    (tmp_path / ".venv" / "lib").mkdir(parents=True)
    (tmp_path / "pkg" / "__init__.py").write_text("x = 1\n" * 100)
    (tmp_path / "pkg" / "sub" / "__init__.py").write_text("x = 1\n" * 101)
    (tmp_path / ".venv" / "lib" / "__init__.py").write_text("x = 1\n" * 500)
    (tmp_path / "build" / "lib").mkdir(parents=True)  # a wheel's build output, a stale copy of the package
    (tmp_path / "build" / "lib" / "__init__.py").write_text("x = 1\n" * 500)
    assert _long_inits(tmp_path) == ["pkg/sub/__init__.py: 101 lines"]


#: The functions of identify/workflow.py, identify/model_selection, identify/uncertainty and identify/cli: at most
#: this many lines and parameters (more: an options object, or stage functions of their own).
MAX_FUNCTION_LINES, MAX_PARAMETERS = 80, 8


def _long_functions(tree, path) -> list[str]:
    """Functions (and methods, ``self``/``cls`` not counted) longer than MAX_FUNCTION_LINES or taking
    more than MAX_PARAMETERS parameters."""
    import ast

    found = []
    for node in ast.walk(tree):
        if not isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            continue
        args = node.args
        params = [*args.posonlyargs, *args.args, *args.kwonlyargs] + [a for a in (args.vararg, args.kwarg) if a]
        n_params = len([p for p in params if p.arg not in ("self", "cls")])
        n_lines = node.end_lineno - node.lineno + 1
        if n_lines > MAX_FUNCTION_LINES or n_params > MAX_PARAMETERS:
            found.append(f"{path}:{node.lineno} {node.name}: {n_lines} lines, {n_params} parameters")
    return found


@pytest.mark.parametrize("folder", ["identify/uncertainty", "identify/model_selection", "identify/cli"])
def test_the_functions_of_identify_s_stages_are_short_and_take_few_parameters(folder):
    # The search's settings come in one SearchSettings and the sweep's in one SweepOptions; the search's
    # stages (statistics shared, screens, full evaluations) and qube-calibrate's (checks, fit, provenance,
    # validation) are functions of their own.
    offenders = [hit for path, tree in _modules(folder) for hit in _long_functions(tree, path)]
    assert not offenders


def test_the_identify_workflow_functions_are_short_and_take_few_parameters():
    # identify_and_score's settings come in one IdentifyOptions, and its stages (fit, intervals, model file,
    # test scores, K-step predictions) are functions of their own.
    offenders = [
        hit
        for path, tree in _modules("identify")
        if path.as_posix() == "identify/workflow.py"
        for hit in _long_functions(tree, path)
    ]
    assert not offenders


def test_the_function_size_check_finds_what_it_is_for():
    import ast

    many = "def many(self, a, b, c, d, e, f, g, h, *, i):\n    return a\n"
    eight = "def eight(self, a, b, c, d, e, f, g, h):\n    return a\n"
    long = "def long():\n" + "    x = 1\n" * 79 + "    return x\n"
    assert _long_functions(ast.parse(many + eight + long), "m.py") == [
        "m.py:1 many: 2 lines, 9 parameters",
        "m.py:5 long: 81 lines, 0 parameters",
    ]


def test_identify_reads_logs_in_its_data_package_only():
    """Within identify, only identify/data imports daq (to read episode logs); the estimators, models,
    model selection and commands get logs from it, and nothing in identify imports daq's real-time parts."""
    import ast

    offenders = []
    for path, tree in _modules("identify"):
        for node in ast.walk(tree):
            names = (
                [a.name for a in node.names]
                if isinstance(node, ast.Import)
                else [node.module]
                if isinstance(node, ast.ImportFrom) and node.module
                else []
            )
            for name in names:
                if name.startswith("qube_koopman.daq") and (
                    path.parts[1] != "data" or not name.startswith("qube_koopman.daq.log")
                ):
                    offenders.append(f"{path}:{node.lineno} imports {name}")
    assert not offenders


def test_every_command_is_written_with_the_toolkit_of_core():
    """One way to write a command: core.cli, core.console and core.command hold the toolkit (the
    parser and argument types, logging and progress, CliError and run_command), no other package
    defines a piece of it again (nor the _Fail or fail() commands had of their own), and every
    command's entry point runs its work through run_command."""
    import ast
    import tomllib
    from pathlib import Path

    from qube_koopman.core import cli, command, console

    toolkit = {*cli.__all__, *console.__all__, *command.__all__, "_Fail", "fail"}
    again = [
        f"{path}:{node.lineno} defines {node.name}"
        for path, tree in _modules(*LAYERS[1:], *APPLICATIONS)
        for node in ast.walk(tree)
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)) and node.name in toolkit
    ]
    assert not again

    root = Path(__file__).resolve().parents[2]
    scripts = tomllib.loads((root / "pyproject.toml").read_text())["project"]["scripts"]
    assert len(scripts) == 9
    without = []
    for name, target in scripts.items():
        module, function = target.removeprefix("qube_koopman.").split(":")
        tree = ast.parse((root / (module.replace(".", "/") + ".py")).read_text())
        main = next(node for node in tree.body if isinstance(node, ast.FunctionDef) and node.name == function)
        calls = {
            node.func.id for node in ast.walk(main) if isinstance(node, ast.Call) and isinstance(node.func, ast.Name)
        }
        if "run_command" not in calls:
            without.append(name)
    assert not without, f"commands not run through core.command.run_command: {without}"


def _ruff() -> list[str]:
    """How to run ruff (in the test extra: missing, it is an incomplete install, which fails rather than skips)."""
    import importlib.util
    import shutil

    if importlib.util.find_spec("ruff") is not None:
        return [sys.executable, "-m", "ruff"]
    if shutil.which("ruff"):
        return [str(shutil.which("ruff"))]
    pytest.fail('ruff is not installed: pip install -e ".[test]"')


def _ruff_run(*args: str) -> subprocess.CompletedProcess:
    """ruff run from the repository's root with its settings (pyproject.toml's [tool.ruff])."""
    from pathlib import Path

    root = Path(__file__).resolve().parents[2]
    return subprocess.run(
        [*_ruff(), *args[:1], "--no-cache", "--config", str(root / "pyproject.toml"), *args[1:]],
        cwd=root,
        capture_output=True,
        text=True,
        timeout=300,
    )


def _ruffed_files() -> list[str]:
    """The Python files ``ruff check .`` reads, relative to the repository's root."""
    from pathlib import Path

    root = Path(__file__).resolve().parents[2]
    shown = _ruff_run("check", "--show-files", ".")
    assert shown.returncode == 0, shown.stdout[-2000:] + shown.stderr[-2000:]
    files = [Path(line.strip()) for line in shown.stdout.splitlines() if line.strip()]
    return [str(path.relative_to(root)) for path in files if path.suffix in (".py", ".pyi", ".ipynb")]


def test_ruff_reads_the_whole_repository_and_ignores_no_folder():
    """``ruff check .`` reads every top folder that holds Python (the tests, benchmarks, the example and
    docs/conf.py as well as the packages), and pyproject.toml's per-file-ignores name single files, each
    with a reason beside it, never a folder or a pattern that would silence many files at once."""
    import tomllib
    from pathlib import Path

    root = Path(__file__).resolve().parents[2]
    holding = {
        top.name
        for top in root.iterdir()
        if top.is_dir() and not top.name.startswith(".") and top.name not in ("build", "dist")
        if not top.name.endswith(".egg-info") and any(top.rglob("*.py"))
    }
    tops = {Path(name).parts[0] for name in _ruffed_files()}
    assert {*LAYERS, *APPLICATIONS, "tests", "bench", "examples", "docs"} <= holding <= tops, (holding, tops)
    ignores = tomllib.loads((root / "pyproject.toml").read_text())["tool"]["ruff"]["lint"].get("per-file-ignores", {})
    assert all((root / name).is_file() for name in ignores), sorted(ignores)


def test_ruff_formats_the_repository_as_it_is():
    """The formatter (``ruff format``, pyproject.toml's [tool.ruff]) would change none of the files the
    linter reads: the packages, the tests, the benchmarks, the tools and the example."""
    checked = _ruff_run("format", "--check", *_ruffed_files())
    assert checked.returncode == 0, "run `ruff format` on:\n" + checked.stdout[-8000:] + checked.stderr[-2000:]


def test_ruff_finds_nothing_in_the_repository():
    """The linter, configured in pyproject.toml ([tool.ruff]), reports nothing on the whole repository.
    ruff is in the test extra: missing, it is an incomplete install, which fails rather than skips."""
    checked = _ruff_run("check", ".")
    assert checked.returncode == 0, checked.stdout[-8000:] + checked.stderr[-2000:]


def test_mypy_finds_nothing_in_the_packages(tmp_path):
    """The type checker, configured in pyproject.toml ([tool.mypy]), reports nothing on the packages.

    mypy cannot follow setuptools' editable finder, so the package folders are linked into
    ``<tmp>/qube_koopman/`` and checked there as the ``qube_koopman`` package. Its cache lives in the
    user's cache (``core.files.cache_root() / "mypy"``), shared by every run on the machine: a cold run
    takes about ten seconds, a warm one under a second."""
    import importlib.util
    from pathlib import Path

    from qube_koopman.core.files import cache_root

    if importlib.util.find_spec("mypy") is None:  # in the test extra, as ruff: missing is an incomplete install
        pytest.fail('mypy is not installed: pip install -e ".[test]"')
    root = Path(__file__).resolve().parents[2]
    tree = tmp_path / "qube_koopman"
    tree.mkdir()
    for top in (*LAYERS, *APPLICATIONS):
        (tree / top).symlink_to(root / top, target_is_directory=True)
    checked = subprocess.run(
        [
            sys.executable,
            "-m",
            "mypy",
            "-p",
            "qube_koopman",
            "--explicit-package-bases",
            "--config-file",
            str(root / "pyproject.toml"),
            "--cache-dir",
            str(cache_root() / "mypy"),
        ],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        timeout=900,
    )
    assert checked.returncode == 0, checked.stdout[-8000:] + checked.stderr[-2000:]


def test_the_tests_are_grouped_as_the_packages_are():
    """tests/<package>/ holds each package's tests (docs/ the documentation's runnable blocks, project/
    the checks of the whole repository); shared fixtures and helpers sit in tests/ itself."""
    from pathlib import Path

    tests = Path(__file__).resolve().parents[1]
    folders = {p.name for p in tests.iterdir() if p.is_dir() and not p.name.startswith((".", "_"))}
    assert folders == {*LAYERS, *APPLICATIONS, "docs", "project"}
    assert not list(tests.glob("test_*.py")), "a test module outside its package's folder"
    assert all(list(tests.glob(f"{folder}/test_*.py")) for folder in folders)


#: Keys only a model file holds: a subscript or ``.get`` with one reads the file's dict, not the typed model.
MODEL_FILE_KEYS = {
    "plant",
    "closed_loop",
    "plant_members",
    "uncertainty",
    "held_out",
    "error_spectra",
    "disturbance",
    "lifting",
}


def _model_dict_reads(tree, path) -> list[str]:
    """Every ``model[...]`` / ``model.get(...)`` (``model`` a name or an attribute) and every subscript or ``.get``
    with a model file's key in ``tree``: the reads of a model file as a dict."""
    import ast

    def is_model(node) -> bool:
        return (isinstance(node, ast.Name) and node.id == "model") or (
            isinstance(node, ast.Attribute) and node.attr == "model"
        )

    def is_key(node) -> bool:
        return isinstance(node, ast.Constant) and node.value in MODEL_FILE_KEYS

    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Subscript) and (is_model(node.value) or is_key(node.slice)):
            found.append(f"{path}:{node.lineno} {ast.unparse(node)}")
        elif (
            isinstance(node, ast.Call)
            and isinstance(node.func, ast.Attribute)
            and node.func.attr == "get"
            and (is_model(node.func.value) or (node.args and is_key(node.args[0])))
        ):
            found.append(f"{path}:{node.lineno} {ast.unparse(node)}")
    return found


def test_design_reads_the_identified_model_by_its_attributes_never_as_a_dict():
    """design takes what identify fitted as one typed object (identify.models.identified.IdentifiedModel, what
    load_model returns): no ``model["plant"]``, ``model.get("controller")`` or ``held["measured"]`` in it."""
    # mpc_file reads the controller file of kind mpc, whose [disturbance] table shares its name with the model
    # file's entry: a TOML table read by key, not the model.
    offenders = [
        hit
        for path, tree in _modules("design")
        if not str(path).endswith("mpc_file.py")
        for hit in _model_dict_reads(tree, path)
    ]
    assert not offenders


def test_the_model_dict_check_finds_what_it_is_for():
    import ast

    code = (
        'a = model["plant"]\nb = report.model.get("controller")\nc = data.get("uncertainty")\n'
        'd = held["held_out"]\ne = model.plant\nf = out["predicted"]\n'
    )
    assert _model_dict_reads(ast.parse(code), "m.py") == [
        "m.py:1 model['plant']",
        "m.py:2 report.model.get('controller')",
        "m.py:3 data.get('uncertainty')",
        "m.py:4 held['held_out']",
    ]
