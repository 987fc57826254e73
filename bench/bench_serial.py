"""Benchmark: the serial path over a pseudo-terminal, against the emulated bridge (``qube-emulate``).

Everything runs as on a rig, in real time: the emulated bridge in its own
process, the host (the acquisition loop with the serial backend, or a small
probe) in this one. Rows:

- round trip over the pty, p50 / p99 / max: a 25-byte frame echoed by a bare
  pty echo process (reference: the link alone), and HELLO -> HELLO_REPLY
  through the emulated bridge (the link plus the firmware core);
- missed ticks over ``--ticks`` ticks at 500 Hz (10,000 by default, 20 s per
  row): one episode of the loop on the serial backend. From the bridge's
  side: ticks that started a period or more late and were caught up back
  to back, schedule restarts after longer stalls (their periods are lost)
  and its worst lateness; from the host's: telemetry
  missed (gaps), skipped (the host fell a tick behind and took the newest),
  commands that missed their tick; and the loop's round trip as the bridge
  sees it, from each tick to the command that answers it (p50 / p99 / max).
  Reference row: the bridge sleeping to its deadlines without the final
  spin (``--spin 0``);
- watchdog: device time from SIGKILL of a running ``qube-run`` to the motor
  at 0 V (target: within 10 ms of device time);
- link loss: host abort after the device vanishes (pty closed) and after it
  goes silent (target: within 50 ms);
- decoder throughput (frames/s) of ``StreamDecoder`` on telemetry, with
  bench/bench_protocol.py's stream (that script has the full comparison).

Usage::

    PYTHONPATH=. python bench/bench_serial.py [--ticks N] [--round-trips N] [--no-reference]
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parent.parent
sys.path[:0] = [str(REPO), str(REPO / "bench")]

_ECHO = """
import os, select, sys, tty
master, slave = os.openpty()
tty.setraw(master); tty.setraw(slave)
print(os.ttyname(slave), flush=True)
while True:
    select.select([master], [], [])
    os.write(master, os.read(master, 4096))
