"""``qube-emulate``: an emulated QUBE-Servo bridge on a pseudo-terminal, for the serial path without hardware."""

from __future__ import annotations

import argparse
import math
import sys

from qube_koopman.core.cli import OneLineParser, add_force_option, number_in, parse_args
from qube_koopman.core.command import CliError, check_output_file, run_command
from qube_koopman.core.files import atomic_path

PROG = "qube-emulate"

_DESCRIPTION = """\
Start an emulated QUBE-Servo bridge: the bridge firmware's own core (compiled
from firmware_protocol/c/src with the system C compiler, cached after the
first build) driving a simulated pendulum at 500 Hz, behind a pseudo-terminal
that a host opens as it would open the real bridge's serial port.

The device path is printed alone on the first line of standard output, so
that scripts can read it, e.g.:

  qube-emulate &                                   # prints /dev/pts/N
  qube-run --backend serial --port /dev/pts/N

Each time a host opens a session the pendulum is put back upright, at rest,
with a small seeded tilt (as a person raises the real one by hand); with
--hanging it is left hanging for a swing-up (qube-run --swing-up). Runs until
Ctrl-C or SIGTERM, or until the device vanishes (--vanish-at).
"""

_EPILOG = """\
fault injection (seeded by --seed; times are seconds of device time after the
host's first HELLO):
  --drop-rate 0.01 --corrupt-rate 1e-4 --garbage-rate 0.01    a bad link
  --latency 3                                                  a slow link (ms, each way)
  --stall-at 2 / --amp-fault-at 2                              the QUBE fails
  --silence-at 2 / --vanish-at 2                               the bridge hangs / is unplugged

exit status: 0 when stopped by Ctrl-C or SIGTERM or after vanishing as asked,
1 when the emulator cannot run (no C compiler...) or --record/--stats cannot
be written at exit, 2 on a usage error.
"""


_RATE = number_in(0.0, 1.0, "a rate")
_TIME = number_in(0.0, 1e6, "a time")


