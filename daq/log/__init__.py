"""The episode log: one MCAP file per episode (format described in FORMAT.md).

Write with :class:`EpisodeWriter` (sample by sample, from a writer thread)
or :func:`write_episode` (a whole episode); read with :func:`read_episode`
(arrays plus metadata, salvaging files cut short) or
:func:`read_episode_metadata` (metadata only).
"""

from qube_koopman.daq.log.reader import IncompleteEpisodeWarning, read_episode, read_episode_metadata
from qube_koopman.daq.log.schema import FORMAT_VERSION, SAMPLE_TOPIC
from qube_koopman.daq.log.writer import EpisodeWriter, write_episode

__all__ = [
    "FORMAT_VERSION",
    "SAMPLE_TOPIC",
    "EpisodeWriter",
    "write_episode",
    "read_episode",
    "read_episode_metadata",
    "IncompleteEpisodeWarning",
]
