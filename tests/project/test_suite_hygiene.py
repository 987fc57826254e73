"""The suite's own guards (tests/conftest.py): leftover processes are seen, the dataset is required in CI."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

import pytest
from conftest import _descendants

pytest_plugins = ["pytester"]


def test_an_orphaned_grandchild_is_still_seen_as_the_suites():
    # The wrapper exits at once; its child (a stand-in for a server) lives on, re-parented to
    # this process (a child subreaper for the session), so the end-of-session check names it.
    wrapper = subprocess.Popen(["sh", "-c", "sleep 30 & echo $!"], stdout=subprocess.PIPE, text=True)
    pid = int(wrapper.stdout.readline())
    wrapper.wait(10)
    try:
        # Seen with its command line: while the forked shell execs sleep, /proc gives an empty
        # one (a loaded run read it in that window once), so wait for it like for the pid, and
        # check the command line that was read rather than reading /proc again mid-exec.
        deadline = time.monotonic() + 5
        while not (command := _descendants(os.getpid()).get(pid)):
            assert time.monotonic() < deadline, "the orphaned grandchild is not counted"
            time.sleep(0.05)
        assert "sleep 30" in command
    finally:
        os.kill(pid, signal.SIGKILL)
        os.waitpid(pid, 0)  # re-parented to this process: reap it here
    assert pid not in _descendants(os.getpid())


def test_a_missing_dataset_fails_under_ci(pytester, monkeypatch):
    pytester.makeconftest(open(os.path.join(os.path.dirname(os.path.dirname(__file__)), "conftest.py")).read())
    pytester.makepyfile("def test_needs(qube_dataset):\n    pass\n")
    monkeypatch.setenv("QUBE_DATASET_DIR", str(pytester.path / "none"))
    monkeypatch.setenv("CI", "true")
    pytester.runpytest("-p", "no:cacheprovider").assert_outcomes(errors=1)
    monkeypatch.setenv("CI", "")
    pytester.runpytest("-p", "no:cacheprovider").assert_outcomes(skipped=1)


@pytest.mark.slow  # a pytest run of its own with two loky workers: about 5 s
def test_joblib_workers_are_stopped_without_tracebacks_after_the_summary(pytester):
    # A memmapped array a worker still holds when its Parallel call ends leaves joblib a folder
    # to free at exit; stopping the trackers first made a fresh tracker print KeyError tracebacks
    # after the summary (or the old one warn of a leaked folder). conftest frees it before.
    pytester.makeconftest(open(os.path.join(os.path.dirname(os.path.dirname(__file__)), "conftest.py")).read())
    pytester.makepyfile("""
        import numpy as np
        from joblib import Parallel, delayed

        _kept = []  # in each worker: the memmap stays open after the call

        def keep(a):
            _kept.append(a)
            return float(a[0])

        def test_memmapped():
            big = np.ones(300_000)
            assert sum(Parallel(n_jobs=2, max_nbytes="1K")(delayed(keep)(big) for i in range(4))) == 4
    """)
    # Not runpytest_subprocess: it reads stderr when pytest exits, before the tracker has written
    # there; a pipe is read to its end, when the last process holding it (the tracker) is gone.
    # The helper modules whose fixtures the conftest registers (pytest_plugins) stay in tests/.
    tests = os.path.dirname(os.path.dirname(__file__))
    proc = subprocess.run(
        [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider"],
        cwd=pytester.path,
        env=dict(os.environ, PYTHONPATH=os.pathsep.join([tests, os.environ.get("PYTHONPATH", "")])),
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 0 and "1 passed" in proc.stdout, proc.stdout + proc.stderr
    err = proc.stderr + proc.stdout.split("1 passed")[-1]
    assert "Traceback" not in err and "KeyError" not in err and "leaked" not in err, err


def test_what_the_readme_blocks_write_in_a_clone_is_ignored_by_git():
    import re
    import subprocess

    from readme_blocks import BLOCKS, REPO, expected_exit

    outputs = {
        m.group(1)
        for block in BLOCKS
        for _, line in block
        if expected_exit(line) == 0
        for m in re.finditer(r"--(?:out|report|rerun|rerun-save)\s+([\w./-]+)", line.split("#")[0])
    }
    assert "qube_logs" in outputs and "designed.toml" in outputs
    tracked = subprocess.run(["git", "check-ignore", *sorted(outputs)], cwd=REPO, capture_output=True, text=True)
    assert set(tracked.stdout.split()) == outputs, sorted(outputs - set(tracked.stdout.split()))


def test_the_longest_files_scheduled_first_exist_and_run_first():
    from conftest import LONGEST_FIRST

    root = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    missing = [path for path in LONGEST_FIRST if not os.path.isfile(os.path.join(root, path))]
    assert not missing, f"tests/conftest.py LONGEST_FIRST names files that are gone: {missing}"
    listed = subprocess.run(
        [
            sys.executable,
            "-m",
            "pytest",
            "--collect-only",
            "-q",
            "-n",
            "0",
            "-p",
            "no:cacheprovider",
            "tests/project/test_suite_hygiene.py",
            LONGEST_FIRST[-1],
        ],
        cwd=root,
        capture_output=True,
        text=True,
        timeout=120,
    ).stdout.splitlines()
    files = [line.split("::")[0] for line in listed if "::" in line]
    assert files and files[0] == LONGEST_FIRST[-1], files[:3]
