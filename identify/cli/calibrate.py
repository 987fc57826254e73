"""``qube-calibrate``: fit the simulator's physical parameters to episode logs.

    qube-calibrate LOGS... --out plant.toml [--split paper] [--validate LOGS...] [--report DIR]

Writes a plant file (``sim.pendulum.params_file``) that ``qube-run --plant``
and ``qube-emulate --plant`` load. With ``--split paper`` the logs sorted by
name are split as in the paper (first 28 fit, the rest validate); with
``--validate`` the given logs are used to validate. The logs may come from
several controllers: the fit is open loop (the logged voltage drives each
segment), so it takes them all at once and gives each controller's residual;
validation replays each controller's logs in closed loop through the
calibrated twin, predicts 0.2 s open loop, and gives per controller the
median standard deviation ratios, overall, of the slow motion (below
0.5 Hz) and in the bands below 0.3, 0.3-1, 1-3 and above 3 Hz
(``--weighting controller`` makes each controller's logs count alike in the
fit, however many each has). What changes between recordings is fitted per
setup, the rest of the physics once (``--setups``): by default the cables'
stiffness per recording day, which the plant file keeps beside the central
value and a replay of a log of that day uses; the
plant file's provenance then records the balanced count, the standard
deviation ratios' minimum and maximum (theta, alpha, voltage) and the mean
replay NRMSE.

``--report DIR`` writes ``DIR/report.md``: the tables printed, and with
validation the power in frequency bands (0-1, 1-3, 3-10, 10-30, 30-100 Hz)
of theta, alpha and voltage, twin vs real (Welch spectra averaged over the
validation episodes). With validation it also writes ``DIR/calibration.rrd``
(one per controller: ``calibration_2.rrd``...),
a rerun recording of each validation episode's measured and twin
trajectories and of the spectra; that needs rerun-sdk (the optional ``viz``
extra), without which a warning says it was skipped.
"""

from __future__ import annotations

import argparse
import logging
import sys
import time

import numpy as np

from qube_koopman.core.cli import (
    OneLineParser,
    add_force_option,
    add_standard_options,
    path,
    positive_number,
    whole_number,
)
from qube_koopman.core.command import CliError, check_output_file, check_output_folder, output_dir, run_command
from qube_koopman.identify.cli.common import expand_logs
from qube_koopman.identify.command_warnings import ONE_LINE_WARNINGS

#: The fits of the physics that --relaxation adds by default, each under the relaxation estimated before
#: (on the paper's 28 training logs and six soft ones the second moved the relaxation by 1-10 % and the
#: held-out bands by at most 0.01).
RELAXATION_PASSES = 2

_log = logging.getLogger(__name__)

#: The longest transport delay --delay takes (samples; 1 s at 500 Hz).
_MAX_DELAY_SAMPLES = 500

__all__ = ["main"]


