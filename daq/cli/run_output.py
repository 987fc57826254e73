"""What ``qube-run`` shows of a run: the progress bar, the episodes' log files, the closing summary.

The same whether the episodes ran in this process or in worker processes (``--n-jobs``): each
episode is entered here in episode order, with its log file and any error writing it.
"""

from __future__ import annotations

import dataclasses
import math
import sys
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from qube_koopman.daq.sinks import EpisodeOutcome

__all__ = ["PROG", "RunProgress", "EpisodeBook", "summary_table", "link_summary", "report"]

PROG = "qube-run"


class RunProgress:
    """A tqdm bar on stderr counting samples over the whole run, silent when stderr is not a terminal.

    A sink on the writer thread (``write`` per sample) for episodes run in this process;
    ``episode_done`` from the main thread for every episode (those of worker processes count
    whole when they come back).

    Parameters
    ----------
    n_episodes : int
    samples_per_episode : int
    enabled : bool
        False for ``-q``: no bar.
    """

    required = False

    def __init__(self, n_episodes: int, samples_per_episode: int, enabled: bool) -> None:
        from qube_koopman.core.console import progress_bar

        self.n = n_episodes
        self.per = samples_per_episode
        self.aborted = 0
        self.bar = progress_bar(n_episodes * samples_per_episode, unit="sample", unit_scale=True, enabled=enabled)
        self._postfix(0)

    def _postfix(self, episode: int) -> None:
        text = f"episode {min(episode + 1, self.n)}/{self.n}"
        self.bar.set_postfix_str(text + (f", {self.aborted} aborted" if self.aborted else ""), refresh=False)

    def open(self, metadata) -> None:
        """An episode starts (nothing to show)."""

    def write(self, sample) -> None:
        """One sample through."""
        self.bar.update(1)

    def close(self, outcome) -> None:
        """An episode ends (shown by :meth:`episode_done`)."""

    def episode_done(self, index: int, result, name: str) -> None:
        """Episode ``index`` is through, its log ``name``: a line above the bar when it was aborted."""
        self.aborted += not result.complete
        self.bar.update((index + 1) * self.per - self.bar.n)  # an aborted episode counts as through
        self._postfix(index + 1)
        if not result.complete and not self.bar.disable:  # the summary table has it too
            status = result.status + (f" ({result.reason})" if result.reason else "")
            self.bar.write(f"{PROG}: episode {index + 1}/{self.n} {name}: {status}", file=sys.stderr)

    def clear(self) -> None:
        """Remove the bar."""
        self.bar.close()


class EpisodeBook:
    """The run's episodes in order: their log file names and the errors writing them.

    Parameters
    ----------
    progress : RunProgress
        Told of each episode as it is entered.
    mcap : McapSink
        The sink of the episodes run in this process (:meth:`serial`).
    """

    def __init__(self, progress: RunProgress, mcap) -> None:
        self.progress = progress
        self.mcap = mcap
        self.names: list[str] = []
        self.log_errors: list = []

    def serial(self, plan, result) -> None:
        """``on_result`` of :func:`daq.session.run_episodes`: an episode of this process, logged by ``mcap``."""
        mcap = self.mcap
        self._enter(plan.index, result, mcap.paths[-1] if result.started and mcap.paths else None, mcap.error)

    def parallel(self, plan, logged) -> None:
        """``on_result`` of :func:`daq.parallel.run_episodes_parallel`: an episode of a worker process."""
        self._enter(plan.index, logged.result, logged.path, logged.log_error)

    def _enter(self, index: int, result, path: Path | None, log_error) -> None:
        name = path.name if path is not None else "(not started)"
        self.names.append(name)
        if log_error is not None and log_error not in self.log_errors:
            self.log_errors.append(log_error)
        self.progress.episode_done(index, result, name)


def _us(value: float | None) -> str:
    return "-" if value is None or not math.isfinite(value) else f"{value * 1e6:.1f}"


