"""``qube-run --identify``: a model of the plant kept up to date while the episodes are recorded.

Registered with ``qube-run`` as an extension (the entry-point group ``qube_koopman.qube_run``), so that
``daq`` imports nothing from ``identify``: ``qube-run`` adds these options and feeds every episode to the
sink made here (:class:`~qube_koopman.identify.live.LiveIdentification`).
"""

from __future__ import annotations

import argparse
import statistics
import sys
from pathlib import Path
from typing import Any

from qube_koopman.core.command import CliError, check_output_folder, output_dir, write_json

__all__ = ["LiveExtension", "MODEL_FOLDER", "PROTOCOL", "send_view", "write_model"]

#: The folder of --out the final model is written to.
MODEL_FOLDER = "model"
#: How each episode's score is held out (report.json's ``live.protocol``).
PROTOCOL = (
    "each complete episode is predicted in closed loop (from its references and feedforward, its first "
    "sample the initial state) by the model fitted on the complete episodes before it, then added to the "
    "model; R^2 and NRMSE from its second sample on, as qube-identify's paper protocol"
)
#: The plateau rule's window and tolerance (--plateau).
PLATEAU_WINDOW, PLATEAU_TOLERANCE, PLATEAU_MIN_SCORED = 5, 1e-3, 10
#: The rerun view's entities (predicted against measured per episode, the score's curve).
VIEW = "identify"
#: The console's trend: the median held-out R^2 of this many last episodes.
TREND = 5
#: --until's run of episodes at or above the target.
UNTIL_PATIENCE = 3
#: The lifting ``--identify`` keeps without FLAGS. Not qube-identify's own default (the paper's poly 2 and 10
#: delays): under the rig's controller on the twin that one levels off at a held-out R^2 of about 0.85 and
#: never meets an --until of 0.98, where these 35 delays with the cubic monomials, the arm's friction shape
#: and the constant score 0.99 from the second episode on, at about 0.5 s of CPU per episode added.
LIVE_DEFAULT_FLAGS = "--poly 3 --delays 35 --friction --const"