def _parser() -> argparse.ArgumentParser:
    p = OneLineParser(
        prog="qube-calibrate",
        description=__doc__.split("\n\n")[0].replace("``", ""),
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("logs", nargs="+", type=path, help="episode logs (.mcap files or folders of them) to fit")
    p.add_argument("--out", type=path, required=True, metavar="FILE.toml", help="plant file to write")
    p.add_argument(
        "--split",
        choices=("none", "paper"),
        default="none",
        help="paper: fit the first 28 logs by name, validate on the rest",
    )
    p.add_argument(
        "--validate",
        nargs="+",
        type=path,
        default=[],
        metavar="LOG",
        help="logs (files or folders) to validate on (never fitted)",
    )
    p.add_argument(
        "--report",
        type=path,
        default=None,
        metavar="DIR",
        help="write report.md there (the tables; with validation also band powers twin vs real) and, "
        "with validation, calibration.rrd (rerun recording of the replayed episodes and spectra; "
        "needs the viz extra)",
    )
    p.add_argument("--horizon", type=float, default=0.2, metavar="S", help="shooting segment length (default 0.2)")
    p.add_argument(
        "--delay", type=whole_number(0), default=0, metavar="N", help="transport delay in samples (default 0)"
    )
    p.add_argument(
        "--max-nfev", type=whole_number(1), default=40, metavar="N", help="solver iteration budget (default 40)"
    )
    p.add_argument(
        "--weighting",
        choices=("episode", "controller"),
        default="episode",
        help="with logs of several controllers: episode (default) counts every episode alike; "
        "controller weights the residuals so that each controller's logs count alike",
    )
    p.add_argument(
        "--setups",
        choices=("cables", "cables-and-delay", "none"),
        default="cables",
        help="what changes between recordings gets a value per setup, the rest of the physics is shared: "
        "cables (default): the stiffness of the cables between the arm's hub and the base per recording "
        "day (they are dressed anew when the rig is set up); cables-and-delay: also the command delay per "
        "recording session (logs started less than 10 minutes apart: the host's latency); none: one value "
        "of each for all logs. A replay of a log recorded then uses its setups' values",
    )
    _add_physics_options(p)
    add_force_option(p)
    add_standard_options(p, "no progress line")
    return p


def _add_physics_options(p: argparse.ArgumentParser) -> None:
    """What the fit adds to the physics or keeps from it: --load, --tilt, --hold."""
    p.add_argument(
        "--load",
        action="store_true",
        help="also estimate the arm's random load (a slow torque at the motor, first-order or random walk) "
        "from the fitted logs, per recording day and over all of them, by the arm's equation run backwards "
        "and a spectral fit; write it into the plant file's [load] tables, and with validation replay the "
        "held-out logs with it too (band table, load off beside on)",
    )
    p.add_argument(
        "--relaxation",
        action="store_true",
        help="with --load: first take out of the reconstructed load the part the arm's motion drives, the cables' "
        "relaxation (stiffer against fast motion, softer held still, relaxing over a time from 0.125 to 8 s), "
        "estimated per recording day with the logs' excitation (the arm's reference, the feedforward) as the "
        "instrument; write it into [relaxation] tables, fit the random load on what it leaves, and with "
        "validation replay the held-out logs with both",
    )
    p.add_argument(
        "--relaxation-time",
        type=positive_number,
        metavar="S",
        help="with --relaxation: fit the relaxation at this time constant (s) instead of choosing it from "
        "0.125-8 s (the report gives each time's share, so a choice can be rerun by hand)",
    )
    p.add_argument(
        "--relaxation-passes",
        type=int,
        default=None,
        metavar="N",
        help=f"with --relaxation: fit the physics again N times (default {RELAXATION_PASSES}), each time with every "
        "log simulated under the relaxation estimated before, so that the cable spring is fitted beside it rather than "
        "taking up its fast stiffness; 0: the relaxation is estimated after the fit only (the report gives "
        "each pass's relaxation and residuals)",
    )
    p.add_argument(
        "--tilt",
        action="store_true",
        help="also estimate the base's tilt per recording day (tilt_x: the pendulum's balance angle moving "
        "with the arm's angle), from the fitted logs' slow balance angles before the fit; the fit then "
        "simulates each log with its day's tilt, and the plant file's setups keep it",
    )
    p.add_argument(
        "--hold",
        action="append",
        type=_held_value,
        default=[],
        metavar="NAME=VALUE",
        help="hold a physical parameter at VALUE instead of fitting it, the rest fitted around it (repeatable; "
        "for example cable_softening=0: a linear cable spring); the report marks it held and the plant file's "
        "provenance records it. NAME is one of the fitted parameters: " + ", ".join(_FITTED),
    )


#: The parameters the fit takes (shooting.PHYSICAL_NAMES, named here without importing scipy for --help).
_FITTED = ("km", "Dr", "Cr", "Lp", "Dp", "dead_zone", "Jh", "delay", "Kr", "cable_softening")


def _held_value(text: str) -> tuple[str, float]:
    """``--hold NAME=VALUE`` parsed (argparse turns the ValueError into a one-line usage error)."""
    name, sep, value = text.partition("=")
    if not sep or name.strip() not in _FITTED:
        raise argparse.ArgumentTypeError(f"expected NAME=VALUE with NAME one of {', '.join(_FITTED)}, got {text!r}")
    try:
        number = float(value)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{name.strip()}: {value!r} is not a number") from None
    if not np.isfinite(number):
        raise argparse.ArgumentTypeError(f"{name.strip()}: {value!r} is not a finite number")
    return name.strip(), number


def _read(paths, segment: float, role: str):
    """The logs' episodes, each long enough for ``role``: the first second skipped, then ``segment`` seconds."""
    from qube_koopman.core.qube import SKIP_SAMPLES
    from qube_koopman.identify.data.logs import load_logs, read_episodes

    try:
        logs = load_logs(paths, strict=True, refusal="refused: qube-calibrate fits complete, readable logs only")
    except ValueError as exc:
        raise CliError(str(exc)) from None
    episodes = read_episodes(logs)
    for log_path, episode in zip(paths, episodes):
        _check_measurements(log_path, episode)
        need = SKIP_SAMPLES + int(round(segment / episode.dt)) + 1
        if len(episode) < need:
            raise CliError(
                f"{log_path}: {len(episode)} samples ({len(episode) * episode.dt:.2f} s), too short to {role}: "
                f"qube-calibrate skips the first {SKIP_SAMPLES * episode.dt:g} s of a log and needs "
                f"{segment:g} s after it ({need} samples)"
            )
    return episodes


#: The largest angle (rad) and voltage (V) a log's sample may hold: the rig's encoders count a few
#: turns at most and its amplifier gives 10 V; a value past these is a damaged or crafted log.
_LARGEST_ANGLE, _LARGEST_VOLTAGE = 100.0, 100.0


def _check_measurements(path, episode) -> None:
    """Refuse a log whose angles or voltage are non-finite or absurd (they would make the fit's arithmetic overflow)."""
    for name, values, largest in (
        ("theta", episode.states[:, 0], _LARGEST_ANGLE),
        ("alpha", episode.states[:, 1], _LARGEST_ANGLE),
        ("voltage", episode.plant_input, _LARGEST_VOLTAGE),
    ):
        bad = np.flatnonzero(~(np.abs(values) <= largest))  # NaN included
        if bad.size:
            raise CliError(
                f"{path}: {name} at sample {bad[0]} is {float(values[bad[0]])!r} ({bad.size} sample"
                f"{'s' if bad.size > 1 else ''} beyond +-{largest:g}); refused: qube-calibrate fits measured logs only"
            )


def _run(args) -> int:
    from qube_koopman.identify.calibrate.report import calibration_text, write_report
    from qube_koopman.identify.calibrate.validate import OPEN_LOOP_HORIZON

    if args.relaxation and not args.load:
        raise CliError("--relaxation needs --load: it is the part of the load that the arm's motion drives")
    if args.relaxation_time is not None and not args.relaxation:
        raise CliError("--relaxation-time needs --relaxation")
    if args.relaxation_passes is not None and not args.relaxation:
        raise CliError("--relaxation-passes needs --relaxation")
    if args.relaxation_passes is None:
        args.relaxation_passes = RELAXATION_PASSES
    if args.relaxation_passes < 0:
        raise CliError(f"--relaxation-passes must be 0 or more, got {args.relaxation_passes}")
    fit_paths, val_paths = _checked_paths(args)
    episodes = _read(fit_paths, args.horizon, "fit")
    held = _read(val_paths, OPEN_LOOP_HORIZON, "validate") if val_paths else []  # refused before the fit, not after
    started = time.perf_counter()
    tilts = _fit_tilts(episodes, fit_paths) if args.tilt else None
    cal, plant, fit_groups = _calibrate(episodes, args, tilts)
    seconds = time.perf_counter() - started  # the physics' fit (with --relaxation, all its passes)
    names = [p.name for p in fit_paths]
    loads_text = passes = ""
    if args.load:
        times = None if args.relaxation_time is None else (args.relaxation_time,)
        loads_text = _fit_loads(episodes, plant, args.relaxation, times)
        if args.relaxation and args.relaxation_passes:
            cal, plant, loads_text, passes = _refit_with_relaxation(episodes, args, tilts, (cal, plant), times)
            seconds = time.perf_counter() - started
    text = calibration_text(cal, names, seconds, fit_groups)
    for section in (_tilt_text(tilts) if tilts is not None else "", passes, loads_text):
        if section:
            text += "\n" + section
    provenance = _provenance(args, cal, names, episodes[0].metadata.software_version, seconds, fit_groups)
    validation, val_dt = None, None
    if val_paths:
        validation, val_dt, summary = _validate_and_record(held, (val_paths, fit_paths), plant, fit_groups, provenance)
        text += summary
    plant.provenance = provenance
    _save(cal, plant, args.out)
    print(text)
    if not cal.converged_:
        _log.warning(
            "the fit did not converge within --max-nfev %d steps (its cost was still falling): %s holds the last "
            "step's parameters; run again with a larger --max-nfev to finish it",
            args.max_nfev,
            args.out,
        )
    print(f"wrote {args.out}: qube-run --plant {args.out}")
    if args.report is not None:
        write_report(output_dir(args.report), text, validation, val_dt)
    return 0


def _checked_paths(args) -> tuple[list, list]:
    """The logs to fit and to validate on (``--split paper`` holds some out), once the options and the
    outputs are checked: before the fit's minute of work, not after."""
    from qube_koopman.identify.model_selection.split import paper_split

    fit_paths, val_paths = expand_logs(args.logs), expand_logs(args.validate)
    if args.split == "paper":
        try:
            fit_paths, held = paper_split(fit_paths)
        except ValueError as exc:
            raise CliError(str(exc)) from None
        val_paths += held
    if not 0.004 <= args.horizon <= 2.0:
        raise CliError(f"--horizon must be between 0.004 and 2 s, got {args.horizon}")
    if args.delay > _MAX_DELAY_SAMPLES:
        raise CliError(
            f"--delay must be at most {_MAX_DELAY_SAMPLES} samples (the QUBE's transport delay is a few), "
            f"got {args.delay}"
        )
    check_output_file(args.out, force=args.force)
    check_output_folder(args.report, ("report.md", "calibration.rrd"), "--report", args.force)
    return fit_paths, val_paths


def _fit_tilts(episodes, paths) -> dict:
    """Each recording day's tilt of the base (``--tilt``), from its fitted logs' balance angles."""
    from qube_koopman.identify.calibrate.tilt_fit import fit_tilt
    from qube_koopman.sim.pendulum import PendulumParameters
    from qube_koopman.sim.pendulum.params_file import recording_day

    days: dict[str, list] = {}
    for e, log_path in zip(episodes, paths):
        days.setdefault(recording_day(e.metadata.start_time), []).append((e, log_path))
    tilts = {}
    for day, pairs in days.items():
        members = [e for e, _ in pairs]
        if len(members) < 2:
            raise CliError(f"{pairs[0][1]}: the only log of {day}: --tilt needs two or more logs of each day")
        try:  # the balance angle needs the pendulum's masses and length, which the fit barely moves (the workbook's)
            tilts[day] = fit_tilt([e.states for e in members], PendulumParameters.previous(), members[0].dt)
        except ValueError as exc:
            raise CliError(f"--tilt: {day}: {exc}") from None
    return tilts


def _tilt_text(tilts: dict) -> str:
    rows = [
        f"| {day} | {fit.n_episodes} | {1e3 * fit.tilt_x:+.2f} +- {1e3 * fit.standard_errors['tilt_x']:.2f} | "
        f"{fit.r2:.2f} |"
        for day, fit in sorted(tilts.items())
    ]
    header = "| recording day | logs | tilt_x (mrad) | R^2 of the slow balance angle |\n|---|---|---|---|"
    return "The base's tilt (the pendulum's balance angle against sin(theta)):\n\n" + "\n".join([header, *rows]) + "\n"


def _calibrate(episodes, args, tilts: dict | None = None, loads=None) -> tuple:
    """The fitted PlantCalibration, its plant file (without provenance) and the fitted logs' controller groups;
    with ``tilts`` (per recording day) each log simulated with its day's tilt, which the setups keep; with
    ``loads`` (one per log) each log simulated with that known torque on the arm."""
    from qube_koopman.identify.calibrate import HoldRefused, PlantCalibration
    from qube_koopman.identify.calibrate.validate import controller_groups
    from qube_koopman.sim.pendulum.params_file import PlantFile, recording_day

    fit_groups = controller_groups(episodes)
    group_of = {i: label for label, members in fit_groups for i in members}
    cal = PlantCalibration(
        horizon=args.horizon,
        delay=args.delay,
        max_nfev=args.max_nfev,
        progress=not args.quiet,
        weighting="group" if args.weighting == "controller" else "episode",
        hold=dict(args.hold),
    )
    try:
        cal.fit(
            [e.states for e in episodes],
            [e.plant_input for e in episodes],
            episodes[0].dt,
            [group_of[i] for i in range(len(episodes))],
            _setups(episodes, args.setups),
            fixed=None
            if tilts is None
            else {"tilt_x": [tilts[recording_day(e.metadata.start_time)].tilt_x for e in episodes]},
            loads=loads,
        )
    except HoldRefused as exc:  # --hold's value out of range, or a parameter with a value per setup
        raise CliError(f"--hold: {exc}" + (" (--setups none fits one value)" if exc.per_setup else "")) from None
    values, errors = dict(cal.setup_values_), dict(cal.setup_errors_)
    if tilts is not None:
        values["tilt_x"] = {day: fit.tilt_x for day, fit in tilts.items()}
        errors["tilt_x"] = {day: fit.standard_errors["tilt_x"] for day, fit in tilts.items()}
    plant = PlantFile(
        cal.params_,
        cal.standard_errors_,
        setups=_by_setup(values),
        setup_standard_errors=_by_setup(errors),
    )
    return cal, plant, fit_groups


def _provenance(args, cal, names: list[str], software_version, seconds: float, fit_groups) -> dict:
    """The plant file's provenance: what was fitted, how, and how well."""
    provenance = {
        "source": "qube-calibrate",
        "logs": names,
        "software_version": software_version,
        "created": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "residual_rms_theta": float(cal.residual_rms_[:, 0].mean()),
        "residual_rms_alpha": float(cal.residual_rms_[:, 1].mean()),
        "horizon_s": args.horizon,
        "delay_samples": args.delay,
        "seconds": round(seconds, 1),
        "weighting": args.weighting,
        "setups": args.setups,
        "tilt": bool(args.tilt),
        **({"relaxation": True} if args.relaxation else {}),
        **({"relaxation_time": args.relaxation_time} if args.relaxation_time is not None else {}),
        **({"relaxation_passes": args.relaxation_passes} if args.relaxation else {}),
    }
    if args.hold:
        provenance["held"] = [f"{name}={value:g}" for name, value in args.hold]
    if len(fit_groups) > 1:
        provenance["fitted_controllers"] = [f"{label} ({len(members)} logs)" for label, members in fit_groups]
    return provenance


def _validate_and_record(held, paths: tuple, plant, fit_groups, provenance: dict) -> tuple:
    """The validation logs replayed on ``plant`` (``paths``: the validation and the fitted logs' paths), their
    figures added to ``provenance``; returns the validation, its sample time and the report's summary."""
    val_paths, fit_paths = paths
    refitted = _also_fitted(val_paths, fit_paths)
    validation, val_dt, summary, with_load = _validate(held, val_paths, plant, set(refitted))
    replays = [v[0] for v in validation]
    ratio = np.concatenate([r.std_ratio for r in replays])
    if refitted:
        shown = ", ".join(p.name for p in refitted[:3]) + (", ..." if len(refitted) > 3 else "")
        _log.warning(
            "%d of the %d validation logs are fitted too (%s): their replay is not a held-out check",
            len(refitted),
            len(val_paths),
            shown,
        )
    provenance.update(
        validated_on=[p.name for p in val_paths],
        validated_also_fitted=len(refitted),
        balanced=int(sum(r.balanced.sum() for r in replays)),
        std_ratio_min=[round(float(v), 4) for v in ratio.min(axis=0)],
        std_ratio_max=[round(float(v), 4) for v in ratio.max(axis=0)],
        replay_nrmse_percent=round(float(np.concatenate([r.nrmse for r in replays]).mean()), 3),
    )
    if len(validation) > 1 or len(fit_groups) > 1:
        provenance.update(
            validation_controllers=[v[3] for v in validation],
            std_ratio_median_by_controller=[
                [round(float(x), 4) for x in np.median(v[0].std_ratio, axis=0)] for v in validation
            ],
        )
    if with_load:  # per controller, with the load: the overall ratio, then each band's (theta, alpha, voltage)
        provenance["load_std_ratio_bands_by_controller"] = [
            [[round(float(x), 4) for x in row] for row in on] for _, _, on in with_load
        ]
    return validation, val_dt, summary


def _save(cal, plant, out) -> None:
    """The plant file written to ``out`` (refused when the fit is not finite)."""
    from qube_koopman.sim.pendulum.params_file import save_plant

    _check_finite(cal, out)
    try:
        save_plant(out, plant)
    except OSError as exc:
        raise CliError(f"{out}: cannot write: {exc.strerror or exc}", status=1) from None


def _fit_loads(episodes, plant, relaxation: bool = False, times=None) -> str:
    """Estimate the arm's random load from the fitted logs (each on its own twin) into ``plant``: over all
    of them (``[load]``) and per recording day (``[load_setups]``, with two days or more); with
    ``relaxation``, the cables' relaxation first (``[relaxation]``, ``[relaxation_setups]``; at the
    relaxation ``times`` given, else the grid's best) and the load from what it leaves. The report's text."""
    from qube_koopman.identify.calibrate.load_fit import (
        RELAXATION_TIMES,
        fit_load,
        fit_relaxation,
        load_text,
        reconstruct_load,
        relaxation_signals,
    )
    from qube_koopman.sim.pendulum.params_file import recording_day

    starts = [e.metadata.start_time for e in episodes]
    twins = plant.params_for_logs(starts)
    loads = [reconstruct_load(e.states, e.plant_input, p, e.dt) for e, p in zip(episodes, twins)]
    days: dict[str, list[int]] = {}
    for i, t in enumerate(starts):
        days.setdefault(recording_day(t), []).append(i)
    dt = episodes[0].dt
    groups = {f"all {len(loads)} logs": list(range(len(loads)))}
    if len(days) > 1:
        groups.update(days)
    relaxations, text = {}, ""
    try:
        if relaxation:
            thetas, excitation = zip(*map(relaxation_signals, episodes))
            for name, members in groups.items():
                relaxations[name] = fit_relaxation(
                    [loads[i] for i in members],
                    [thetas[i] for i in members],
                    [excitation[i] for i in members],
                    dt,
                    RELAXATION_TIMES if times is None else times,
                )
            text = _relaxation_text(relaxations)
        fits = {
            name: fit_load(relaxations[name].residuals if relaxation else [loads[i] for i in members], dt)
            for name, members in groups.items()
        }
    except ValueError as exc:
        raise CliError(f"--load: {exc}") from None
    central = next(iter(fits.values()))
    plant.load, plant.load_standard_errors = central.load, central.standard_errors
    if len(days) > 1:
        plant.load_setups = {day: fits[day].load for day in days}
        plant.load_setup_standard_errors = {day: fits[day].standard_errors for day in days}
    if relaxation:
        central_relaxation = next(iter(relaxations.values()))
        plant.relaxation = central_relaxation.relaxation
        plant.relaxation_standard_errors = dict(central_relaxation.standard_errors)
        per_day = len(days) > 1
        plant.relaxation_setups = {day: relaxations[day].relaxation for day in days} if per_day else {}
        plant.relaxation_setup_standard_errors = (
            {day: dict(relaxations[day].standard_errors) for day in days} if per_day else {}
        )
    return text + load_text(fits)


def _refit_with_relaxation(episodes, args, tilts, first: tuple, times) -> tuple:
    """``--relaxation-passes`` fits of the physics, each simulating every log with the relaxation the pass
    before estimated (its torque along the logged arm angle, :meth:`CableRelaxation.torque_of`), then the
    relaxation and the load estimated again on the new twin: (calibration, plant file, the loads' report text,
    the passes' report section).

    The first fit knows nothing of the relaxation, so its cable spring takes up the relaxation's fast
    stiffness over its 0.25 s segments; told the relaxation's torque, the spring is fitted beside it (on the
    paper's 28 training logs and six soft ones the segments' residuals fell by 12 %, and the held-out rig
    logs' 1-3 Hz band came back from 0.96 / 0.96 / 0.93 of the real to 0.99 / 0.99 / 0.98)."""
    cal, plant = first
    starts = [e.metadata.start_time for e in episodes]
    rows = [_pass_row(0, cal, plant)]
    loads_text = ""
    for n in range(1, args.relaxation_passes + 1):
        torques = [
            r.torque_of(np.asarray(e.states, float)[:, 0], e.dt)
            for e, r in zip(episodes, plant.relaxations_for_logs(starts))
        ]
        cal, plant, _ = _calibrate(episodes, args, tilts, torques)
        loads_text = _fit_loads(episodes, plant, True, times)
        rows.append(_pass_row(n, cal, plant))
    lines = [
        "## The relaxation in the fit",
        "",
        "Each pass fits the physics with every log simulated under the relaxation the pass before estimated (its",
        "torque along the logged arm angle), then estimates the relaxation and the load again on the new twin",
        "(`--relaxation-passes`; pass 0 is the fit without it). The tables above are the last pass's.",
        "",
        "| pass | residual RMS theta, alpha (mrad) | cost | "
        + " | ".join(f"{day}: fast, relaxing (V/rad)" for day in rows[0][3])
        + " |",
        "|---|---|---|" + "---|" * len(rows[0][3]),
    ]
    for n, rms, cost, per_day in rows:
        cells = " | ".join(f"{r.fast:.4f}, {r.relaxing:.4f}" for r in per_day.values())
        lines.append(f"| {n} | {rms[0]:.2f}, {rms[1]:.2f} | {cost:.6g} | {cells} |")
    return cal, plant, loads_text, "\n".join(lines) + "\n"


def _pass_row(n: int, cal, plant) -> tuple:
    """A pass's row of the report: its number, the fit's residual RMS (mrad), its cost, the relaxation per day."""
    per_day = dict(plant.relaxation_setups) or {"all logs": plant.relaxation}
    return n, 1e3 * np.sqrt(np.mean(cal.residual_rms_**2, axis=0)), cal.cost_, per_day


def _relaxation_text(fits: dict) -> str:
    """The report's section on the cables' relaxation: one row per group of logs, and why its time won."""
    lines = [
        "## The cables' relaxation",
        "",
        "The part of the reconstructed load that the arm's motion drives (stiffer than the twin's cables against",
        "fast motion by `fast`, softer held still by `relaxing - fast`, relaxing over `time constant`): two-stage",
        "least squares with the excitation as the instrument. The relaxation time is the one whose fit explains",
        "most of the load's excitation-driven part (below 1 Hz); the random load is fitted on what it leaves.",
        "The +- are standard errors from resampling whole logs (on twin replays they came out at about 0.7 of the",
        "estimates' spread over draws of the load).",
        "",
        "| logs | fast (V/rad) | relaxing (V/rad) | time constant (s) | load explained | excitation-driven "
        "| explained of it, per time (s) |",
        "|---|---|---|---|---|---|---|",
    ]
    for name, fit in fits.items():
        r, se = fit.relaxation, fit.standard_errors
        per_time = ", ".join(f"{t:g}: {v:.2f}" for t, v in fit.explained_by_time.items())
        lines.append(
            f"| {name} | {r.fast:.4f} +- {se['fast']:.4f} | {r.relaxing:.4f} +- {se['relaxing']:.4f} "
            f"| {r.time_constant:g} | {fit.explained:.2f} "
            f"| {fit.driven:.2f} | {per_time} |"
        )
    return "\n".join(lines) + "\n\n"


def _check_finite(cal, out) -> None:
    """Refuse to write a plant whose fitted values or standard errors are not finite numbers."""
    values = {name: getattr(cal.params_, name) for name in cal.standard_errors_}
    bad = [f"{name} = {value}" for name, value in values.items() if not np.isfinite(value)]
    bad += [f"standard error of {name} = {se}" for name, se in cal.standard_errors_.items() if not np.isfinite(se)]
    if bad:
        raise CliError(
            f"{out}: not written: the fit gave {', '.join(bad[:3])}{' ...' if len(bad) > 3 else ''} "
            "(the logs do not determine the parameters)",
            status=1,
        )


def _setups(episodes, which: str) -> dict:
    """Each episode's setups (``--setups``): its recording day for the cables, its session for the delay."""
    from qube_koopman.sim.pendulum.params_file import setup_labels

    labels = setup_labels([e.metadata.start_time for e in episodes])
    return {"cables-and-delay": labels, "cables": {"Kr": labels["Kr"]}, "none": {}}[which]


def _by_setup(per_parameter: dict) -> dict:
    """``{parameter: {setup: value}}`` turned into the plant file's ``{setup: {parameter: value}}``."""
    out: dict = {}
    for name, values in per_parameter.items():
        for label, value in values.items():
            out.setdefault(label, {})[name] = value
    return out


def _also_fitted(val_paths, fit_paths) -> list:
    """The validation logs that are fit logs too (the same file, however it was named)."""
    fitted = {p.resolve() for p in fit_paths}
    return [p for p in val_paths if p.resolve() in fitted]


def _validate(held, paths, plant, refitted=frozenset()):
    """Replay the held-out logs one controller at a time, each log on its day's twin (``plant.params_for``).

    ``refitted`` holds the paths of those logs that the fit used too: their tables say so.
    Returns the per-controller ``(replay, open_loop, names, label)`` tuples, the
    sample period, the report's text (each controller's table, then the
    summary across controllers) and, with the plant's load, per controller
    ``(label, ratios without it, ratios with it)`` (``report.load_band_ratios``).
    """
    from qube_koopman.identify.calibrate.report import (
        controller_summary_text,
        load_band_ratios,
        load_bands_text,
        validation_text,
    )
    from qube_koopman.identify.calibrate.validate import (
        OPEN_LOOP_HORIZON,
        controller_groups,
        open_loop_error,
        replay_episodes,
    )

    groups = controller_groups(held)
    several = len(groups) > 1
    twins = plant.params_for_logs([e.metadata.start_time for e in held])
    loads = plant.loads_for_logs([e.metadata.start_time for e in held])
    relaxations = plant.relaxations_for_logs([e.metadata.start_time for e in held])
    out, text, with_load = [], "", []
    for label, members in groups:
        episodes = [held[i] for i in members]
        params = [twins[i] for i in members]
        replay = replay_episodes(episodes, params)
        relaxed = [relaxations[i] for i in members] if plant.relaxation is not None else None
        open_loop = open_loop_error(episodes, params, replay.offsets, OPEN_LOOP_HORIZON, relaxation=relaxed)
        out.append((replay, open_loop, [paths[i].name for i in members], label))
        fitted = sum(paths[i] in refitted for i in members)
        text += "\n" + validation_text(*out[-1][:3], controller=label if several else None, fitted=fitted)
        if plant.load is not None:
            loaded = replay_episodes(
                episodes,
                params,
                load=[loads[i] for i in members],
                relaxation=relaxed,
            )
            with_load.append((label, load_band_ratios(replay, held[0].dt), load_band_ratios(loaded, held[0].dt)))
    dt = held[0].dt
    text += "\n" + controller_summary_text([(v[3], v[0]) for v in out], dt)
    if with_load:
        text += "\n" + load_bands_text(with_load)
    return out, dt, text, with_load


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``qube-calibrate``; returns the exit status."""
    args = _parser().parse_args(argv)
    return run_command("qube-calibrate", _run, args, one_line_warnings=ONE_LINE_WARNINGS)


if __name__ == "__main__":
    sys.exit(main())