def build_parser() -> argparse.ArgumentParser:
    """The command-line parser (also documents the options)."""
    from qube_koopman.core.cli import add_standard_options, path, seed, whole_number

    p = OneLineParser(
        prog=PROG, description=_DESCRIPTION, epilog=_EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    p.add_argument(
        "--target",
        choices=("host", "avr"),
        default="host",
        help="host (default): the firmware core compiled for this machine; avr: the whole Uno "
        "sketch on an emulated ATmega328P (simavr; Debian packages gcc-avr avr-libc "
        "arduino-core-avr simavr libsimavr-dev libsimavrparts1), real time, no fault injection",
    )
    p.add_argument(
        "--seed",
        type=seed,
        default=None,
        metavar="K",
        help="seeds the start tilts and the injected faults (default: a fresh one, printed)",
    )
    p.add_argument(
        "--perturbation",
        type=number_in(0.0, 4.9, "the tilt"),
        default=2.0,
        metavar="DEG",
        help="each session starts with |alpha| up to this (default 2; qube-run starts below 5); with --hanging "
        "the first session, that far from straight down",
    )
    p.add_argument(
        "--plant",
        type=path,
        default=None,
        metavar="FILE.toml",
        help="the pendulum's physical parameters: a qube-calibrate plant file or a named set "
        "(default: the twin calibrated on the paper's rig; 'calibrated-with-load': with the arm's random load; "
        "'calibrated-with-relaxation': also the cables' relaxation; "
        "'workbook', 'previous'); with a [load] table, each session's load is a new draw (from --seed)",
    )
    p.add_argument(
        "--no-load",
        action="store_true",
        help="leave out the plant file's random load on the arm (its [load] table)",
    )
    p.add_argument(
        "--hanging",
        action="store_true",
        help="do not raise the pendulum: the first session finds it hanging at rest (within --perturbation of "
        "straight down; --target avr: straight down), later ones wherever the last one left it",
    )
    p.add_argument(
        "--raise-time",
        type=number_in(0.0, 60.0, "--raise-time"),
        default=0.0,
        metavar="S",
        help="raise the pendulum from hanging over S seconds, as by hand (default 0: at once); "
        "the host's start gate holds the motor at 0 V meanwhile",
    )
    p.add_argument(
        "--lockstep",
        action="store_true",
        help="tick as soon as the host answers (max 10 ms apart) instead of every 2 ms of wall "
        "time: deterministic and faster than real time, for tests",
    )
    p.add_argument(
        "--spin",
        type=number_in(0.0, 1900.0, "--spin"),
        default=300.0,
        metavar="US",
        help="spin this long before each tick deadline (default 300 us; 0: sleep only, less CPU, more jitter)",
    )
    faults = p.add_argument_group("fault injection")
    faults.add_argument(
        "--drop-rate", type=_RATE, default=0.0, metavar="P", help="fraction of frames to the host dropped"
    )
    faults.add_argument(
        "--corrupt-rate", type=_RATE, default=0.0, metavar="P", help="probability per byte, each way, of a flipped bit"
    )
    faults.add_argument(
        "--garbage-rate",
        type=_RATE,
        default=0.0,
        metavar="P",
        help="probability per tick of a burst of random bytes to the host",
    )
    faults.add_argument(
        "--latency",
        type=number_in(0.0, 9999.0, "--latency"),
        default=0.0,
        metavar="MS",
        help="added to every byte's trip, each way (ms)",
    )
    for name, what in (
        ("stall-at", "the QUBE reports a motor stall error"),
        ("amp-fault-at", "the QUBE reports an amplifier fault"),
        ("silence-at", "the bridge stops sending (the port stays open)"),
        ("vanish-at", "the device disappears (the pseudo-terminal is closed)"),
        ("hold-at", "the firmware is held for --hold-periods periods (periods lost)"),
    ):
        faults.add_argument(f"--{name}", type=_TIME, default=None, metavar="S", help=f"{what} at S")
    faults.add_argument(
        "--hold-periods",
        type=whole_number(1, 100_000),
        default=10,
        metavar="N",
        help="periods the --hold-at hold lasts (default 10)",
    )
    out = p.add_argument_group("output")
    out.add_argument(
        "--record",
        type=path,
        default=None,
        metavar="FILE.csv",
        help="write a per-tick record (device time, applied voltage, commands) at exit (the last 10 minutes)",
    )
    out.add_argument("--stats", type=path, default=None, metavar="FILE.json", help="write the final counters at exit")
    add_force_option(out)
    add_standard_options(p, "only the device path on standard output")
    return p


def _write_outputs(emulator, args) -> list[str]:
    """Write --stats and --record; return the errors, one ``<file>: cannot write: <reason>`` each."""
    import json

    errors = []

    def write(path: str, fill) -> None:
        try:
            with atomic_path(path) as tmp, open(tmp, "w") as f:  # whole or not at all
                fill(f)
        except OSError as exc:  # a full disk at exit: the other file is still written
            errors.append(f"{path}: cannot write: {exc.strerror or exc}")

    if args.stats:
        write(
            args.stats,
            lambda f: json.dump(
                {
                    "stats": emulator.stats(),
                    "faults": emulator.faults.as_dict(),
                    "vanished_at": emulator.vanished_at,
                    "events": [{"device_us": d, "wall": w, "event": e} for d, w, e in emulator.events],
                },
                f,
                indent=1,
            ),
        )
    if args.record:
        from qube_koopman.sim.bridge import RECORD_FIELDS

        record = emulator.record()

        def rows(f) -> None:
            f.write(",".join(RECORD_FIELDS) + "\n")
            for row in zip(*(record[name].tolist() for name in RECORD_FIELDS)):
                f.write(",".join(repr(v) for v in row) + "\n")

        write(args.record, rows)
    return errors


def main(argv: list[str] | None = None) -> int:
    """Run ``qube-emulate``; returns the exit status (see ``qube-emulate --help``)."""
    parser = build_parser()
    args = parse_args(parser, argv)
    if isinstance(args, int):  # --help, or a usage error argparse has already explained
        return args
    # Ctrl-C and SIGTERM reach run_command only before the bridge runs: while it runs they stop it (exit 0).
    return run_command(PROG, lambda a: _main_avr(a, parser) if a.target == "avr" else _emulate(a), args)


def _emulate(args) -> int:
    """``qube-emulate`` (--target host): the firmware core and the simulated pendulum behind a pty."""
    import signal

    from qube_koopman.firmware_protocol.ccore import CompilerNotFound
    from qube_koopman.sim.bridge import BridgeEmulator, Faults

    faults = Faults(
        drop_rate=args.drop_rate,
        corrupt_rate=args.corrupt_rate,
        garbage_rate=args.garbage_rate,
        latency=args.latency / 1e3,
        stall_at=args.stall_at,
        amp_fault_at=args.amp_fault_at,
        silence_at=args.silence_at,
        vanish_at=args.vanish_at,
        hold_at=args.hold_at,
        hold_periods=args.hold_periods,
    )
    from qube_koopman.sim.pendulum.params_file import PlantFileError, plant_file

    try:
        plant = plant_file(args.plant)
    except PlantFileError as exc:
        raise CliError(str(exc)) from None
    emulator = BridgeEmulator(
        seed=args.seed,
        params=plant.params,
        load=None if args.no_load else plant.load,
        relaxation=plant.relaxation,
        lockstep=args.lockstep,
        perturbation=math.radians(args.perturbation),
        start_upright=not args.hanging,
        raise_time=args.raise_time,
        faults=faults,
        spin=args.spin / 1e6,
        record_ticks=300_000 if args.record else 0,
    )
    check_output_file(args.record, "--record", args.force)  # before the emulator starts
    check_output_file(args.stats, "--stats", args.force)
    try:
        path = emulator.open()
    except CompilerNotFound as exc:
        raise CliError(f"{exc} (the emulated bridge runs the bridge firmware's C core)", status=1) from None
    except (RuntimeError, OSError) as exc:
        raise CliError(f"cannot start the emulated bridge: {_first_line(exc)}", status=1) from None
    previous = {}

    def on_signal(signum, frame):
        emulator.request_stop()

    for signum in (signal.SIGINT, signal.SIGTERM):
        previous[signum] = signal.signal(signum, on_signal)
    try:
        print(path, flush=True)
        if not args.quiet:
            mode = "lockstep" if args.lockstep else "real time, 500 Hz"
            mode += "" if emulator.load is None else ", the plant's random load on the arm"
            mode += "" if emulator.relaxation is None else ", the cables' relaxation"
            print(
                f"{PROG}: emulated QUBE-Servo bridge on {path} ({mode}, seed {emulator.seed}); try "
                f"qube-run --backend serial --port {path}; Ctrl-C to stop",
                file=sys.stderr,
                flush=True,
            )
        emulator.run()
    finally:
        for signum, handler in previous.items():
            signal.signal(signum, handler)
        emulator.close()
        errors = _write_outputs(emulator, args)
    for error in errors:
        print(f"{PROG}: error: {error}", file=sys.stderr)
    if not args.quiet:
        s = emulator.stats()
        end = "vanished as asked" if emulator.vanished_at is not None else "stopped"
        print(
            f"{PROG}: {end} after {s['ticks']} ticks ({s['device_time']:.1f} s of device time), "
            f"{s['sessions']} session(s), {s['commands']} commands, {s['late_ticks']} ticks caught up late, "
            f"{s['slips']} schedule restarts "
            f"(max lateness {s['max_lateness'] * 1e3:.1f} ms)",
            file=sys.stderr,
        )
    return 1 if errors else 0


def _first_line(exc: Exception) -> str:
    """The first line of why the emulator could not start (a compiler's or simavr's output can be long)."""
    return str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__


_AVR_OPTIONS = ("target", "seed", "perturbation", "hanging", "quiet", "verbose")


def _main_avr(args, parser) -> int:
    """``qube-emulate --target avr``: the Uno sketch on simavr behind a pty."""
    import signal

    defaults = vars(parser.parse_args([]))
    extra = [k for k, v in vars(args).items() if k not in _AVR_OPTIONS and v != defaults[k]]
    if extra:
        raise CliError(
            f"--target avr takes only --seed, --perturbation, --hanging and -q (not --{extra[0].replace('_', '-')})"
        )
    from qube_koopman.firmware_protocol.avr_build import AvrToolsMissing
    from qube_koopman.sim.bridge.avr_pty import AvrPtyBridge

    emulator = AvrPtyBridge(
        seed=args.seed, perturbation=math.radians(args.perturbation), start_upright=not args.hanging
    )
    try:
        path = emulator.open()
    except (AvrToolsMissing, RuntimeError, OSError) as exc:
        raise CliError(f"cannot start the emulated Uno: {_first_line(exc)}", status=1) from None
    previous = {
        signum: signal.signal(signum, lambda *_: emulator.request_stop()) for signum in (signal.SIGINT, signal.SIGTERM)
    }
    try:
        print(path, flush=True)
        if not args.quiet:
            print(
                f"{PROG}: bridge sketch on an emulated ATmega328P (simavr) on {path} (real time, seed "
                f"{emulator.seed}); try qube-run --backend serial --port {path}; Ctrl-C to stop",
                file=sys.stderr,
                flush=True,
            )
        emulator.run()
    finally:
        for signum, handler in previous.items():
            signal.signal(signum, handler)
        emulator.close()
    if not args.quiet:
        s = emulator.stats()
        print(
            f"{PROG}: stopped after {s['ticks']} ticks ({s['device_time']:.1f} s of device time in "
            f"{s['wall_time']:.1f} s), {s['sessions']} session(s), CPU busy {100 * s['busy']:.0f} %, "
            f"at most {s['max_behind'] * 1e3:.1f} ms behind the wall clock",
            file=sys.stderr,
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
