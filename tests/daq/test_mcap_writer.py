"""The block MCAP writer writes mcap's own Writer's file, byte for byte; the episode logs with it too."""

from __future__ import annotations

import io

import numpy as np
import pytest

from _episodes import make_episode
from qube_koopman.daq.episode import Episode
from qube_koopman.daq.log import EpisodeWriter, read_episode
from qube_koopman.daq.log.mcap_writer import CHUNK_SIZE, BlockWriter

COMPRESSIONS = ("zstd", "lz4", "none")


def _script(rng: np.random.Generator):
    """A writing session: schemas, channels, metadata, blocks of messages (two sizes, two channels) and
    flushes in between, some blocks taking a chunk past its size more than once."""
    steps = [
        ("schema", "a", "ros2msg", b"float64 x\n"),
        ("schema", "b", "jsonschema", b"{}"),
        ("channel", "/a", "cdr", 1, {}),
        ("channel", "/b", "json", 2, {"k": "v"}),
        ("metadata", "first", {"x": "1"}),
    ]
    sequence, time = 0, 1_700_000_000_000_000_000
    for size, n, channel in [(40, 250, 1), (40, 250, 1), (900, 2600, 2), (40, 3, 1), (120, 9000, 1), (40, 1, 2)]:
        times = time + np.cumsum(rng.integers(0, 3_000_000, n))  # repeated times too
        if n == 3:
            times = times[::-1]  # out of order: a chunk's and the file's times are the extremes, not the ends
        steps.append(("messages", channel, sequence, times, rng.integers(0, 256, (n, size), dtype=np.uint8)))
        sequence, time = sequence + n, int(times[-1])
        if rng.random() < 0.7 or n == 3:
            steps.append(("flush",))
    # Last, a message older than all the others: the file's first and last times are the extremes.
    steps.append(("messages", 2, sequence, np.array([1_000]), rng.integers(0, 256, (1, 40), dtype=np.uint8)))
    steps += [("flush",), ("flush",), ("metadata", "status", {"status": "complete"})]
    return steps


def _with_mcap(stream, steps, compression: str) -> None:
    from mcap.writer import CompressionType, Writer

    writer = Writer(
        stream,
        compression={"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4, "none": CompressionType.NONE}[
            compression
        ],
    )
    _play(
        writer,
        steps,
        per_message=lambda channel, seq, times, payloads: [
            writer.add_message(channel, int(t), p.tobytes(), int(t), seq + i)
            for i, (t, p) in enumerate(zip(times, payloads))
        ],
    )


def _with_blocks(stream, steps, compression: str) -> None:
    writer = BlockWriter(stream, compression)
    _play(writer, steps, per_message=writer.add_messages)


def _play(writer, steps, per_message) -> None:
    writer.start(profile="", library="test 1")
    for step in steps:
        if step[0] == "schema":
            writer.register_schema(*step[1:])
        elif step[0] == "channel":
            writer.register_channel(*step[1:])
        elif step[0] == "metadata":
            writer.add_metadata(*step[1:])
        elif step[0] == "messages":
            per_message(*step[1:])
        else:
            writer.flush()
    writer.finish()


@pytest.mark.parametrize("compression", COMPRESSIONS)
def test_the_block_writer_writes_mcaps_file_byte_for_byte(compression):
    steps = _script(np.random.default_rng(3))
    assert sum(s[4].nbytes for s in steps if s[0] == "messages") > 2 * CHUNK_SIZE  # chunks closed by size too
    theirs, ours = io.BytesIO(), io.BytesIO()
    _with_mcap(theirs, steps, compression)
    _with_blocks(ours, steps, compression)
    assert len(ours.getvalue()) == len(theirs.getvalue())
    assert ours.getvalue() == theirs.getvalue()


