"""``qube-run --n-jobs`` (daq.parallel): episodes in worker processes are a serial run's, timing apart.

A run with ``--n-jobs 2`` and the same run with ``--n-jobs 1`` must leave the same logs: the
same names but for their start times, in the same order, every sample and every metadata field
equal, except the host's timing (the start time, each tick's lateness and compute time, the
status record's timing statistics). Compared twice: through the project's reader, and record
by record in the MCAP files themselves.
"""

from __future__ import annotations

import copy
import os
import re
import signal
import subprocess
import sys
import time
from dataclasses import fields
from pathlib import Path

import numpy as np
import pytest

from qube_koopman.daq.backends import SimBackend
from qube_koopman.daq.cli.run import main
from qube_koopman.daq.log import read_episode
from qube_koopman.daq.log.names import LOG_SUFFIX, parse_episode_name
from qube_koopman.daq.log.schema import parse_schema, payload_dtype
from qube_koopman.sim.pendulum import SensorModel

REPO = Path(__file__).resolve().parents[2]
# Four short episodes; episode 2 reaches the 20 deg arm limit (a safety stop) in a worker.
RUN = ["--episodes", "4", "--duration", "2", "--seed", "13", "--theta-limit", "20"]
#: The host's timing: per sample, in the episode metadata, in the status record.
TIMING_SIGNALS = ("lateness", "compute_time")
TIMING_METADATA = {"qube.episode": {"start_time"}, "qube.status": {"timing"}}


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """The same run with one job and with two: {jobs: (folder, stdout)}."""
    out = {}
    for jobs in (1, 2):
        folder = tmp_path_factory.mktemp(f"jobs{jobs}")
        proc = subprocess.run(
            [sys.executable, "-m", "qube_koopman.daq.cli.run", *RUN, "--n-jobs", str(jobs), "--out", str(folder), "-q"],
            capture_output=True,
            text=True,
            timeout=120,
        )
        assert proc.returncode == 0, proc.stderr
        out[jobs] = folder, proc.stdout
    return out


def _logs(folder: Path) -> list[Path]:
    return sorted(folder.glob(f"*{LOG_SUFFIX}"))


def test_the_logs_have_the_same_names_but_their_start_times_in_the_same_order(runs):
    serial, parallel = (_logs(runs[jobs][0]) for jobs in (1, 2))
    assert len(serial) == 4
    seeds = [[parse_episode_name(p, LOG_SUFFIX).seeds for p in logs] for logs in (serial, parallel)]
    assert seeds[0] == seeds[1]  # sorted by name: the episodes in the order they ran
    stems = [{re.sub(r"^qube_\d{8}T\d{6}\.\d{3}", "", p.name) for p in logs} for logs in (serial, parallel)]
    assert stems[0] == stems[1]
    assert [read_episode(p).metadata.extra["episode_index"] for p in parallel] == [0, 1, 2, 3]


def test_every_sample_and_metadata_field_is_the_serial_runs(runs):
    statuses = []
    for a, b in zip(*(_logs(runs[jobs][0]) for jobs in (1, 2))):
        ea, eb = read_episode(a), read_episode(b)
        assert len(ea) == len(eb) and len(ea) > 0
        for name, values in ea.arrays().items():
            if name not in TIMING_SIGNALS:
                np.testing.assert_array_equal(eb.arrays()[name], values, err_msg=f"{b.name}: {name}")
        ma, mb = ({f.name: getattr(e.metadata, f.name) for f in fields(e.metadata)} for e in (ea, eb))
        for meta in (ma, mb):
            del meta["start_time"], meta["timing"]
            meta["controller"] = meta["controller"].as_dict()  # plain lists, not arrays
        assert ma == mb
        statuses.append(ea.metadata.status)
    assert statuses == ["complete", "complete", "aborted", "complete"]  # the safety stop ran in a worker


def _records(path: Path):
    """The file's metadata records (timing keys dropped) and its messages (timing fields zeroed)."""
    from mcap.reader import make_reader

    with path.open("rb") as f:
        reader = make_reader(f)
        metadata = [
            (m.name, {k: v for k, v in m.metadata.items() if k not in TIMING_METADATA.get(m.name, ())})
            for m in reader.iter_metadata()
        ]
        messages = list(reader.iter_messages())
    schema, channel, first = messages[0]
    samples = np.frombuffer(
        b"".join(m.data for _, _, m in messages), dtype=payload_dtype(parse_schema(schema.data.decode()))
    ).copy()
    for name in TIMING_SIGNALS:
        samples[name] = 0.0
    # log_time is the start time + t: only its offset from the first is the run's
    header = [
        (m.sequence, m.log_time - first.log_time, m.publish_time - m.log_time, m.channel_id) for _, _, m in messages
    ]
    return (
        metadata,
        (schema.name, schema.encoding, schema.data, channel.topic, channel.message_encoding),
        header,
        samples.tobytes(),
    )


