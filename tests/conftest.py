"""Shared fixtures: where the paper's QUBE-Servo dataset lives; no process outlives the suite."""

from __future__ import annotations

import ctypes
import os
import sys
import time
from pathlib import Path

import pytest
from hypothesis import settings as hypothesis_settings

# Property tests draw the same examples every run (derandomized): a suite that failed on a fresh draw
# one run in a few would block everyone's work for a bug nobody's change made (a damaged-log property
# did, at byte 25926 of its file). QUBE_FUZZ_EXPLORE=1 draws fresh ones, as a developer's run that
# looks for more; a failure it finds becomes a fixed example in the test.
hypothesis_settings.register_profile("suite", derandomize=True, database=None)
hypothesis_settings.register_profile("explore", derandomize=False)
hypothesis_settings.load_profile("explore" if os.environ.get("QUBE_FUZZ_EXPLORE") == "1" else "suite")

# Bytecode is cached during the suite even where the environment turns it off (PYTHONDONTWRITEBYTECODE,
# set on some CI images): each pytest-xdist worker otherwise rewrites every test module's asserts and
# compiles the package from source (7 s a worker of the 12 s collection), and each of the suite's
# few hundred command subprocesses compiles the modules it imports again (0.2 s of a 0.7 s start).
# Read here, at the conftest's import in the controller, before the workers start: they and every
# subprocess inherit the environment. The files go where Python puts them by default (__pycache__,
# ignored by git); the tests judge the same code either way.
if os.environ.pop("PYTHONDONTWRITEBYTECODE", None) is not None:
    sys.dont_write_bytecode = False

# Fixtures the tests of several files share: the built firmware core and the environment of the
# emulated bridge's subprocesses (bridge_helpers), the Uno firmware built for simavr (avr_helpers),
# the dask cluster tests' logs (_cluster_logs), the documentation blocks' clone (readme_blocks), the
# commands' input folder and stubbed long work (_command_stubs). Registered once here, not imported
# by name into each test module: an imported fixture is a second definition per module (a
# session-scoped value built again) and the test's parameter of the same name shadows the import.
pytest_plugins = ["bridge_helpers", "avr_helpers", "_cluster_logs", "readme_blocks", "_command_stubs"]

DATASET_ENV = "QUBE_DATASET_DIR"
DEFAULT_DATASET = Path(__file__).resolve().parents[2] / "shared" / "datasets" / "qube_servo_20230828"
SOFT_DATASET_ENV = "QUBE_SOFT_DATASET_DIR"
DEFAULT_SOFT_DATASET = DEFAULT_DATASET.parent / "qube_servo_20230915_soft"
DATASET_SOURCE = (
    "the paper's QUBE-Servo dataset (public repository decargroup/closed_loop_koopman, "
    "folder dataset/controller_20230828, MIT licence)"
)


@pytest.fixture(autouse=True, scope="session")
def _own_cache_folder(tmp_path_factory):
    """The search's twin probe sets cached in the session's temporary folder, not the user's.

    One folder for all of pytest-xdist's workers (their own temporary folders share a parent): a
    probe set one worker simulated (several seconds each) is read back by the others, as
    concurrent commands share the user's cache (written whole and renamed: no partial file).
    """
    base = tmp_path_factory.getbasetemp()
    folder = base.parent / "qube-koopman-probes" if os.environ.get("PYTEST_XDIST_WORKER") else base / "probes"
    folder.mkdir(exist_ok=True)
    os.environ["QUBE_KOOPMAN_PROBE_CACHE"] = str(folder)
    yield