def test_a_file_without_messages_is_mcaps_too():
    steps = [("schema", "a", "ros2msg", b""), ("channel", "/a", "cdr", 1, {}), ("metadata", "m", {}), ("flush",)]
    theirs, ours = io.BytesIO(), io.BytesIO()
    _with_mcap(theirs, steps, "zstd")
    _with_blocks(ours, steps, "zstd")
    assert ours.getvalue() == theirs.getvalue()


def _reference_log(path, episode, flush_every: int | None) -> None:
    """The episode log as mcap's Writer wrote it, a message per sample (the writer before the blocks)."""
    import struct

    from mcap.writer import Writer

    from qube_koopman.daq.log.metadata import STATUS_RECORD, episode_records, status_record
    from qube_koopman.daq.log.schema import (
        CDR_LE_HEADER,
        FORMAT_VERSION,
        SAMPLE_SCHEMA_NAME,
        SAMPLE_TOPIC,
        sample_fields,
        schema_text,
    )
    from qube_koopman.daq.log.writer import _epoch_ns

    n_states = episode.controller_state.shape[1]
    packer = struct.Struct("<4s" + "d" * (len(sample_fields(n_states)) - 1) + "b")
    epoch = _epoch_ns(episode.metadata.start_time)
    with open(path, "wb") as f:
        writer = Writer(f)
        writer.start(profile="", library=f"qube-koopman daq.log {FORMAT_VERSION}")
        schema = writer.register_schema(SAMPLE_SCHEMA_NAME, "ros2msg", schema_text(n_states).encode())
        channel = writer.register_channel(SAMPLE_TOPIC, "cdr", schema)
        for name, record in episode_records(episode.metadata).items():
            writer.add_metadata(name, record)
        writer.flush()
        a = episode.arrays()
        signals = (
            "t",
            "theta",
            "alpha",
            "target_theta",
            "target_alpha",
            "feedforward",
            "control_output",
            "plant_input",
            "lateness",
            "compute_time",
            "device_time",
        )
        for k in range(len(episode)):
            payload = packer.pack(
                CDR_LE_HEADER, *[float(a[n][k]) for n in signals], *a["controller_state"][k], int(a["saturation"][k])
            )
            time = epoch + round(float(a["t"][k]) * 1e9)
            writer.add_message(channel, time, payload, time, k)
            if flush_every and (k + 1) % flush_every == 0:
                writer.flush()
        writer.flush()
        writer.add_metadata(STATUS_RECORD, status_record("complete", "", len(episode), None, None))
        writer.finish()


def _part(episode: Episode, start: int, stop: int) -> Episode:
    return Episode(metadata=episode.metadata, **{name: value[start:stop] for name, value in episode.arrays().items()})


@pytest.mark.parametrize("flush_interval_s", [0.5, None])
def test_episode_logs_are_the_ones_mcaps_writer_wrote_sample_by_sample_and_whole(tmp_path, flush_interval_s):
    # None: chunks close at 1 MiB only (8000 samples of 160 bytes take a chunk past it).
    episode = make_episode(8000 if flush_interval_s is None else 1130)
    reference = tmp_path / "reference.mcap"
    _reference_log(reference, episode, None if flush_interval_s is None else 250)
    whole, by_sample = tmp_path / "whole.mcap", tmp_path / "by_sample.mcap"
    with EpisodeWriter(whole, episode.metadata, flush_interval_s=flush_interval_s) as log:
        for start, stop in [(0, 300), (300, 301), (301, len(episode))]:  # blocks across the chunks' ends
            log.write_samples(_part(episode, start, stop))
    with EpisodeWriter(by_sample, episode.metadata, flush_interval_s=flush_interval_s) as log:
        arrays = episode.arrays()
        for k in range(len(episode)):
            log.write_sample(**{name: value[k] for name, value in arrays.items()})
    assert whole.read_bytes() == reference.read_bytes()
    assert by_sample.read_bytes() == reference.read_bytes()
    read = read_episode(whole)
    np.testing.assert_array_equal(read.controller_state, episode.controller_state)
    np.testing.assert_array_equal(read.t, episode.t)