def test_the_files_are_the_same_record_for_record_but_the_timing_fields(runs):
    for a, b in zip(*(_logs(runs[jobs][0]) for jobs in (1, 2))):
        meta_a, layout_a, header_a, samples_a = _records(a)
        meta_b, layout_b, header_b, samples_b = _records(b)
        assert [name for name, _ in meta_a] == ["qube.episode", "qube.controller", "qube.status"]
        assert meta_a == meta_b and layout_a == layout_b and header_a == header_b
        assert samples_a == samples_b and len(samples_a) > 0


def test_the_summary_says_the_same_but_the_timing(runs):
    def outcome(stdout: str) -> list[str]:
        rows = [line.split()[2:4] for line in stdout.splitlines() if re.match(r"^\d+\s+qube_", line)]
        said = [line for line in stdout.splitlines() if line.startswith("episode ")]
        closing = [line.split(";")[0] for line in stdout.splitlines() if " complete, " in line]
        return [*map(" ".join, rows), *said, *closing]

    serial, parallel = (outcome(runs[jobs][1]) for jobs in (1, 2))
    assert serial == parallel
    assert serial[2] == "aborted 791" and "3 complete, 1 aborted" in serial  # the default twin's safety stop
    assert "2 worker processes" in runs[2][1] and "processes" not in runs[1][1]


def test_a_skipped_backend_starts_the_episode_a_serial_one_starts():
    ran, skipped = SimBackend(seed=5), SimBackend(seed=5)
    for _ in range(3):
        ran.start()
        ran.stop()
        skipped.skip_episode()
    copy_ = copy.deepcopy(skipped)
    for backend in (ran, skipped, copy_):
        backend.start()
    assert ran.describe() == skipped.describe() == copy_.describe()
    assert ran.read() == skipped.read() == copy_.read()
    first = SimBackend(seed=5)
    first.start()
    assert first.describe()["sensor"] != ran.describe()["sensor"]  # the draws did move on


def test_a_noisy_sensor_cannot_be_skipped():
    with pytest.raises(ValueError, match="noise"):
        SimBackend(sensor=SensorModel(noise_std=1e-3), seed=1).skip_episode()