@pytest.fixture(autouse=True, scope="session")
def _ctrl_c_as_python_sets_it():
    """SIGINT raises KeyboardInterrupt, as Python sets it up when it starts from a terminal.

    A shell without job control starts a background command (``tools/loaded_ci.sh &``, a CI step
    run with ``&``) with SIGINT ignored, and Python keeps an ignored SIGINT ignored: the tests that
    send the process a SIGINT to stop a command would then see nothing arrive. The commands'
    handling of Ctrl-C is what they check, not how the suite was started.
    """
    import signal

    before = signal.getsignal(signal.SIGINT)
    if before == signal.SIG_IGN:
        signal.signal(signal.SIGINT, signal.default_int_handler)
    yield
    if before == signal.SIG_IGN:
        signal.signal(signal.SIGINT, before)


def pytest_xdist_auto_num_workers(config: pytest.Config) -> int:
    """``-n auto``: one worker per CPU this process may run on.

    pytest-xdist's own count asks psutil (which the test extra brings) for physical cores,
    one on a 2-vCPU machine with SMT, and ignores a restricted CPU set; the affinity mask
    is what the scheduler will actually give the suite.
    """
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1


#: The files that take longest on 2 cores (half a minute or more each in the suite), longest first. They
#: are scheduled first, then every other file in collection order (pyproject's addopts turn off
#: pytest-xdist's own reordering, by number of tests, which put these few-test files last and left
#: one core idle for minutes at the end). xdist gives a worker the next file when it runs low, so
#: the long ones started first end with the short ones filling in. A test checks the paths exist.
LONGEST_FIRST = [
    "tests/docs/test_readme_design.py",
    "tests/identify/test_calibrate_dataset.py",
    "tests/docs/test_readme.py",
    "tests/project/test_lowest_versions.py",
    "tests/docs/test_readme_calibrate.py",
    "tests/identify/test_search.py",
    "tests/identify/test_calibrate.py",
    "tests/design/test_design.py",
    "tests/sim/test_twin_equivalence.py",
    "tests/docs/test_docs.py",
    "tests/core/test_rerun_recordings.py",
]


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """The longest files first (:data:`LONGEST_FIRST`), the others after them in collection order."""
    rank = {path: i for i, path in enumerate(LONGEST_FIRST)}
    items.sort(key=lambda item: rank.get(item.nodeid.split("::")[0], len(rank)))  # stable: the rest keep order


def dataset_dir() -> Path | None:
    """The dataset folder: $QUBE_DATASET_DIR, else ../shared/datasets/qube_servo_20230828."""
    path = Path(os.environ.get(DATASET_ENV, DEFAULT_DATASET))
    return path if path.is_dir() and any(path.glob("*.csv")) else None


@pytest.fixture(scope="session")
def qube_dataset() -> Path:
    """Path of the dataset folder; skips with a message saying where the data comes from."""
    path = dataset_dir()
    if path is None:
        # CI must run them: a missing dataset there is a broken setup, not a reason to skip.
        fail = pytest.fail if os.environ.get("CI", "").lower() == "true" else pytest.skip
        fail(f"dataset not found: set {DATASET_ENV} or place {DATASET_SOURCE} at {DEFAULT_DATASET}")
    return path


@pytest.fixture(scope="session")
def soft_logs(tmp_path_factory) -> Path:
    """The 10 real episodes of the same rig under the softer second controller, imported into MCAP logs."""
    from qube_koopman.daq.legacy_csv import legacy_episode, load_legacy_controller
    from qube_koopman.daq.log import write_episode
    from qube_koopman.daq.log.names import log_path

    folder = Path(os.environ.get(SOFT_DATASET_ENV, DEFAULT_SOFT_DATASET))
    files = sorted(folder.glob("*.csv")) if folder.is_dir() else []
    if not files:
        fail = pytest.fail if os.environ.get("CI", "").lower() == "true" else pytest.skip
        fail(f"soft-controller dataset not found: set {SOFT_DATASET_ENV} or place it at {DEFAULT_SOFT_DATASET}")
    out = tmp_path_factory.mktemp("soft_logs")
    controller = load_legacy_controller(folder / "controller.toml")
    for path in files:
        write_episode(log_path(out, path.stem), legacy_episode(path, controller))
    return out


