"""Benchmark of the episode log: read speed, import time of the dataset, size.

Measures, against the targets of the log format's issue:

- median time to read one 10,000-sample episode into arrays (target 50 ms),
  and the same with the mcap library's own reader decoding message by
  message (the reference approach), as a ratio;
- wall time of ``qube-import`` on all 48 files of the paper's dataset, in a
  fresh process (target 15 s);
- total size of the MCAP logs over the CSV files (target 40 %).

Usage::

    PYTHONPATH=. python bench/bench_log_read.py [--dataset DIR] [--repeats N]

Without the dataset ($QUBE_DATASET_DIR or ../shared/datasets/qube_servo_20230828)
the read benchmark uses a synthetic episode and the import rows are skipped.
"""

from __future__ import annotations

import argparse
import os
import statistics
import struct
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
DEFAULT_DATASET = Path(os.environ.get("QUBE_DATASET_DIR", REPO.parent / "shared" / "datasets" / "qube_servo_20230828"))


def _median_seconds(fn, repeats: int) -> float:
    fn()  # warm up: imports, page cache
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def _synthetic_episode_file(folder: Path) -> Path:
    import numpy as np

    from qube_koopman.daq.episode import SIGNALS, Episode, EpisodeMetadata
    from qube_koopman.core.controller_file import ControllerInfo
    from qube_koopman.daq.log import write_episode
    from qube_koopman.core.lti import DiscreteStateSpace

    a = 1 / 1.1
    controller = DiscreteStateSpace(
        np.eye(2) * a, np.eye(2), [[7.4380165, 10.3305785]], [[-87.8181818, -143.6363636]], 0.002
    )
    meta = EpisodeMetadata(ControllerInfo(controller, "backward-euler"), 500.0, "sim", "bench", "2026-01-01T00:00:00")
    rng = np.random.default_rng(0)
    n = 10_000
    signals = {name: np.cumsum(rng.normal(0, 1e-3, n)) for name in SIGNALS if name != "t"}
    episode = Episode(
        t=np.arange(n) / 500, controller_state=rng.normal(size=(n, 2)), saturation=np.zeros(n), metadata=meta, **signals
    )
    return write_episode(folder / "synthetic.mcap", episode)


def _read_with_mcap_library(path: Path) -> None:
    """The reference: mcap's reader yields one Python object per message, decoded with struct."""
    from mcap.reader import make_reader

    unpack = None
    rows = []
    with open(path, "rb") as f:
        for schema, _, message in make_reader(f).iter_messages(topics=["/qube/sample"]):
            if unpack is None:
                n_fields = sum(
                    1 for line in schema.data.decode().splitlines() if line.strip() and not line.startswith("#")
                )
                unpack = struct.Struct("<4x" + "d" * (n_fields - 1) + "b").unpack
            rows.append(unpack(message.data))


def _import_dataset(dataset: Path, out: Path) -> float:
    code = "import sys; from daq.cli.import_csv import main; sys.exit(main(sys.argv[1:]))"
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")])}
    start = time.perf_counter()
    subprocess.run(
        [sys.executable, "-c", code, str(dataset), "--out", str(out), "--quiet"],
        check=True,
        env=env,
        stdout=subprocess.DEVNULL,
    )
    return time.perf_counter() - start


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--dataset", type=Path, default=DEFAULT_DATASET)
    parser.add_argument("--repeats", type=int, default=30)
    args = parser.parse_args()
    sys.path.insert(0, str(REPO))
    from qube_koopman.daq.log import read_episode

    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        csvs = sorted(args.dataset.glob("*.csv")) if args.dataset.is_dir() else []
        if csvs:
            import_s = _import_dataset(args.dataset, tmp / "out")
            mcaps = sorted((tmp / "out").glob("*.mcap"))
            ratio = sum(p.stat().st_size for p in mcaps) / sum(p.stat().st_size for p in csvs)
            sample = mcaps[0]
            source = f"dataset episode {sample.name}"
        else:
            sample = _synthetic_episode_file(tmp)
            source = "synthetic episode (dataset not found)"
        n = len(read_episode(sample))
        ours = _median_seconds(lambda: read_episode(sample), args.repeats)
        reference = _median_seconds(lambda: _read_with_mcap_library(sample), max(3, args.repeats // 6))
        rows.append((f"read {n} samples into arrays (median)", f"{ours * 1e3:.1f} ms", "<= 50 ms", ours <= 0.050))
        rows.append(
            (
                "  reference: mcap reader + struct per message",
                f"{reference * 1e3:.1f} ms",
                f"ratio {reference / ours:.0f}x slower",
                None,
            )
        )
        if csvs:
            rows.append(
                (f"qube-import {len(csvs)} files (fresh process)", f"{import_s:.1f} s", "<= 15 s", import_s <= 15)
            )
            rows.append(("MCAP size / CSV size", f"{ratio * 100:.1f} %", "<= 40 %", ratio <= 0.40))
        else:
            rows.append(("qube-import of the dataset", "skipped", "<= 15 s", None))
            rows.append(("MCAP size / CSV size", "skipped", "<= 40 %", None))

    print(f"episode log benchmark ({source}; {args.repeats} repeats)")
    width = max(len(r[0]) for r in rows)
    print(f"{'measure':<{width}}  {'value':>10}  {'target':<22}  ok")
    for name, value, target, ok in rows:
        mark = "" if ok is None else ("yes" if ok else "NO")
        print(f"{name:<{width}}  {value:>10}  {target:<22}  {mark}")


if __name__ == "__main__":
    main()