class LiveExtension:
    """The ``--identify``, ``--until`` and ``--plateau`` options of ``qube-run``."""

    option = "--identify"

    def __init__(self) -> None:
        self.sink: Any = None  # the LiveIdentification of the run
        self.recording: Any = None  # the run's rerun view or recording (--rerun, --rerun-save)
        self.fit: Any = None  # the --identify options (live_fit_options)

    def add_arguments(self, parser: argparse.ArgumentParser) -> None:
        """The options, in their own group."""
        from qube_koopman.core.cli import finite_number

        group = parser.add_argument_group("identification while recording (--identify)")
        group.add_argument(
            "--identify",
            nargs="?",
            const="",
            default=None,
            metavar="FLAGS",
            help="keep a CL EDMD model up to date: each complete episode is first predicted by the model of "
            "the episodes before it (its held-out R^2 printed), then added; FLAGS: qube-identify's lifting "
            f'and fit options in one string (default "{LIVE_DEFAULT_FLAGS}"). The '
            f"final model goes to OUT/{MODEL_FOLDER}/ as qube-identify writes one",
        )
        group.add_argument(
            "--until",
            type=finite_number,
            default=None,
            metavar="R2",
            help=f"stop the run once the held-out R^2 of {UNTIL_PATIENCE} episodes in a row is at least R2",
        )
        group.add_argument(
            "--plateau",
            action="store_true",
            help=f"stop the run once the best held-out R^2 of the last {PLATEAU_WINDOW} episodes beats the best "
            f"before them by less than {PLATEAU_TOLERANCE:g} (after {PLATEAU_MIN_SCORED} scored episodes)",
        )

    def active(self, args: argparse.Namespace) -> bool:
        """--identify given (--until and --plateau alone are refused)."""
        if args.identify is None:
            if args.until is not None or args.plateau:
                raise CliError(f"{'--until' if args.until is not None else '--plateau'} is for --identify")
            return False
        from qube_koopman.identify.cli.identify import live_fit_options

        self.fit = live_fit_options(args.identify or LIVE_DEFAULT_FLAGS)
        return True

    def start(self, args: argparse.Namespace, logs, stop, recording=None) -> list:
        """The sink scoring and adding each episode off the loop's thread; with ``recording``, its view too."""
        from qube_koopman.identify.cli.identify import OUTPUT_FILES
        from qube_koopman.identify.live import IncrementalIdentifier, LiveIdentification, StopRule

        check_output_folder(Path(args.out) / MODEL_FOLDER, OUTPUT_FILES, force=args.force)
        fit = self.fit
        self.recording = recording
        if recording is not None:
            recording.log(f"{VIEW}/r2", "SeriesLines", static=True, names=["held-out R^2"])
        paced = args.backend != "sim" or args.realtime
        rule = StopRule(
            until=args.until,
            plateau=args.plateau,
            patience=UNTIL_PATIENCE,
            window=PLATEAU_WINDOW,
            tolerance=PLATEAU_TOLERANCE,
            min_scored=PLATEAU_MIN_SCORED,
        )
        self.sink = LiveIdentification(
            IncrementalIdentifier(fit.lifting, fit.method, fit.alpha),
            logs,
            rule,
            stop=stop,
            skip=fit.skip,
            on_score=self._on_score,
            keep_predictions=recording is not None,
            # A free-running simulator has no deadline to miss: each episode is scored on a thread before the next
            # starts (the stop rule then stops on the episode that meets it). A paced loop never waits, and its
            # refits run in a worker process: never in the loop's interpreter.
            max_behind=None if paced else 0,
            worker="process" if paced else "thread",
        )
        return [self.sink]

    def _on_score(self, live) -> None:
        self._print(live)
        if self.recording is not None and live.score is not None:
            send_view(self.recording, live)

    def _print(self, live) -> None:
        if live.score is None:
            print(f"identify: {live.log.name}: the model's first episode ({live.cpu_seconds:.2f} s CPU)", flush=True)
            return
        r2 = [s.score.r2 for s in self.sink.scores if s.score is not None][-TREND:]
        trend = f"; median of the last {len(r2)} {statistics.median(r2):.4f}" if len(r2) > 1 else ""
        print(
            f"identify: {live.log.name}: held-out R^2 {live.score.r2:.4f}, NRMSE {live.score.nrmse:.2f} % "
            f"(model of {live.index} episodes{trend}; added in {live.cpu_seconds:.2f} s CPU)",
            flush=True,
        )

    def ended_run(self) -> bool:
        """Whether the stop rule ended the run."""
        return self.sink is not None and self.sink.stop is not None and self.sink.stop.reason.startswith("identified:")

    def finish(self, args: argparse.Namespace) -> None:
        """Wait for the last episodes, refit exactly, write OUT/model/ (model.json, report.json, report.md)."""
        sink = self.sink
        if sink is None:
            return
        scores = sink.finish()
        for error in sink.errors:
            print(f"qube-run: warning: --identify: {error}", file=sys.stderr)
        ident = sink.identifier
        if not ident.n_episodes_:
            print("qube-run: --identify: no complete episode: no model written", file=sys.stderr)
            return
        ident.refit_exact(skip=self.fit.skip)
        folder = output_dir(Path(args.out) / MODEL_FOLDER)
        report = _report(self.fit, ident, scores, args, sink.stop_reason)
        write_model(folder, self.fit, ident)
        write_json(folder / "report.json", report)
        _write_markdown(folder / "report.md", report)
        r2 = [s.score.r2 for s in scores if s.score is not None]
        mean = f", held-out R^2 median {statistics.median(r2):.4f} over {len(r2)}" if r2 else ""
        print(
            f"identify: model of {ident.n_episodes_} episodes{mean}; wrote {folder}/model.json, report.json, report.md"
        )