def summary_table(rows: list[tuple[str, EpisodeOutcome]], totals) -> str:
    """The end-of-run table: one row per episode, then the whole run's timing."""
    header = ("#", "log file", "status", "samples", "late p50 us", "p99 us", "max us", "overruns", "compute p99 us")
    lines = []
    table = [header]
    for i, (name, r) in enumerate(rows):
        t = r.timing
        table.append(
            (
                str(i),
                name,
                r.status,
                str(r.n_samples),
                _us(t.lateness_p50),
                _us(t.lateness_p99),
                _us(t.lateness_max),
                str(t.overruns) if t.paced else "-",
                _us(t.compute_p99),
            )
        )
    widths = [max(len(row[j]) for row in table) for j in range(len(header))]
    for j, row in enumerate(table):
        lines.append("  ".join(c.ljust(w) if k < 3 else c.rjust(w) for k, (c, w) in enumerate(zip(row, widths))))
        if j == 0:
            lines.append("  ".join("-" * w for w in widths))
    for i, (_, r) in enumerate(rows):
        if r.reason:
            lines.append(f"episode {i}: {r.reason}")
    t = totals
    line = f"all {t.n_ticks} ticks: "
    if t.paced:
        line += (
            f"lateness p50 {_us(t.lateness_p50)} us, p99 {_us(t.lateness_p99)} us, max "
            f"{_us(t.lateness_max)} us; {t.overruns} overruns, {t.stalls} stalls > 2 ms; "
        )
    else:
        line += "free-running (no deadlines); "
    line += f"compute p50 {_us(t.compute_p50)} us, p99 {_us(t.compute_p99)} us, max {_us(t.compute_max)} us"
    lines.append(line)
    return "\n".join(lines)


def link_summary(results) -> str | None:
    """One line of the serial link's counters over the run, or None for a backend without them."""
    stats = [r.backend_stats for r in results if r.backend_stats and "telemetry" in r.backend_stats]
    if not stats:
        return None
    total = {
        k: sum(s.get(k, 0) for s in stats)
        for k in ("telemetry", "ticks_missed", "ticks_skipped", "frames_lost", "late_commands", "host_rejects")
    }
    return (
        f"serial link: {total['telemetry']} telemetry frames, {total['ticks_missed']} ticks missed, "
        f"{total['ticks_skipped']} skipped, {total['frames_lost']} frames lost, {total['host_rejects']} "
        f"rejected, {total['late_commands']} commands late"
    )


def _as_logged(rows: list[tuple[str, EpisodeOutcome]], log_errors: list) -> list[tuple[str, EpisodeOutcome]]:
    """The summary's rows, an episode whose log failed counted by the samples its file still holds.

    After a write error the loop has run more ticks than the file keeps (it is readable up to its
    last flush); the summary gives what can be read, and both counts in the episode's reason line.
    """
    from qube_koopman.daq.log import read_episode

    for error in log_errors:
        if not error.path.exists():
            continue
        try:
            readable = len(read_episode(error.path, warn=False))
        except (OSError, ValueError):  # not even the start readable
            readable = 0
        rows = [
            (
                name,
                dataclasses.replace(
                    r,
                    n_samples=readable,
                    reason=f"{r.reason}; the log holds the first "
                    f"{readable} of the {r.n_samples} samples run, marked incomplete",
                ),
            )
            if name == error.path.name
            else (name, r)
            for name, r in rows
        ]
    return rows


def report(args, run, book: EpisodeBook, totals, n_planned: int, recording_problem: str | None = None) -> int:
    """Print the summary and the closing lines of a run; its exit status (see ``qube-run --help``).

    ``recording_problem``: why the rerun recording or view failed (an error line, exit status 1).
    """
    results = run.results
    print(summary_table(_as_logged(list(zip(book.names, results)), book.log_errors), totals))
    link = link_summary(results)
    if link:
        print(link)
    for r in results:
        for error in r.sink_errors:
            if not (book.log_errors and error.startswith("McapSink.")):
                print(f"{PROG}: warning: {error}", file=sys.stderr)
    logs = sum(1 for name in book.names if (args.out / name).is_file())  # what is there to read, not what ran
    print(
        f"{run.n_complete} complete, {run.n_aborted} aborted; {logs} episode "
        f"log{'s' if logs != 1 else ''} in {args.out.resolve()}"
        + (f"; rerun recording in {args.rerun_save.resolve()}" if args.rerun_save and not recording_problem else "")
    )
    if run.stopped and not book.log_errors:
        print(f"{PROG}: run stopped: {run.stopped}", file=sys.stderr)
    for error in book.log_errors:
        print(
            f"{PROG}: error: {error}: "
            + (
                "the episode was not started"
                if not error.path.exists()
                else "the episode was stopped with the motor at 0 V; the samples flushed before stay "
                "readable, marked incomplete"
            ),
            file=sys.stderr,
        )
    if recording_problem:
        print(f"{PROG}: error: {recording_problem}", file=sys.stderr)
    if run.signal is not None:
        return 128 + int(run.signal)
    if recording_problem:
        return 1
    # A safety stop, or a swing-up the supervisor gave up, is a recorded outcome of an episode, not an
    # error of the run.
    errors = [r for r in results if r.status == "aborted" and r.cause not in ("safety", "swing-up")]
    return 0 if not errors and len(results) == n_planned else 1
