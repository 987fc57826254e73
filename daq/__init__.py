"""The host side of an experiment on the QUBE-Servo: acquisition, logs and their formats.

``daq`` owns what runs and records an episode: backends (``daq.backends``:
the simulated pendulum and the serial bridge; controllers and their files
are ``core``'s), the rig's excitation (``daq.excitation``), the
500 Hz loop with its safety supervisor and timing statistics (``daq.loop``,
``daq.safety``, ``daq.timing``), the swing-up before an episode (``daq.swing_up``), the episode and its metadata
(``daq.episode``, with ``stack_signals``), the MCAP episode log (``daq.log``, format in
``daq/log/FORMAT.md``; file names in ``daq.log.names``), legacy CSV import (``daq.legacy_csv``), export to
CSV, Parquet and MATLAB (``daq.export``) and the live rerun view
(``daq.viz``). Start with :func:`~qube_koopman.daq.session.run_episodes` (what ``qube-run``
calls) to acquire, and :func:`~qube_koopman.daq.log.reader.read_episode` to read a log back.
Imports only ``firmware_protocol``, ``sim`` and ``core`` from this project.

Import what is listed here from ``qube_koopman.daq``: each name is imported from its module when
first used, so ``import qube_koopman.daq`` loads none of them (the loop's modules do not pay
for mcap, scipy or the exporters).
"""

from qube_koopman.core.exports import lazy_exports

# Each public name and the module (relative to this package) that defines it.
_HOMES = {
    # episodes and their logs
    "Episode": "episode",
    "EpisodeMetadata": "episode",
    "stack_signals": "episode",
    "read_episode": "log",
    "read_episode_metadata": "log",
    "write_episode": "log",
    "EpisodeWriter": "log",
    "IncompleteEpisodeWarning": "log",
    "log_path": "log.names",
    "find_logs": "log.names",
    "parse_episode_name": "log.names",
    # other formats: the legacy CSV in, CSV, Parquet and MATLAB out
    "legacy_episode": "legacy_csv",
    "load_legacy_controller": "legacy_csv",
    "read_legacy_csv": "legacy_csv",
    "export_episode": "export",
    # sessions: what qube-run runs (controllers and their files are core's)
    "run_seeds": "session",
    "excitation_settings": "session",
    "plan_episodes": "session",
    "run_episodes": "session",
    "RunResult": "session",
    # one episode: the loop, its safety limits, the excitation, backends and sinks
    "run_episode": "loop",
    "EpisodePlan": "loop",
    "EpisodeResult": "loop",
    "SafetyLimits": "safety",
    # the swing-up before an episode: its settings, energy controller and the supervisor's limits
    "SwingUp": "swing_up",
    "EnergyController": "swing_up",
    "SwingUpLimits": "safety",
    "ExcitationSettings": "excitation",
    "generate_excitation": "excitation",
    "Backend": "backends",
    "SimBackend": "backends",
    "SerialBackend": "backends",
    "Sink": "sinks",
    "McapSink": "sinks",
    "MemorySink": "sinks",
}

__all__ = list(_HOMES)

__getattr__, __dir__ = lazy_exports(__name__, _HOMES)