def send_view(recording, live) -> None:
    """One scored episode in the rerun view: its measured and predicted angles (entity
    ``identify/episodes/<n>/<angle>``, timeline ``episode_time``) and its score on the curve ``identify/r2``
    (timeline ``identify_episode``: the complete episodes' count)."""
    import numpy as np

    from qube_koopman.core.qube import MEASURED, STATE_NAMES

    if live.prediction is None or live.measured is None:
        return
    n = len(live.measured)
    t = (live.first_sample + np.arange(n)) * (live.dt or 0.002)
    for j, channel in enumerate(MEASURED):
        path = f"{VIEW}/episodes/{live.index}/{STATE_NAMES[channel]}"
        recording.log(path, "SeriesLines", static=True, names=["measured", "predicted"])
        block = np.column_stack([live.measured[:, j], live.prediction[:, j]])
        recording.send_scalars(path, [("episode_time", "duration", t)], block)
    r2 = np.array([[live.score.r2 if np.isfinite(live.score.r2) else np.nan]])
    recording.send_scalars(f"{VIEW}/r2", [("identify_episode", "sequence", np.array([live.index]))], r2)


def write_model(folder: Path, fit, ident) -> None:
    """model.json as qube-identify writes it (without the intervals' bootstrap, as its --interval 0)."""
    from qube_koopman.core.qube import MEASURED
    from qube_koopman.identify.models.model_file import save_model

    save_model(
        folder / "model.json",
        method=fit.method,
        alpha=float(fit.alpha),
        plant=ident.plant_model_,
        closed_loop=ident.model_,
        controller=ident.controller_,
        measured=MEASURED,
        training={"logs": [p.name for p in ident.logs_]},
    )


def _report(fit, ident, scores, args, stop_reason) -> dict:
    from qube_koopman.identify.metrics import summarize_scores
    from qube_koopman.identify.models.model_file import lifting_to_dict

    scored = [s for s in scores if s.score is not None]
    return {
        "method": fit.method,
        "alpha": float(fit.alpha),
        "train_logs": [p.name for p in ident.logs_],
        "controller": ident.controller_.as_dict(),
        "lifting": lifting_to_dict(ident.plant_model_.lifting),
        "spectral_radius": {
            "closed_loop": ident.model_.spectral_radius(),
            "plant": ident.plant_model_.spectral_radius(),
        },
        "live": {
            "flags": args.identify or LIVE_DEFAULT_FLAGS,
            "protocol": PROTOCOL,
            "until": args.until,
            "plateau": bool(args.plateau),
            "stopped": stop_reason,
            "episodes": [s.as_dict() for s in scores],
            "held_out": summarize_scores([s.score for s in scored], [s.log.name for s in scored]) if scored else None,
        },
    }


def _write_markdown(path: Path, report: dict) -> None:
    from qube_koopman.core.files import atomic_path

    live = report["live"]
    lines = [
        "# Identification while recording",
        "",
        f"- method {report['method']}, alpha {report['alpha']:g}, flags `{live['flags']}`",
        f"- {len(report['train_logs'])} episodes in the model; {live['protocol']}",
        f"- stopped: {live['stopped'] or 'no (every planned episode ran)'}",
        "",
        "| episode | log | model of | held-out R^2 | NRMSE % | CPU s |",
        "|---:|---|---:|---:|---:|---:|",
    ]
    for i, e in enumerate(live["episodes"]):
        r2 = "-" if e["r2"] is None else f"{e['r2']:.4f}"
        nrmse = "-" if e["nrmse"] is None else f"{e['nrmse']:.2f}"
        lines.append(f"| {i} | {e['log']} | {e['n_training_episodes']} | {r2} | {nrmse} | {e['cpu_seconds']:.3f} |")
    with atomic_path(path) as tmp:
        tmp.write_text("\n".join(lines) + "\n")
