"""``qube-run``: collect closed-loop episodes of the QUBE-Servo (simulated, or through the serial bridge)
into MCAP logs."""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

from qube_koopman.core.cli import OneLineParser, add_force_option, parse_args, whole_number
from qube_koopman.core.command import CliError, check_output_file, output_dir, run_command
from qube_koopman.core.console import configure_logging
from qube_koopman.core.controller import QUBE_SAMPLE_PERIOD
from qube_koopman.core.qube import ALPHA_LIMIT, THETA_LIMIT
from qube_koopman.daq.cli.run_output import PROG

DEFAULT_EPISODES = 3
DEFAULT_DURATION = 20.0
DEFAULT_OUT = Path("episodes")
#: The safety limits' defaults in degrees, as the options take them (the rig's: 90 and 45).
DEFAULT_THETA_LIMIT = math.degrees(THETA_LIMIT)
DEFAULT_ALPHA_LIMIT = math.degrees(ALPHA_LIMIT)
#: --swing-up's defaults: the catch angle (deg), the time limit (s) and the voltage clamp (V).
DEFAULT_CATCH_ANGLE = 20.0
DEFAULT_SWING_UP_TIME = 20.0
DEFAULT_SWING_UP_VOLTAGE = 10.0

_DESCRIPTION = f"""\
Run closed-loop episodes of the QUBE-Servo rotary inverted pendulum and write
one MCAP episode log per episode (format: daq/log/FORMAT.md).

Each episode: the pendulum starts upright (the simulator adds a small random
perturbation), the PD controller balances it while the rig's excitation
(PRBS references and feedforward, three seeds per episode drawn from --seed)
drives it. Every tick is logged: angles, references, feedforward, controller
state and output, applied voltage, saturation, lateness and compute time.
Safety: the command is clamped to +-10 V (lower: --max-voltage); an episode stops with the motor at
0 V when |theta| > {DEFAULT_THETA_LIMIT:g} deg or |alpha| > {DEFAULT_ALPHA_LIMIT:g} deg; Ctrl-C or SIGTERM stops the
run with the motor at 0 V and the current logs closed as "aborted".

With --swing-up each episode starts from the pendulum hanging (the simulator's
hangs at rest): an energy-based swing-up brings it up, the PD controller
catches it within --catch-angle of upright and, once it has settled, the
recorded episode starts, its samples those of an episode started upright. The
swing-up is not in the samples; its outcome is in the log's metadata. While it
runs the supervisor's swing-up limits hold: |theta| within --theta-limit, the
command within +-{DEFAULT_SWING_UP_VOLTAGE:g} V (--swing-up-voltage), and a time limit
(--swing-up-time) after which it gives up with 0 V; a failed swing-up writes a
log without samples that says why, and the next episode swings up again.

With no arguments: 3 episodes of 20 s on the simulator, as fast as the
computer allows (episodes side by side on every core: --n-jobs), into
./episodes. With --backend serial --port DEV the
episodes run on the QUBE through the bridge firmware (or on the emulated
bridge that qube-emulate starts), paced by the bridge's 500 Hz clock; a lost
link or a fault reported by the bridge ends the run with the motor at 0 V and
the log closed as "aborted" with the reason.
"""

_EPILOG = """\
exit status: 0 when every episode completed or was stopped by the safety limits,
its swing-up's included (a recorded outcome, counted in the summary); 1 when one was aborted by a fault,
a log write error (the file and the error are named) or another run error; 2 on
a usage error; 130 / 143 when stopped by SIGINT / SIGTERM. Before each episode
the free space of --out is checked against what it needs.

examples:
  qube-run                                        # 3 x 20 s on the simulator into ./episodes
  qube-run --episodes 48 --seed 1 --out data/     # a dataset the size of the paper's
  qube-run --episodes 48 --seed 1 --n-jobs 1      # the same, one episode at a time
  qube-run --realtime --rerun                     # paced like hardware, live in a rerun viewer
  qube-run --swing-up                             # each episode swung up from hanging first
  qube-run --controller gains.toml --rerun-save run.rrd
  qube-run --backend serial --port /dev/ttyACM0   # the rig, through the bridge firmware
"""