@pytest.mark.parametrize(
    "value, said",
    [
        ("0", "must be -1 (every core) or at least 1, got 0"),
        ("-2", "must be -1 (every core) or at least 1, got -2"),
        ("two", "'two' is not a whole number"),
    ],
)
def test_n_jobs_out_of_range_is_a_usage_error_naming_the_option(value, said, tmp_path, capsys):
    out = tmp_path / "out"
    assert main(["--n-jobs", value, "--episodes", "2", "--duration", "1", "--out", str(out), "-q"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("qube-run: error: argument --n-jobs: ") and said in err
    assert not out.exists()


@pytest.mark.parametrize(
    "options, said",
    [
        (["--backend", "serial", "--port", "/dev/null"], "--n-jobs 2: --backend serial runs one episode at a time"),
        (["--rerun-save", "{tmp}/run.rrd"], "--n-jobs 2: --rerun-save runs one episode at a time"),
        (["--rt-cpu", "0"], "--n-jobs 2: --rt-cpu runs one episode at a time"),
    ],
)
def test_one_rig_one_view_or_one_pinned_process_refuse_more_jobs(options, said, tmp_path, capsys):
    out = tmp_path / "out"
    options = [o.format(tmp=tmp_path) for o in options]
    assert main([*options, "--n-jobs", "2", "--episodes", "3", "--duration", "1", "--out", str(out), "-q"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("qube-run: error: ") and said in err, err
    assert not out.exists()


def test_help_explains_n_jobs(capsys):
    assert main(["--help"]) == 0
    text = " ".join(capsys.readouterr().out.split())
    assert "--n-jobs N" in text and "default -1: one per core" in text and "--backend serial" in text


@pytest.mark.slow
def test_sigterm_to_the_run_stops_the_workers_episodes_with_their_logs_closed(tmp_path):
    # Paced episodes of 3 s: the first runs here, then two in workers; SIGTERM goes to this
    # process only (not the workers): it stops them through the run's flags.
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "qube_koopman.daq.cli.run",
            "--realtime",
            "--episodes",
            "4",
            "--duration",
            "3",
            "--seed",
            "5",
            "--n-jobs",
            "2",
            "--out",
            str(tmp_path),
            "-q",
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        deadline = time.monotonic() + 60
        while len(_logs(tmp_path)) < 3:
            assert proc.poll() is None, proc.communicate()
            assert time.monotonic() < deadline, "no worker started an episode in 60 s"
            time.sleep(0.05)
        time.sleep(0.5)
        proc.send_signal(signal.SIGTERM)
        out, err = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 128 + signal.SIGTERM, err
    logs = _logs(tmp_path)
    assert len(logs) == 3, "no episode starts after the signal"
    episodes = [read_episode(p) for p in logs]  # warns if anything was salvaged: it must not be
    assert episodes[0].metadata.status == "complete"
    for ep in episodes[1:]:
        n = len(ep)
        assert ep.metadata.status == "aborted" and ep.metadata.status_reason == "interrupted by SIGTERM"
        assert 0 < n < 1500 and not ep.metadata.salvaged and ep.plant_input[-1] == 0.0
        assert np.array_equal(ep.t, np.arange(n) / 500), "no sample lost"
    assert "1 complete, 2 aborted" in out and "interrupted by SIGTERM" in err
    assert "Traceback" not in err


def _alive_descendants(root: int) -> set[int]:
    """Pids of the live (not zombie) processes under ``root``, from /proc."""
    parents = {}
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                stat = (entry / "stat").read_text()
            except OSError:
                continue
            fields = stat[stat.rindex(")") + 2 :].split()
            if fields[0] != "Z":
                parents[int(entry.name)] = int(fields[1])
    found, frontier = set(), [root]
    while frontier:
        pid = frontier.pop()
        children = {c for c, p in parents.items() if p == pid} - found
        found |= children
        frontier += children
    return found


def _gone(pid: int) -> bool:
    """Whether ``pid`` has ended (reaping it if it was handed to this process, the suite's subreaper)."""
    try:
        os.waitpid(pid, os.WNOHANG)
    except ChildProcessError:
        pass
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return True
    return stat[stat.rindex(")") + 2] == "Z"


@pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="reads the process tree from /proc")
def test_sigkill_of_the_run_leaves_no_worker_behind(tmp_path):
    # SIGKILL: the run cannot tell its workers anything. They see their parent gone and end, a running
    # episode first closing its log as aborted (within 50 ms); within a few seconds all are gone.
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "qube_koopman.daq.cli.run",
            "--realtime",
            "--episodes",
            "4",
            "--duration",
            "3",
            "--seed",
            "5",
            "--n-jobs",
            "2",
            "--out",
            str(tmp_path),
            "-q",
        ],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        deadline = time.monotonic() + 60
        while len(_logs(tmp_path)) < 3:  # the first episode here, then two in the workers
            assert proc.poll() is None, proc.communicate()
            assert time.monotonic() < deadline, "no worker started an episode in 60 s"
            time.sleep(0.05)
        workers = _alive_descendants(proc.pid)
        assert len(workers) >= 2, workers
        proc.kill()
        proc.wait(10)
        deadline = time.monotonic() + 5
        while not all(_gone(pid) for pid in workers) and time.monotonic() < deadline:
            time.sleep(0.05)
        left = {pid for pid in workers if not _gone(pid)}
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(10)
    for pid in left:
        os.kill(pid, signal.SIGKILL)  # this test's own leftovers, by pid, so the suite goes on clean
    assert not left, f"{len(left)} of the run's {len(workers)} processes outlived it by 5 s"
    for path in _logs(tmp_path)[1:]:
        meta = read_episode(path).metadata  # warns if anything was salvaged: it must not be
        assert meta.status == "aborted" and meta.status_reason == "the run's process ended"


def test_a_relative_out_folder_is_this_processs_even_when_joblibs_workers_started_elsewhere(tmp_path, monkeypatch):
    # joblib's reusable workers keep the working directory they were started in: another part of
    # the same process (a search, an earlier run from elsewhere) may have started them. The
    # workers' episodes must still go to the folder the caller named, relative to its own cwd.
    import joblib

    (tmp_path / "elsewhere").mkdir()
    (tmp_path / "here").mkdir()
    monkeypatch.chdir(tmp_path / "elsewhere")
    # Workers started here, as the run's (the same settings: joblib reuses them) and left running.
    started = joblib.Parallel(n_jobs=2, return_as="generator", max_nbytes=None, batch_size=1)(
        joblib.delayed(abs)(-k) for k in range(4)
    )
    assert list(started) == [0, 1, 2, 3]
    monkeypatch.chdir(tmp_path / "here")
    assert main(["--episodes", "3", "--duration", "1", "--seed", "3", "--n-jobs", "2", "--out", "logs", "-q"]) == 0
    assert len(_logs(tmp_path / "here" / "logs")) == 3
    assert not (tmp_path / "elsewhere" / "logs").exists()