"""


def _env() -> dict:
    return dict(os.environ, PYTHONPATH=os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")]))


def _spawn(args: list[str]) -> tuple[subprocess.Popen, str]:
    proc = subprocess.Popen(
        [sys.executable, *args], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=_env()
    )
    path = proc.stdout.readline().strip()
    if not path.startswith("/dev/"):
        proc.kill()
        raise RuntimeError(f"{args}: no device path ({proc.communicate()[1].strip()})")
    return proc, path


def _emulator(*args: str) -> tuple[subprocess.Popen, str]:
    return _spawn(["-m", "qube_koopman.sim.cli.emulate", "-q", *args])


def _stop(proc: subprocess.Popen) -> None:
    # Our own child, by its pid.
    if proc.poll() is None:
        proc.terminate()
    try:
        proc.communicate(timeout=10)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.communicate()


def _percentiles(values) -> str:
    v = np.asarray(values, dtype=float) * 1e3
    return f"{np.percentile(v, 50):8.3f} {np.percentile(v, 99):8.3f} {v.max():8.3f}"


def _time_round_trips(proc: subprocess.Popen, path: str, n: int, timeout: float, exchange) -> list[float]:
    """``n`` timed calls of ``exchange(port, i)`` on the device at ``path`` (served by ``proc``), in s."""
    import serial

    try:
        port = serial.Serial(path, 500000, timeout=timeout)
        port.reset_input_buffer()
        times = []
        for i in range(1, n + 1):
            t = time.perf_counter()
            exchange(port, i)
            times.append(time.perf_counter() - t)
        port.close()
        return times
    finally:
        _stop(proc)


def round_trips(n: int) -> list[tuple[str, list[float]]]:
    """Echo round trips over a bare pty, and HELLO round trips through the emulated bridge (s)."""
    from qube_koopman.firmware_protocol import Command, Hello, HelloReply, StreamDecoder, encode_frame

    frame = encode_frame(Command(1000, 1), 1, 0)

    def echo(port, _):
        port.write(frame)
        if len(port.read(len(frame))) != len(frame):
            raise RuntimeError("echo lost bytes")

    decoder = StreamDecoder()

    def hello(port, nonce):
        t = time.perf_counter()
        port.write(encode_frame(Hello(nonce), nonce, 0))
        while not any(
            isinstance(f.message, HelloReply) and f.message.nonce == nonce
            for f in decoder.feed(port.read(max(1, port.in_waiting)))
        ):
            if time.perf_counter() - t > 1:
                raise RuntimeError("no HELLO_REPLY within 1 s")

    return [
        ("pty echo, 25 B (reference: the link alone)", _time_round_trips(*_spawn(["-c", _ECHO]), n, 1, echo)),
        ("HELLO -> HELLO_REPLY via the emulated bridge", _time_round_trips(*_emulator("--seed", "1"), n, 0.005, hello)),
    ]


class _TimedBackend:
    """Mixin: notes when a read or write first raises (the host's abort), on the monotonic clock."""

    fault_at: float | None = None

    def _timed(self, call, *args):
        from qube_koopman.daq.backends.contract import BackendFault

        try:
            return call(*args)
        except BackendFault:
            self.fault_at = self.fault_at or time.perf_counter()
            raise

    def read(self):
        return self._timed(super().read)

    def write(self, volts):
        return self._timed(super().write, volts)


def _serial_episode(path: str, seconds: float, out: str, timed: bool = False):
    """One episode of the loop on the serial backend at ``path``: (result, backend)."""
    from qube_koopman.daq.backends.serial import SerialBackend
    from qube_koopman.daq.loop import run_episode
    from qube_koopman.daq.session import excitation_settings, plan_episodes, run_seeds
    from qube_koopman.core.controller_file import load_controller
    from qube_koopman.daq.sinks import McapSink

    backend = type("Timed", (_TimedBackend, SerialBackend), {})(path) if timed else SerialBackend(path)
    try:
        seeds, _ = run_seeds(0, 1)
        plan = plan_episodes(load_controller(), seeds, excitation_settings(seconds), source="bench")[0]
        return run_episode(backend, plan, [McapSink(out)]), backend
    finally:
        backend.close()


def episode(ticks: int, spin_us: float) -> dict:
    """One real-time episode of ``ticks`` on the serial backend; the bridge's and the host's counts."""
    with tempfile.TemporaryDirectory() as tmp:
        stats_file, record = Path(tmp) / "stats.json", Path(tmp) / "record.csv"
        proc, path = _emulator(
            "--seed", "2", "--spin", str(spin_us), "--stats", str(stats_file), "--record", str(record)
        )
        try:
            result, _ = _serial_episode(path, ticks / 500.0, tmp)
        finally:
            _stop(proc)
        device = json.loads(stats_file.read_text())["stats"]
        rows = _read_record(record)
    # The episode's ticks: the last session's, while the host drove the motor.
    episode_ticks = (rows["session"] == rows["session"].max()) & rows["amp_enabled"]
    return {"result": result, "device": device, "link": result.backend_stats, "answer": rows["answer"][episode_ticks]}


def _read_record(path: Path) -> dict[str, np.ndarray]:
    with open(path) as f:
        rows = list(csv.DictReader(f))
    return {
        "wall": np.array([float(r["wall"]) for r in rows]),
        "device_us": np.array([int(r["device_us"]) for r in rows]),
        "amp_enabled": np.array([r["amp_enabled"] == "True" for r in rows]),
        "session": np.array([int(r["session"]) for r in rows]),
        "answer": np.array([float(r["answer"]) for r in rows]),
    }


def watchdog_after_kill() -> float:
    """Device ms from SIGKILL of a running qube-run to the emulated motor at 0 V."""
    with tempfile.TemporaryDirectory() as tmp:
        record = Path(tmp) / "record.csv"
        emulator, path = _emulator("--seed", "3", "--record", str(record))
        code = "import sys; from daq.cli.run import main; sys.exit(main(sys.argv[1:]))"
        host = subprocess.Popen(
            [
                sys.executable,
                "-c",
                code,
                "--backend",
                "serial",
                "--port",
                path,
                "--episodes",
                "1",
                "--duration",
                "20",
                "--out",
                tmp,
                "-q",
            ],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
            env=_env(),
        )
        time.sleep(4.0)  # imports, handshake, two seconds of control
        if host.poll() is not None:
            raise RuntimeError("qube-run ended before it could be killed")
        t_kill = time.perf_counter()  # CLOCK_MONOTONIC, as the emulator's record
        host.kill()
        host.wait()
        time.sleep(0.2)
        _stop(emulator)
        rows = _read_record(record)
    wall, device_us, enabled = rows["wall"], rows["device_us"], rows["amp_enabled"]
    k = np.flatnonzero(wall >= t_kill)[0]
    if not enabled[k - 100 : k].all():
        raise RuntimeError("the motor was not being driven when the host was killed")
    z = k + np.flatnonzero(~enabled[k:])[0]
    return (device_us[z] - device_us[k]) / 1e3


def link_loss(fault: str) -> tuple[float, str]:
    """ms from the device vanishing / going silent (the emulator's clock) to the host's abort."""
    with tempfile.TemporaryDirectory() as tmp:
        stats_file = Path(tmp) / "stats.json"
        proc, path = _emulator("--seed", "4", f"--{fault}-at", "1.0", "--stats", str(stats_file))
        try:
            result, backend = _serial_episode(path, 4.0, tmp, timed=True)
        finally:
            _stop(proc)
        events = json.loads(stats_file.read_text())["events"]
    at = next(e["wall"] for e in events if e["event"] == fault)
    return (backend.fault_at - at) * 1e3, result.reason


def decoder_rate(n_frames: int = 20_000) -> float:
    """StreamDecoder frames/s on telemetry in 1-64 byte chunks (median of 5)."""
    from bench_protocol import chunked, make_stream, time_decoder

    from qube_koopman.firmware_protocol import StreamDecoder

    stream = make_stream(n_frames, 1)
    return time_decoder(StreamDecoder, chunked(stream, 1, 64, 1), n_frames, 5)[0]


def main(argv: list[str] | None = None) -> int:
    """Run the benchmark and print the table."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--ticks", type=int, default=10_000, help="ticks per episode row (default 10000 = 20 s)")
    parser.add_argument("--round-trips", type=int, default=2000, help="round trips per latency row")
    parser.add_argument("--no-reference", action="store_true", help="skip the sleep-only bridge row")
    args = parser.parse_args(argv)

    print("round trip over the pty (ms)              p50      p99      max")
    for name, times in round_trips(args.round_trips):
        print(f"  {name:<44} {_percentiles(times)}")

    print(f"\n{args.ticks} ticks at 500 Hz, loop on the serial backend, bridge in real time")
    header = (
        f"  {'bridge pacing':<23} {'status':<9} | {'late':>4} {'restarts':>8} {'lost':>4} {'max ms':>6} | "
        f"{'missed':>6} {'skipped':>7} {'late cmds':>9} | {'tick->cmd ms p50/p99/max':>24} | "
        f"{'loop late ms p50/p99':>20}"
    )
    print(header)
    rows = [("sleep + 300 us spin", 300.0)] + ([] if args.no_reference else [("sleep only (reference)", 0.0)])
    for name, spin in rows:
        r = episode(args.ticks, spin)
        d, link, t = r["device"], r["link"], r["result"].timing
        answered = r["answer"][np.isfinite(r["answer"])] * 1e3
        trip = "/".join(f"{v:.2f}" for v in (np.percentile(answered, 50), np.percentile(answered, 99), answered.max()))
        print(
            f"  {name:<23} {r['result'].status:<9} | {d['late_ticks']:>4} {d['slips']:>8} "
            f"{d['missed_periods']:>4} {d['max_lateness'] * 1e3:>6.2f} | {link['ticks_missed']:>6} "
            f"{link['ticks_skipped']:>7} {link['late_commands']:>9} | {trip:>24} | "
            f"{t.lateness_p50 * 1e3:>9.3f}/{t.lateness_p99 * 1e3:.3f}"
        )
        if r["result"].reason:
            print(f"    ({r['result'].reason})")

    print("\nsafety")
    print(f"  host SIGKILLed -> motor at 0 V: {watchdog_after_kill():.0f} ms of device time (target <= 10)")
    for fault in ("vanish", "silence"):
        ms, reason = link_loss(fault)
        print(
            f"  device {fault + 'ed' if fault == 'vanish' else 'silent'} -> host abort: {ms:.1f} ms "
            f"(target < 50): {reason}"
        )

    rate = decoder_rate()
    print(
        f"\ndecoder: StreamDecoder {rate:,.0f} telemetry frames/s ({rate / 500:,.0f}x the 500 frames/s needed; "
        "bench/bench_protocol.py compares decoders)"
    )
    print(
        "\nmissed: telemetry lost on the link; skipped: telemetry passed over because the host was a tick "
        "behind;\nlate cmds: ticks at which the bridge had no new command (it applied the previous one);\nbridge late: "
        "ticks that started a period or more late, caught up at once; restarts: stalls beyond three\nperiods "
        "(device time pauses for the lost periods); max ms: the bridge's worst tick lateness;\ntick->cmd: from a "
        "bridge tick to the host's command answering it; loop late: the loop's tick lateness\nagainst the "
        "bridge's clock."
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