def build_parser() -> argparse.ArgumentParser:
    """The command-line parser (also documents the options)."""
    from qube_koopman.core.cli import (
        add_standard_options,
        n_jobs,
        non_negative_number,
        path,
        positive_number,
        positive_whole_number,
        seed,
    )

    p = OneLineParser(
        prog=PROG, description=_DESCRIPTION, epilog=_EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    p.add_argument(
        "--backend",
        default="sim",
        choices=("sim", "serial"),
        help="sim: the simulated pendulum (default); serial: the bridge firmware on --port",
    )
    p.add_argument(
        "--episodes",
        type=positive_whole_number,
        default=DEFAULT_EPISODES,
        metavar="N",
        help=f"number of episodes (default {DEFAULT_EPISODES})",
    )
    p.add_argument(
        "--duration",
        type=positive_number,
        default=DEFAULT_DURATION,
        metavar="S",
        help=f"seconds per episode (default {DEFAULT_DURATION:g}; the excitation is active "
        "from 20%% to 80%% of it, as the rig's was from 4 s to 16 s of 20 s)",
    )
    p.add_argument(
        "--seed",
        type=seed,
        default=None,
        metavar="K",
        help="run seed: draws the three excitation seeds of every episode and the "
        "simulator's perturbations (default: a fresh one, printed so the run can be repeated)",
    )
    p.add_argument(
        "--out",
        type=path,
        default=DEFAULT_OUT,
        metavar="DIR",
        help=f"folder for the episode logs, created if missing (default ./{DEFAULT_OUT}); one that "
        "already holds episode logs is refused unless --append",
    )
    p.add_argument(
        "--append",
        action="store_true",
        help="add this run's logs to an --out folder that already holds episode logs (whatever reads "
        "the folder then reads both runs': qube-identify trains on every log in it)",
    )
    p.add_argument(
        "--replay",
        type=path,
        nargs="+",
        default=None,
        metavar="LOG",
        help="run the same excitations as these logs (their seeds, settings and durations), "
        "under their own controller unless --controller is given; on the simulator each on its "
        "recording day's and session's twin when the plant file (--plant, or the shipped one) has that "
        "day's cables and that session's command delay",
    )
    p.add_argument(
        "--controller",
        type=path,
        default=None,
        metavar="FILE.toml",
        help="controller file: PD gains (kp_theta, kd_theta, kp_alpha, kd_alpha, tau) or a discrete "
        "state-space controller at 500 Hz (A, B, C, D; core/CONTROLLER_FORMAT.md); a file or a "
        "shipped name: 'rig' (the gains that recorded the paper's dataset: the default) or "
        "'soft-theta' (a softer arm, kp_theta 2)",
    )
    p.add_argument(
        "--run-unstable",
        action="store_true",
        help="run on the rig (--backend serial) a --controller file that destabilises the twin's loop "
        "linearized at upright, which is refused without it; on the simulator such a file runs with a warning "
        "(a linear controller only: PD gains or state space)",
    )
    p.add_argument(
        "--discretization",
        default="backward-euler",
        choices=("backward-euler", "zoh", "tustin"),
        help="discretization of a PD gains file's derivative filters (default backward-euler, as the "
        "rig ran); a state-space file is already discrete",
    )
    p.add_argument(
        "--realtime",
        action="store_true",
        help="pace the simulator like hardware, one tick every 2 ms (default: as fast as possible)",
    )
    p.add_argument(
        "--n-jobs",
        type=n_jobs,
        default=None,
        metavar="N",
        help="run the simulator's episodes N at a time, in worker processes (default -1: one per "
        "core); the logs, their names, seeds and samples are a serial run's, timing apart. The "
        "first episode runs alone, while the workers start: a setup that fails (a full disk, "
        "say) stops the run there, as a serial run stops. Always one at a time with --backend "
        "serial (one rig), --rerun, --rerun-save, --rt-cpu and --rt-priority, which refuse N > 1",
    )
    p.add_argument(
        "--rerun",
        nargs="?",
        const="",
        default=None,
        metavar="URL",
        help="stream live to a rerun viewer: URL, else one listening on 127.0.0.1:9876, "
        "else a newly spawned one (needs a display)",
    )
    p.add_argument(
        "--rerun-save",
        type=path,
        default=None,
        metavar="FILE.rrd",
        help="write a rerun recording of the run (no display needed)",
    )
    add_force_option(p)
    safety = p.add_argument_group("safety and simulator")
    safety.add_argument(
        "--theta-limit",
        type=positive_number,
        default=DEFAULT_THETA_LIMIT,
        metavar="DEG",
        help=f"stop an episode when |theta| exceeds this (default {DEFAULT_THETA_LIMIT:g})",
    )
    safety.add_argument(
        "--max-voltage",
        type=positive_number,
        default=10.0,
        metavar="V",
        help="clamp the command to +-V, at most the rig's 10 V (default 10), whatever the controller: a "
        "linear design run clipped at an MPC's voltage limit",
    )
    safety.add_argument(
        "--alpha-limit",
        type=positive_number,
        default=DEFAULT_ALPHA_LIMIT,
        metavar="DEG",
        help=f"stop an episode when |alpha| exceeds this (default {DEFAULT_ALPHA_LIMIT:g})",
    )
    safety.add_argument(
        "--perturbation",
        type=non_negative_number,
        default=2.0,
        metavar="DEG",
        help="the simulated pendulum starts at rest with |alpha| up to this (default 2; "
        "an episode starts only once |alpha| < 5)",
    )
    swing = p.add_argument_group("swing-up (--swing-up)")
    swing.add_argument(
        "--swing-up",
        action="store_true",
        help="start each episode from the pendulum hanging: swing it up, catch it, wait until it has "
        "settled, then record (the simulator's pendulum starts hanging at rest)",
    )
    swing.add_argument(
        "--catch-angle",
        type=positive_number,
        default=None,
        metavar="DEG",
        help=f"the PD controller takes over within this of upright (default {DEFAULT_CATCH_ANGLE:g})",
    )
    swing.add_argument(
        "--swing-up-time",
        type=positive_number,
        default=None,
        metavar="S",
        help=f"give up, with 0 V, when not caught and settled after this (default {DEFAULT_SWING_UP_TIME:g})",
    )
    swing.add_argument(
        "--swing-up-voltage",
        type=positive_number,
        default=None,
        metavar="V",
        help=f"clamp of the swing-up's commands (default {DEFAULT_SWING_UP_VOLTAGE:g}, at most the rig's 10)",
    )
    safety.add_argument(
        "--plant",
        type=path,
        default=None,
        metavar="FILE.toml",
        help="the simulated pendulum's physical parameters: a qube-calibrate plant file or a "
        "named set (default: the twin calibrated on the rig under two controllers, "
        "'calibrated-two-controllers'; 'calibrated-with-load': the same with the arm's random load and each "
        "recording day's tilt of the base; 'calibrated-with-relaxation': also the cables' relaxation, fitted "
        "with the physics (the closest replay of both controllers' slow band); 'calibrated-20230828': on the "
        "rig's gains alone; "
        "'workbook': the Quanser workbook; 'previous': the workbook with fitted damping)",
    )
    safety.add_argument(
        "--no-load",
        action="store_true",
        help="leave out the plant file's random load on the arm (its [load] table): the twin without "
        "it, exactly as a plant file without the table (the shipped twin has none)",
    )
    link = p.add_argument_group("serial bridge (--backend serial)")
    link.add_argument(
        "--port",
        default=None,
        metavar="DEV",
        help="the bridge's serial device (e.g. /dev/ttyACM0, or the path qube-emulate prints)",
    )
    link.add_argument(
        "--baud",
        type=positive_whole_number,
        default=None,
        metavar="B",
        help="baud rate of a UART bridge (default 500000, the sketch's; USB CDC ignores it)",
    )
    link.add_argument(
        "--link-timeout",
        type=positive_number,
        default=None,
        metavar="MS",
        help="abort an episode after this long without telemetry (default 25; raise it on a "
        "heavily loaded host, the bridge's watchdog still stops the motor after 10 ms)",
    )
    link.add_argument(
        "--check",
        action="store_true",
        help="pre-flight only, the pendulum hanging at rest: module id 777, encoders, amplifier enabling at 0 V, "
        "the round trip, the motor's sign (1 V for 40 ms turns the arm a few degrees) and the bridge's watchdog; "
        "exit 0 when all pass, 1 naming the failed checks",
    )
    rt = p.add_argument_group("real-time scheduling (attempted only when asked; works without)")
    rt.add_argument("--rt-cpu", type=int, default=None, metavar="N", help="pin the process to CPU N")
    rt.add_argument(
        "--rt-priority",
        type=whole_number(1, 99),
        default=None,
        metavar="P",
        help="run SCHED_FIFO at priority P (1..99; needs permission)",
    )
    rt.add_argument(
        "--spin",
        action="store_true",
        help="wait for each tick busy instead of asleep (--realtime: the loop spins to each deadline; "
        "--backend serial: the port is polled): the core stays awake for the controller's step after the "
        "wait, which a cold core makes slower (an MPC's step at its 99th percentile), at the cost of a "
        "core kept busy for the whole run. Default: sleep until 0.3 ms before the deadline, or in the "
        "port's read",
    )
    for extension in _extensions():
        extension.add_arguments(p)
    add_standard_options(p, "no progress bar")
    return p


def _extensions() -> list:
    """The options packages above daq add to qube-run (:mod:`~qube_koopman.daq.cli.run_extensions`)."""
    from qube_koopman.daq.cli.run_extensions import run_extensions

    return run_extensions()


def fresh_seed() -> int:
    """A run seed from the system's entropy, when ``--seed`` is not given (printed to repeat the run)."""
    import numpy as np

    entropy = np.random.SeedSequence().entropy
    assert isinstance(entropy, int)  # drawn from the OS: one int
    return entropy % 1_000_000


def _controller_form(controller, args) -> str:
    """How the controller was made, for the header line: the PD's discretization, or its kind and size."""
    if controller.kind == "pd":
        return args.discretization
    return f"{controller.kind}, {controller.system.n_states} states"


def _check_not_adding(folder: Path, append: bool) -> None:
    """Refuse an --out folder holding episode logs already, unless --append: a second run would
    mix its logs with the first's without a word, and whatever reads the folder reads both."""
    from qube_koopman.daq.log.names import find_logs

    if append or not folder.is_dir():
        return
    found = len(find_logs(folder))
    if found:
        raise CliError(
            f"{folder}: already holds {found} episode log{'s' if found != 1 else ''}; add --append to add "
            "this run's to them, or give another --out"
        )


def _check_writable(folder: Path) -> None:
    import tempfile

    try:
        output_dir(folder)  # a folder it creates goes again if the run fails before writing a log
    except CliError:
        pass  # said below, in the run's words
    try:
        folder.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryFile(dir=folder):
            pass
    except OSError as exc:
        raise CliError(f"cannot write episode logs to {folder}: {exc.strerror or exc}") from None


def main(argv: list[str] | None = None) -> int:
    """Run ``qube-run``; returns the exit status (see ``qube-run --help``)."""
    args = parse_args(build_parser(), argv)
    if isinstance(args, int):  # --help, or a usage error already explained in one line
        return args
    # Ctrl-C or SIGTERM reach run_command only before the episodes (nothing written yet): while
    # they run, _collect's handlers stop them with the motor at 0 V and the logs closed as aborted.
    return run_command(PROG, _run, args)


def _check_backend_options(args) -> None:
    if args.backend == "serial":
        if not args.port:
            raise CliError(
                "--backend serial needs --port DEV (the bridge's serial device, or the path qube-emulate prints)"
            )
        if args.realtime:
            raise CliError("--realtime is for --backend sim: the bridge's clock paces the serial backend")
        if args.plant is not None:
            raise CliError("--plant is for --backend sim: the serial backend drives a real (or emulated) pendulum")
        if args.no_load:
            raise CliError("--no-load is for --backend sim: the serial backend drives a real (or emulated) pendulum")
    elif args.check:
        raise CliError("--check is for --backend serial (the pre-flight of the real rig)")
    elif args.spin and not args.realtime:
        raise CliError("--spin is for a loop that waits: give --realtime (a free-running simulator never waits)")
    elif args.port is not None or args.baud is not None or args.link_timeout is not None:
        raise CliError("--port, --baud and --link-timeout are for --backend serial")


def _jobs(args, n_episodes: int) -> int:
    """The worker processes of the run (--n-jobs); 1: every episode in this process.

    The first episode runs in this process and the others share the workers: one worker would
    only add its start-up to a serial run. Where episodes cannot run side by side, the default
    (and -1) mean 1, and N > 1 is refused.
    """
    alone = [
        (option, why)
        for option, why, given in (
            ("--backend serial", "one rig", args.backend == "serial"),
            ("--rerun", "one live view", args.rerun is not None),
            ("--rerun-save", "one recording", args.rerun_save is not None),
            ("--rt-cpu", "one pinned process", args.rt_cpu is not None),
            ("--rt-priority", "one real-time process", args.rt_priority is not None),
            *((ext.option, "one model kept up to date", True) for ext in args.extensions),
        )
        if given
    ]
    if alone and args.n_jobs is not None and args.n_jobs > 1:
        option, why = alone[0]
        raise CliError(
            f"--n-jobs {args.n_jobs}: {option} runs one episode at a time ({why}); leave --n-jobs out or give 1"
        )
    if alone:
        return 1
    from qube_koopman.daq.parallel import resolve_n_jobs

    return resolve_n_jobs(-1 if args.n_jobs is None else args.n_jobs, n_episodes - 1)


def _replay(args, rate: float, swing_up=None):
    """Plans repeating the --replay logs' excitations (each swung up first with ``swing_up``), and the
    longest one's settings (for progress)."""
    from qube_koopman.daq.replay import replay_plans
    from qube_koopman.core.controller_file import load_controller

    controller = None
    if args.controller is not None:
        controller = load_controller(args.controller, args.discretization, 1.0 / rate)
    twins = loads = relaxations = None
    if args.backend == "sim":  # each log on its recording day's twin, when the plant file knows the day
        plant = _load_plant_file(args.plant)
        twins = plant.params_for_logs
        if plant.load is not None and not args.no_load:  # and with its day's load, when the file has one
            loads = plant.loads_for_logs
        if plant.relaxation is not None:  # and its day's cables' relaxation
            relaxations = plant.relaxations_for_logs
    try:
        plans = replay_plans(args.replay, controller, twins=twins, loads=loads, relaxations=relaxations)
    except ValueError as exc:
        raise CliError(f"{exc} (--replay)") from None
    if swing_up is not None:
        from dataclasses import replace

        plans = [replace(plan, swing_up=swing_up) for plan in plans]
    args.episodes = len(plans)
    from qube_koopman.daq.excitation import ExcitationSettings

    longest = max(plans, key=lambda p: p.n_samples)
    return plans, ExcitationSettings.from_dict(longest.excitation_info["settings"])


def _load_plant(path):
    """The --plant file's parameters (the defaults without one); a one-line error when unreadable."""
    return _load_plant_file(path).params


def _load_plant_file(path):
    """The --plant file (the shipped twin's without one), with its setups; a one-line error when unreadable."""
    from qube_koopman.sim.pendulum.params_file import PlantFileError, plant_file

    try:
        return plant_file(path)
    except PlantFileError as exc:
        raise CliError(str(exc)) from None


def _make_backend(args, limits, backend_seed: int, rate: float):
    """The backend the options ask for, connected; a one-line error when it cannot be."""
    if args.backend == "sim":
        from qube_koopman.daq.backends import SimBackend

        plant = _load_plant_file(args.plant)
        return SimBackend(
            params=plant.params,
            load=None if args.no_load else plant.load,
            relaxation=plant.relaxation,
            perturbation=math.radians(args.perturbation),
            seed=backend_seed,
            realtime=args.realtime,
            dt=1.0 / rate,
            start="hanging" if args.swing_up else "upright",
            spin=args.spin,
        )
    from qube_koopman.daq.backends import BackendFault
    from qube_koopman.daq.backends.serial import DEFAULT_BAUD, DEFAULT_LINK_TIMEOUT, SerialBackend

    link_timeout = DEFAULT_LINK_TIMEOUT if args.link_timeout is None else args.link_timeout / 1e3
    backend = SerialBackend(
        args.port,
        args.baud or DEFAULT_BAUD,
        rate_hz=round(rate),
        max_voltage=limits.max_voltage,
        link_timeout=link_timeout,
        spin=args.spin,
    )
    try:
        backend.open()
    except BackendFault as exc:
        backend.close()
        raise CliError(str(exc), status=1) from None
    return backend


def _preflight(backend) -> int:
    """``--check``: the pre-flight report on standard output; 0 when every check passed."""
    from qube_koopman.daq.backends import BackendFault
    from qube_koopman.daq.preflight import preflight

    try:
        report = preflight(backend)
    except BackendFault as exc:
        raise CliError(f"check failed: {exc}", status=1) from None
    finally:
        backend.close()
    print(f"pre-flight of the bridge on {backend.port}:\n{report.text()}")
    if not report.ok:
        print(f"{PROG}: check failed: {', '.join(report.failed)}", file=sys.stderr)
        return 1
    return 0


def _where(args, backend) -> str:
    if args.backend == "sim":
        jobs = f", {args.n_jobs} worker processes" if args.n_jobs > 1 else ""
        return f"the simulator ({'paced in real time' if args.realtime else 'free-running'}{jobs})"
    info = backend.describe()
    kind = "emulated bridge" if info.get("emulated") else "bridge"
    return f"the {kind} on {args.port} (firmware {info.get('firmware', '?')})"


def _run(args) -> int:
    _check_backend_options(args)
    args.extensions = [ext for ext in _extensions() if ext.active(args)]
    from qube_koopman.daq.safety import SafetyLimits
    from qube_koopman.daq.session import MAX_EPISODES, excitation_settings, plan_episodes, run_seeds
    from qube_koopman.core.qube import MAX_DURATION
    from qube_koopman.core.controller_file import load_controller

    if args.episodes > MAX_EPISODES:
        raise CliError(f"--episodes {args.episodes}: at most {MAX_EPISODES:,} in one run (start another run for more)")
    if args.duration > MAX_DURATION:
        raise CliError(f"--duration {args.duration:g}: at most {MAX_DURATION:g} s (24 h) per episode")
    rate = 1.0 / QUBE_SAMPLE_PERIOD
    try:
        settings = excitation_settings(args.duration, rate)
    except ValueError as exc:
        raise CliError(f"--duration: {exc}") from None
    try:
        controller = load_controller(args.controller, args.discretization, 1.0 / rate)
    except ValueError as exc:
        raise CliError(f"{exc} (--controller)") from None
    _check_on_twin(args, controller)
    if args.max_voltage > 10.0:
        raise CliError(f"--max-voltage {args.max_voltage:g}: at most the rig's 10 V")
    try:
        limits = SafetyLimits(
            max_voltage=args.max_voltage,
            theta_limit=math.radians(args.theta_limit),
            alpha_limit=math.radians(args.alpha_limit),
        )
    except ValueError as exc:  # the start gate above --alpha-limit (the library's radians)
        raise CliError(f"--alpha-limit {args.alpha_limit:g} deg: inside the start gate ({exc})") from None
    if args.backend == "sim" and math.radians(args.perturbation) >= limits.start_alpha:
        raise CliError(
            f"--perturbation {args.perturbation:g} deg: the simulated pendulum must start inside "
            f"the {math.degrees(limits.start_alpha):g} deg start gate (it cannot be raised by hand)"
        )
    check_output_file(args.rerun_save, "--rerun-save", args.force)
    if not args.check:  # a check writes no log
        _check_not_adding(args.out, args.append)

    swing_up = _swing_up(args, limits)
    seed = args.seed if args.seed is not None else fresh_seed()
    seeds, backend_seed = run_seeds(seed, args.episodes)
    run_id = f"qube-run seed {seed}"
    plans = plan_episodes(
        controller, seeds, settings, source=run_id, extra={"run_seed": seed, "command": "qube-run"}, swing_up=swing_up
    )
    if args.replay:
        plans, settings = _replay(args, rate, swing_up)
    args.n_jobs = _jobs(args, len(plans))
    backend = _make_backend(args, limits, backend_seed, rate)
    if args.check:
        return _preflight(backend)  # closes the backend
    try:
        # Only now: a refused command, or a bridge check, leaves no empty episode folder behind.
        _check_writable(args.out)
        return _collect(args, backend, plans, settings, limits, seed, rate)
    finally:
        backend.close()


def _check_on_twin(args, controller) -> None:
    """A --controller file checked on the twin's loop linearized at upright before anything runs: on the rig a
    diverging loop is refused (exit 2) unless --run-unstable, on the simulator a warning line; kinds beyond LTI
    (the MPC) are not judged. The shipped gains (no --controller) balance the twin, and a pre-flight runs none."""
    if args.run_unstable and args.backend != "serial":
        raise CliError("--run-unstable is for --backend serial: the simulator runs such a controller with a warning")
    if args.controller is None or args.check:
        return
    from qube_koopman.daq.twin_check import check_controller_file_on_twin

    params = _load_plant(args.plant) if args.backend == "sim" else None  # the simulator: the plant it runs
    warning = check_controller_file_on_twin(controller, str(args.controller), args.backend, args.run_unstable, params)
    if warning:
        print(f"{PROG}: warning: {warning}", file=sys.stderr, flush=True)


def _swing_up(args, limits):
    """The --swing-up settings (None without it); the swing-up options alone are refused."""
    given = [
        option
        for option, value in (
            ("--catch-angle", args.catch_angle),
            ("--swing-up-time", args.swing_up_time),
            ("--swing-up-voltage", args.swing_up_voltage),
        )
        if value is not None
    ]
    if not args.swing_up:
        if given:
            raise CliError(f"{given[0]} is for --swing-up")
        return None
    from qube_koopman.daq.safety import SwingUpLimits
    from qube_koopman.daq.swing_up import EnergyController, SwingUp

    catch = DEFAULT_CATCH_ANGLE if args.catch_angle is None else args.catch_angle
    if math.radians(catch) >= limits.alpha_limit:
        raise CliError(f"--catch-angle {catch:g} deg: must be inside --alpha-limit ({args.alpha_limit:g} deg)")
    volts = DEFAULT_SWING_UP_VOLTAGE if args.swing_up_voltage is None else args.swing_up_voltage
    if volts > limits.max_voltage:
        raise CliError(f"--swing-up-voltage {volts:g}: at most the clamp, {limits.max_voltage:g} V")
    # On the simulator the energy controller's model is the simulated pendulum; on the rig, the twin.
    params = _load_plant(args.plant) if args.backend == "sim" else None
    energy = EnergyController() if params is None else EnergyController(params)
    return SwingUp(
        energy=energy,
        limits=SwingUpLimits(
            arm_limit=limits.theta_limit,
            max_voltage=volts,
            time_limit=DEFAULT_SWING_UP_TIME if args.swing_up_time is None else args.swing_up_time,
        ),
        catch_angle=math.radians(catch),
    )


def _rerun_sink(args):
    """The rerun view or recording the options ask for, or None."""
    if args.rerun is None and args.rerun_save is None:
        return None
    from qube_koopman.daq.viz import RerunSink, RerunUnavailable, open_recording

    try:
        recording = open_recording(live=args.rerun is not None, url=args.rerun or None, save=args.rerun_save)
    except RerunUnavailable as exc:
        raise CliError(f"--rerun: {exc}", status=1) from None
    return RerunSink(recording)


def _worker_logging(level: int) -> None:
    """A worker process's log lines: as this process's (``-v``, ``-q``), on the same stderr, without the banner."""
    configure_logging(PROG, argparse.Namespace(quiet=True)).setLevel(level)


def _episodes(args, backend, plans, mcap, sinks, limits, stop, book, timing):
    """Run the episodes, in this process with one job, else the first here and the others in workers."""
    if args.n_jobs == 1:
        from qube_koopman.daq.session import run_episodes

        return run_episodes(
            backend, plans, [mcap, *sinks], limits=limits, stop=stop, on_result=book.serial, timing=timing
        )
    import functools
    import logging

    from qube_koopman.core.console import LOGGER
    from qube_koopman.daq.parallel import run_episodes_parallel

    return run_episodes_parallel(
        backend,
        plans,
        args.out,
        n_jobs=args.n_jobs,
        sinks=sinks,
        limits=limits,
        stop=stop,
        on_result=book.parallel,
        timing=timing,
        worker_setup=functools.partial(_worker_logging, logging.getLogger(LOGGER).level),
    )


def _collect(args, backend, plans, settings, limits, seed: int, rate: float) -> int:
    from qube_koopman.daq.cli.run_output import EpisodeBook, RunProgress, report
    from qube_koopman.daq.safety import StopRequest, stop_on_signals
    from qube_koopman.daq.sinks import McapSink
    from qube_koopman.daq.timing import TimingRecord, realtime_scheduling

    mcap = McapSink(args.out)
    rerun_sink = _rerun_sink(args)
    print(
        f"{PROG}: {args.episodes} episode{'s' if args.episodes != 1 else ''} x {args.duration:g} s on "
        f"{_where(args, backend)}, seed {seed}, controller "
        f"{args.controller or 'of the paper dataset'} ({_controller_form(plans[0].controller, args)}), "
        f"logs to {args.out}/",
        flush=True,
    )
    progress = RunProgress(args.episodes, settings.n_samples, enabled=not args.quiet)  # after the header line
    stop = StopRequest()
    view = None if rerun_sink is None else rerun_sink.recording
    added = [sink for ext in args.extensions for sink in ext.start(args, mcap, stop, view)]
    sinks = [*([rerun_sink] if rerun_sink is not None else []), progress, *added]
    book = EpisodeBook(progress, mcap)
    timing = TimingRecord(1.0 / rate)  # all episodes' ticks, in bounded memory
    try:
        with realtime_scheduling(args.rt_cpu, args.rt_priority) as rt, stop_on_signals(stop):
            if args.rt_cpu is not None or args.rt_priority is not None:
                print(f"{PROG}: real-time scheduling: {rt.describe()}", flush=True)
            run = _episodes(args, backend, plans, mcap, sinks, limits, stop, book, timing)
    finally:
        progress.clear()
        recording_problem = _finish_rerun(rerun_sink)
    # The summary whatever became of the recording: the logs are there. A run an extension ended (its goal
    # reached) ran as planned.
    ended = any(ext.ended_run() for ext in args.extensions)
    status = report(args, run, book, timing.stats(), len(run.results) if ended else len(plans), recording_problem)
    for ext in args.extensions:
        ext.finish(args)
    return status


def _finish_rerun(rerun_sink) -> str | None:
    """End the rerun view or recording; what went wrong with it, or None."""
    if rerun_sink is None:
        return None
    from qube_koopman.daq.viz import RecordingFailed

    try:
        rerun_sink.finish()
    except RecordingFailed as exc:
        return str(exc)
    return None


if __name__ == "__main__":
    sys.exit(main())