@pytest.fixture(scope="session")
def qube_csv_files(qube_dataset: Path) -> list[Path]:
    """The dataset's 48 episode files, sorted by name (the paper's split order)."""
    return sorted(qube_dataset.glob("*.csv"))


def made_once(tmp_path_factory, name: str, make) -> Path:
    """The folder ``name`` that ``make(folder)`` fills, made once for the whole session.

    pytest-xdist runs each worker in a process of its own, where a session-scoped fixture is made
    again: every worker imported the dataset (6 s) and ran ``qube-reproduce`` (20 s) when files
    needing them went to both. The workers' temporary folders share a parent; the first worker to
    need the folder makes it there under a lock, and the others wait for it and read it. Nothing in
    the suite writes into these folders (within one worker they were already shared by every test).
    """
    import fcntl

    root = tmp_path_factory.getbasetemp()
    if os.environ.get("PYTEST_XDIST_WORKER"):
        root = root.parent  # this run's workers' folders are gw0, gw1, ... in it
    folder, done = root / name, root / f"{name}.done"
    with open(root / f"{name}.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)  # released when the file closes, also if make raises
        if not done.exists():
            if folder.exists():  # a worker's make that failed left it half written
                import shutil

                shutil.rmtree(folder)
            folder.mkdir()
            make(folder)
            done.touch()
    return folder


@pytest.fixture(scope="session")
def qube_logs(qube_csv_files, tmp_path_factory) -> Path:
    """All 48 episodes imported into MCAP logs once per session (about 6 s), shared by the workers."""

    def make(out: Path) -> None:
        from qube_koopman.daq.legacy_csv import legacy_episode, load_legacy_controller
        from qube_koopman.daq.log import write_episode
        from qube_koopman.daq.log.names import log_path

        controller = load_legacy_controller(qube_csv_files[0].parent / "controller.toml")
        for path in qube_csv_files:
            write_episode(log_path(out, path.stem), legacy_episode(path, controller))

    return made_once(tmp_path_factory, "qube_logs", make)


@pytest.fixture(scope="module")
def small_set(qube_logs, tmp_path_factory) -> Path:
    """8 training and 4 test episodes of the real data (``train/`` and ``test/`` of a folder), for the
    qube-identify tests (tests/identify/test_identify_cli.py, test_figures.py)."""
    import shutil

    from qube_koopman.daq.log.names import find_logs

    logs = find_logs(qube_logs)
    root = tmp_path_factory.mktemp("small")
    for name, chosen in (("train", logs[:8]), ("test", logs[28:32])):
        (root / name).mkdir()
        for path in chosen:
            shutil.copy(path, root / name / path.name)
    return root


@pytest.fixture(scope="session")
def qube_reproduction_out(qube_logs, tmp_path_factory) -> Path:
    """``qube-reproduce qube --figures`` on the imported dataset, once per session: its output folder."""

    def make(out: Path) -> None:
        from qube_koopman.reproduce.cli.reproduce import main

        assert main(["qube", "--data", str(qube_logs), "--out", str(out), "--figures", "-q"]) == 0

    return made_once(tmp_path_factory, "qube_out", make)


@pytest.fixture(scope="session")
def qube_reproduction(qube_reproduction_out) -> tuple[dict, str]:
    """The session's ``qube-reproduce qube``: (qube.json, qube.md)."""
    import json

    out = qube_reproduction_out
    return json.loads((out / "qube.json").read_text()), (out / "qube.md").read_text()


@pytest.fixture
def legacy_folder(tmp_path):
    """A folder with one synthetic legacy CSV episode (tests/daq/test_legacy_import.py) and its controller.toml."""
    from _legacy_csv import GAINS_TOML, GOOD, write_synthetic_csv

    src = tmp_path / "src"
    src.mkdir()
    (src / "controller.toml").write_text(GAINS_TOML)
    write_synthetic_csv(src / f"{GOOD}.csv")
    return src


# --- no process started by the suite outlives it -------------------------------------------------

_PR_SET_CHILD_SUBREAPER = 36


def _become_subreaper() -> bool:
    """Let orphans of the suite's children be re-parented to this process, not to init (Linux)."""
    if not sys.platform.startswith("linux"):
        return False
    try:
        return ctypes.CDLL(None, use_errno=True).prctl(_PR_SET_CHILD_SUBREAPER, 1, 0, 0, 0) == 0
    except (OSError, AttributeError):
        return False


def _descendants(root: int) -> dict[int, str]:
    """Live (not zombie) descendants of ``root`` from /proc: {pid: command line}."""
    parent: dict[int, int] = {}
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            stat = (entry / "stat").read_text()
        except OSError:
            continue
        fields = stat[stat.rindex(")") + 2 :].split()
        if fields[0] != "Z":
            parent[int(entry.name)] = int(fields[1])
    found, frontier = {}, [root]
    while frontier:
        pid = frontier.pop()
        for child, ppid in parent.items():
            if ppid == pid and child not in found:
                try:
                    cmd = (Path("/proc") / str(child) / "cmdline").read_bytes().replace(b"\0", b" ").decode()
                except OSError:
                    cmd = "?"
                found[child] = cmd.strip()
                frontier.append(child)
    return found


def stop_library_daemons() -> set[int]:
    """Stop joblib's reusable loky workers; return the pids of the resource trackers left running.

    The workers are library daemons that live until their parent exits (identification runs
    its sweeps and searches through joblib); stopping them leaves only real leaks to be found.
    The executor is terminated, not only shut down, so that it frees its memmapping folders.
    The resource trackers of loky and multiprocessing are left to end with this process, as
    they do for a user: every ``Parallel`` call registers a folder with loky's tracker and an
    atexit handler that unregisters it, and an unregistration sent to a tracker stopped here
    would start a fresh one that does not know the folder (a ``KeyError`` traceback on stderr
    after pytest's summary). A tracker ends when this process closes its pipe.
    """
    if "joblib" not in sys.modules:
        return set()
    from multiprocessing import resource_tracker

    from joblib.externals.loky import reusable_executor
    from joblib.externals.loky.backend import resource_tracker as loky_tracker

    executor = reusable_executor._executor  # the last one, live or shut down; None if none was made
    if executor is not None:
        # joblib's executor frees its memmapping folders (and cancels their atexit handlers)
        getattr(executor, "terminate", executor.shutdown)()
    return {
        tracker._pid
        for tracker in (loky_tracker._resource_tracker, resource_tracker._resource_tracker)
        if getattr(tracker, "_pid", None) is not None
    }


@pytest.fixture(scope="session", autouse=True)
def no_process_outlives_the_suite():
    """At the end of the session, fail naming any process the suite started that still runs.

    This process becomes a child subreaper, so a grandchild whose parent died (a server
    started through a wrapper script) is still counted. Those found are then terminated.
    """
    if not Path("/proc/self/stat").exists():
        yield
        return
    before = set(_descendants(os.getpid()))
    _become_subreaper()
    yield
    before |= stop_library_daemons()  # the resource trackers end with this process
    time.sleep(0.3)  # a process started just now is forked by then
    deadline = time.monotonic() + 5  # give processes being stopped a moment to go
    left = {p: c for p, c in _descendants(os.getpid()).items() if p not in before}
    while left and time.monotonic() < deadline:
        time.sleep(0.1)
        left = {p: c for p, c in _descendants(os.getpid()).items() if p not in before}
    for pid in left:
        try:
            os.kill(pid, 15)
        except OSError:
            pass
    if left:
        pytest.fail(
            "processes started by the test suite outlived it: "
            + "; ".join(f"pid {p}: {c}" for p, c in sorted(left.items())),
            pytrace=False,
        )
