"""Episode log (daq.log): round trips, salvage of files cut short, refused files."""

from __future__ import annotations

import os
import pickle
import signal
import struct
import subprocess
import sys
import time
import warnings
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from _episodes import QUBE_PD, RATE, make_episode, make_metadata, sample
from qube_koopman.daq.episode import SIGNALS, Episode
from qube_koopman.daq.log import (
    EpisodeWriter,
    IncompleteEpisodeWarning,
    read_episode,
    read_episode_metadata,
    write_episode,
)
from qube_koopman.daq.log.schema import FORMAT_VERSION, parse_schema

REPO = Path(__file__).resolve().parents[2]


def assert_prefix(read: Episode, full: Episode, n: int) -> None:
    assert len(read) == n
    for name, value in full.arrays().items():
        np.testing.assert_array_equal(getattr(read, name), value[:n], err_msg=name)


def read_quietly(path) -> Episode:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", IncompleteEpisodeWarning)
        return read_episode(path)


# --- round trips -----------------------------------------------------------


def test_whole_episode_round_trip_is_exact(tmp_path):
    episode = make_episode(2000)
    path = write_episode(tmp_path / "e.mcap", episode)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # an intact file must not warn
        read = read_episode(path)
    assert_prefix(read, episode, 2000)
    assert read.saturation.dtype == np.int8
    meta = read.metadata
    assert meta.status == "complete" and not meta.salvaged and read.is_complete
    assert meta.log_format_version == FORMAT_VERSION
    assert (meta.backend, meta.source, meta.start_time) == ("sim", "unit test", "2026-11-21T12:00:00+00:00")
    assert meta.excitation == episode.metadata.excitation
    assert meta.controller.gains == episode.metadata.controller.gains
    assert meta.controller.method == "backward-euler"
    for m in "ABCD":  # bit-exact, through JSON
        np.testing.assert_array_equal(getattr(read.controller, m), getattr(QUBE_PD, m))
    assert read.controller.dt == QUBE_PD.dt


def test_incremental_writer_round_trip_and_status(tmp_path):
    episode = make_episode(730)
    path = tmp_path / "live.mcap"
    with EpisodeWriter(path, episode.metadata, flush_interval_s=0.5) as log:
        for k in range(len(episode)):
            log.write_sample(**{name: value[k] for name, value in episode.arrays().items()})
        assert log.n_samples == 730
        log.finish("aborted", "safety stop: |alpha| > pi/4")
    read = read_episode(path)
    assert_prefix(read, episode, 730)
    assert read.metadata.status == "aborted"
    assert read.metadata.status_reason == "safety stop: |alpha| > pi/4"
    assert not read.is_complete
    with pytest.raises(RuntimeError, match="already finished"):
        log.write_sample(**{name: value[0] for name, value in episode.arrays().items()})


def test_writer_flushes_one_chunk_per_half_second(tmp_path):
    from mcap.reader import make_reader

    episode = make_episode(1200)
    path = tmp_path / "e.mcap"
    with EpisodeWriter(path, episode.metadata, flush_interval_s=0.5) as log:
        log.write_samples(episode)
    with open(path, "rb") as f:
        chunks = make_reader(f).get_summary().chunk_indexes
    # 250 samples per 0.5 s at 500 Hz: 4 full chunks and the rest.
    assert len(chunks) == 5
    assert (chunks[1].message_start_time - chunks[0].message_start_time) == 250 * 2_000_000


def test_context_manager_records_the_exception_as_abort_reason(tmp_path):
    episode = make_episode(10)
    path = tmp_path / "e.mcap"
    with pytest.raises(KeyError):
        with EpisodeWriter(path, episode.metadata) as log:
            log.write_samples(episode)
            raise KeyError("backend lost")
    read = read_episode(path)
    assert read.metadata.status == "aborted"
    assert "KeyError" in read.metadata.status_reason and "backend lost" in read.metadata.status_reason
    assert len(read) == 10


def test_zero_sample_episode_round_trip(tmp_path):
    episode = make_episode(0)
    read = read_episode(write_episode(tmp_path / "e.mcap", episode))
    assert len(read) == 0 and read.controller_state.shape == (0, 2) and read.is_complete


@pytest.mark.parametrize("compression", ["lz4", "none"])
def test_other_compressions_round_trip(tmp_path, compression):
    episode = make_episode(600)
    read = read_episode(write_episode(tmp_path / "e.mcap", episode, compression=compression))
    assert_prefix(read, episode, 600)


@settings(max_examples=30, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(data=hnp.arrays(np.float64, (5, 12), elements=st.floats(allow_nan=True, allow_infinity=True)))
def test_any_float_values_round_trip_bit_exact(tmp_path, data):
    # Signed zeros, infinities and NaN payloads included: the log stores bits, not decimals.
    names = [n for n in SIGNALS if n != "t"]
    episode = Episode(
        t=np.arange(5) / RATE,
        controller_state=data[:, 10:12],
        saturation=np.zeros(5),
        metadata=make_metadata(),
        **dict(zip(names, data.T)),
    )
    path = tmp_path / "h.mcap"
    read = read_episode(write_episode(path, episode, overwrite=True))
    for name in names:
        assert getattr(read, name).tobytes() == getattr(episode, name).tobytes(), name
    assert read.controller_state.tobytes() == episode.controller_state.tobytes()


def test_episode_pickles(tmp_path):
    read = read_episode(write_episode(tmp_path / "e.mcap", make_episode(20)))
    again = pickle.loads(pickle.dumps(read))
    np.testing.assert_array_equal(again.alpha, read.alpha)
    assert again.metadata.excitation == read.metadata.excitation


def test_episode_arrays_are_read_only_copies():
    theta = np.zeros(3)
    episode = Episode(
        t=np.arange(3) / RATE,
        theta=theta,
        alpha=np.zeros(3),
        target_theta=np.zeros(3),
        target_alpha=np.zeros(3),
        feedforward=np.zeros(3),
        controller_state=np.zeros((3, 2)),
        control_output=np.zeros(3),
        plant_input=np.zeros(3),
        saturation=np.zeros(3),
        metadata=make_metadata(),
    )
    theta[0] = 1.0
    assert episode.theta[0] == 0.0 and theta.flags.writeable
    with pytest.raises(ValueError):
        episode.theta[0] = 2.0
    assert np.isnan(episode.lateness).all() and np.isnan(episode.compute_time).all()


@pytest.mark.parametrize(
    "change, message",
    [
        (dict(alpha=np.zeros(4)), "alpha must have shape"),
        (dict(controller_state=np.zeros((5, 3))), "controller_state must have shape"),
        (dict(saturation=np.full(5, 2)), "saturation must hold only"),
    ],
)
def test_episode_rejects_inconsistent_arrays(change, message):
    arrays = dict(
        t=np.arange(5) / RATE,
        theta=np.zeros(5),
        alpha=np.zeros(5),
        target_theta=np.zeros(5),
        target_alpha=np.zeros(5),
        feedforward=np.zeros(5),
        controller_state=np.zeros((5, 2)),
        control_output=np.zeros(5),
        plant_input=np.zeros(5),
        saturation=np.zeros(5),
    )
    arrays.update(change)
    with pytest.raises(ValueError, match=message):
        Episode(metadata=make_metadata(), **arrays)


def test_metadata_rejects_a_controller_at_another_rate():
    with pytest.raises(ValueError, match="does not match the sample rate"):
        make_metadata(sample_rate_hz=1000.0)


def test_existing_file_is_never_overwritten_silently(tmp_path):
    path = tmp_path / "e.mcap"
    path.write_bytes(b"precious")
    with pytest.raises(FileExistsError):
        write_episode(path, make_episode(5))
    with pytest.raises(FileExistsError):
        EpisodeWriter(path, make_metadata())
    assert path.read_bytes() == b"precious"
    assert list(tmp_path.iterdir()) == [path]  # no temporary left behind
    write_episode(path, make_episode(5), overwrite=True)
    assert len(read_episode(path)) == 5


# --- Foxglove compatibility: the mcap library and a CDR decoder agree ------


def _decode_cdr(schema: str, payload: bytes) -> dict:
    """A deliberately naive classic-CDR decoder driven by the ros2msg text."""
    formats = {"float64": "<d", "int8": "<b"}
    assert payload[:4] == b"\x00\x01\x00\x00"
    body, pos, out = payload[4:], 0, {}
    for ros_type, name in (line.split("#")[0].split() for line in schema.splitlines() if line.split("#")[0].strip()):
        size = struct.calcsize(formats[ros_type])
        pos += -pos % size
        (out[name],) = struct.unpack_from(formats[ros_type], body, pos)
        pos += size
    assert pos == len(body)
    return out


def test_mcap_library_reads_one_scalar_message_per_sample(tmp_path):
    from mcap.reader import make_reader

    episode = make_episode(600)
    path = tmp_path / "e.mcap"
    with EpisodeWriter(path, episode.metadata) as log:
        log.write_samples(episode)
    with open(path, "rb") as f:
        reader = make_reader(f)
        messages = list(reader.iter_messages(topics=["/qube/sample"]))
        metadata = {m.name: m.metadata for m in reader.iter_metadata()}
    assert len(messages) == 600
    schema, channel, _ = messages[0]
    assert (schema.encoding, channel.message_encoding) == ("ros2msg", "cdr")
    assert all(t in ("float64", "int8") for _, t in parse_schema(schema.data.decode()))
    start_ns = 1_795_262_400 * 10**9  # 2026-11-21T12:00:00Z (date -u -d ... +%s)
    for k in (0, 1, 299, 599):
        _, _, message = messages[k]
        assert message.sequence == k and message.log_time == start_ns + k * 2_000_000
        fields = _decode_cdr(schema.data.decode(), message.data)
        for name in ("t", "theta", "alpha", "control_output", "plant_input", "feedforward"):
            assert fields[name] == getattr(episode, name)[k]
        assert fields["controller_state_1"] == episode.controller_state[k, 1]
        assert fields["saturation"] == episode.saturation[k]
    assert metadata["qube.status"] == {"status": "complete", "reason": "", "n_samples": "600"}
    assert metadata["qube.episode"]["format_version"] == FORMAT_VERSION


# --- salvage -----------------------------------------------------------------


def _chunks(path) -> list[tuple[int, int]]:
    """(start, end) byte offsets of every chunk, from the mcap library's own index."""
    from mcap.reader import make_reader

    with open(path, "rb") as f:
        return [
            (c.chunk_start_offset, c.chunk_start_offset + c.chunk_length)
            for c in make_reader(f).get_summary().chunk_indexes
        ]


def test_truncated_file_reads_the_prefix_of_whole_chunks(tmp_path):
    episode = make_episode(1000)
    path = tmp_path / "full.mcap"
    with EpisodeWriter(path, episode.metadata, flush_interval_s=0.1) as log:  # 50 samples a chunk
        log.write_samples(episode)
    data = path.read_bytes()
    chunks = _chunks(path)
    assert len(chunks) == 20
    starts, ends = zip(*chunks)
    offsets = [
        starts[0],
        starts[0] + 10,
        ends[0] - 1,
        ends[0],
        ends[0] + 1,
        ends[7] + 5,
        (starts[13] + ends[13]) // 2,
        ends[19] - 1,
        ends[19] + 5,
    ]
    cut = tmp_path / "cut.mcap"
    for offset in offsets:
        cut.write_bytes(data[:offset])
        with pytest.warns(IncompleteEpisodeWarning, match="cut.mcap"):
            read = read_episode(cut)
        whole = sum(end <= offset for end in ends)
        assert_prefix(read, episode, 50 * whole)
        assert read.metadata.salvaged and read.metadata.status == "incomplete"
        assert "no final status" in read.metadata.status_reason
        assert read.metadata.salvage_note and not read.is_complete
        np.testing.assert_array_equal(read.controller.C, QUBE_PD.C)  # metadata survives


def test_file_cut_in_its_summary_keeps_status_and_all_samples(tmp_path):
    episode = make_episode(300)
    path = write_episode(tmp_path / "e.mcap", episode)
    data = path.read_bytes()
    path.write_bytes(data[:-30])  # footer and magic lost
    with pytest.warns(IncompleteEpisodeWarning):
        read = read_episode(path)
    assert_prefix(read, episode, 300)
    assert read.metadata.status == "complete" and read.metadata.salvaged


def _five_chunks(tmp_path):
    episode = make_episode(500)
    path = tmp_path / "e.mcap"
    with EpisodeWriter(path, episode.metadata, flush_interval_s=0.2) as log:  # 100 samples a chunk
        log.write_samples(episode)
    return episode, path, _chunks(path)


def test_damaged_chunk_is_skipped_and_every_chunk_after_it_read(tmp_path):
    episode, path, chunks = _five_chunks(tmp_path)
    intact = read_episode(path).metadata
    data = bytearray(path.read_bytes())
    data[chunks[2][1] - 50] ^= 0xFF  # inside the compressed data of the third chunk
    path.write_bytes(bytes(data))
    with pytest.warns(IncompleteEpisodeWarning, match="unusable") as caught:
        read = read_episode(path)
    kept = np.r_[0:200, 300:500]
    assert len(read) == 400
    for name, value in episode.arrays().items():
        np.testing.assert_array_equal(getattr(read, name), value[kept], err_msg=name)
    meta = read.metadata
    assert meta.salvaged and not read.is_complete and meta.status == "incomplete"
    gap = meta.salvage_note
    assert gap.startswith(f"Chunk record at byte {chunks[2][0]} is unusable: ") and "; " not in gap.split(": ", 1)[0]
    assert gap.endswith("; skipped: samples 200 to 299 lost, 200 read after it") and gap in str(caught[0].message)
    assert meta.status_reason == f"corrupted: {gap}; the log's final status: complete"
    assert meta.timing == intact.timing and meta.backend_stats == intact.backend_stats  # the status record kept


def test_damaged_last_chunk_of_a_finished_log_names_the_samples_lost(tmp_path):
    episode, path, chunks = _five_chunks(tmp_path)
    data = bytearray(path.read_bytes())
    data[chunks[4][1] - 50] ^= 0xFF
    path.write_bytes(bytes(data))
    read = read_quietly(path)
    assert_prefix(read, episode, 400)
    assert "skipped: samples 400 to 499 lost, 0 read after it" in read.metadata.salvage_note


def test_damaged_chunk_length_costs_that_chunk_and_reading_resumes_at_the_next_sound_one(tmp_path):
    # The record's length field itself damaged: where the next record starts is unknown, so the
    # reader looks for the next chunk whose framing and CRC check out.
    episode, path, chunks = _five_chunks(tmp_path)
    data = bytearray(path.read_bytes())
    data[chunks[2][0] + 1] ^= 0x07  # low byte of the Chunk record's length
    path.write_bytes(bytes(data))
    read = read_quietly(path)
    kept = np.r_[0:200, 300:500]
    for name, value in episode.arrays().items():
        np.testing.assert_array_equal(getattr(read, name), value[kept], err_msg=name)
    note = read.metadata.salvage_note
    assert read.metadata.salvaged and f"reading resumed at the chunk at byte {chunks[3][0]}" in note
    assert note.endswith("skipped: samples 200 to 299 lost, 200 read after it")


def test_a_flipped_chunk_type_costs_that_chunk_and_the_chunks_after_it_are_read(tmp_path):
    # The third chunk read as another record kind: framing intact, its samples missing, the rest read.
    episode, path, chunks = _five_chunks(tmp_path)
    data = bytearray(path.read_bytes())
    data[chunks[2][0]] ^= 0x01  # the third chunk's type: 0x06 becomes 0x07, a message index
    path.write_bytes(bytes(data))
    read = read_quietly(path)
    kept = np.r_[0:200, 300:500]
    np.testing.assert_array_equal(read.t, episode.t[kept])
    # Read as a message index, its length does not match one: reading resumes at the next chunk.
    assert f"reading resumed at the chunk at byte {chunks[3][0]}" in read.metadata.salvage_note
    assert "samples 200 to 299 lost, 200 read after it" in read.metadata.salvage_note


def test_file_cut_before_its_metadata_is_refused(tmp_path):
    data = write_episode(tmp_path / "e.mcap", make_episode(10)).read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[:40])
    with pytest.raises(ValueError, match=r"cut\.mcap.*before any episode metadata"):
        read_episode(cut)


_KILL_CHILD = """
import sys, time
import numpy as np
sys.path[:0] = [sys.argv[1], sys.argv[1] + "/tests"]
from _episodes import make_metadata, sample
from qube_koopman.daq.log import EpisodeWriter
mode, path = sys.argv[2], sys.argv[3]
log = EpisodeWriter(path, make_metadata(), flush_interval_s=0.1)
for k in range(1_000_000):  # bounded, in case the kill never comes
    log.write_sample(**sample(k))
    if k == 1019:
        print("ready", flush=True)
        if mode == "idle":
            time.sleep(60)
"""


@pytest.mark.parametrize("mode", ["idle", "busy"])
def test_writer_killed_mid_episode_leaves_a_readable_prefix(tmp_path, mode):
    path = tmp_path / "killed.mcap"
    child = subprocess.Popen(
        [sys.executable, "-c", _KILL_CHILD, str(REPO), mode, str(path)], stdout=subprocess.PIPE, text=True
    )
    try:
        assert child.stdout.readline().strip() == "ready"
        if mode == "busy":
            time.sleep(0.05)  # let it write on, so the kill lands anywhere
        os.kill(child.pid, signal.SIGKILL)
    finally:
        child.kill()
        child.wait(timeout=10)
    read = read_quietly(path)
    n = len(read)
    # Flushed every 50 samples; the 20 samples after the last flush are lost when idle.
    assert n == 1000 if mode == "idle" else (n >= 1000 and n % 50 == 0)
    expected = {name: np.array([sample(k)[name] for k in range(n)]) for name in sample(0)}
    for name, value in expected.items():
        np.testing.assert_array_equal(getattr(read, name), value, err_msg=name)
    assert read.metadata.status == "incomplete" and read.metadata.salvaged


# --- refused files -------------------------------------------------------------


def test_not_an_mcap_file_is_refused_with_its_name(tmp_path):
    path = tmp_path / "notes.mcap"
    path.write_text("t, theta\n0, 0\n")
    with pytest.raises(ValueError, match=r"notes\.mcap: not an MCAP file"):
        read_episode(path)
    empty = tmp_path / "empty.mcap"
    empty.write_bytes(b"")
    with pytest.raises(ValueError, match=r"empty\.mcap: empty file"):
        read_episode(empty)


def _mcap_with_metadata(path, records: dict) -> None:
    from mcap.writer import Writer

    with open(path, "wb") as f:
        writer = Writer(f)
        writer.start()
        for name, value in records.items():
            writer.add_metadata(name, value)
        writer.finish()


def test_unknown_format_version_is_refused(tmp_path):
    good = write_episode(tmp_path / "good.mcap", make_episode(3))
    from mcap.reader import make_reader

    with open(good, "rb") as f:
        records = {m.name: m.metadata for m in make_reader(f).iter_metadata()}
    records["qube.episode"]["format_version"] = "2.0"
    path = tmp_path / "future.mcap"
    _mcap_with_metadata(path, records)
    with pytest.raises(ValueError, match=r"future\.mcap: episode log format version '2.0' is not supported"):
        read_episode(path)


def test_mcap_that_is_not_an_episode_log_is_refused(tmp_path):
    path = tmp_path / "other.mcap"
    _mcap_with_metadata(path, {"something": {"a": "b"}})
    with pytest.raises(ValueError, match=r"other\.mcap: not a QUBE episode log"):
        read_episode(path)


def test_metadata_only_read_skips_samples(tmp_path):
    path = write_episode(tmp_path / "e.mcap", make_episode(100))
    meta = read_episode_metadata(path)
    assert meta.status == "complete" and meta.sample_rate_hz == RATE
    np.testing.assert_array_equal(meta.controller.system.D, QUBE_PD.D)


@pytest.mark.parametrize("use_chunking", [True, False])
def test_file_rewritten_by_another_mcap_writer_reads_the_same(tmp_path, use_chunking):
    # Another tool may rewrite a log: unchunked, or with other channels interleaved
    # (which takes the reader off its one-view-per-chunk fast path).
    from mcap.reader import make_reader
    from mcap.writer import Writer

    episode = make_episode(400)
    original = write_episode(tmp_path / "e.mcap", episode)
    rewritten = tmp_path / "rewritten.mcap"
    with open(original, "rb") as f, open(rewritten, "wb") as out:
        reader = make_reader(f)
        writer = Writer(out, use_chunking=use_chunking)
        writer.start()
        for record in reader.iter_metadata():
            writer.add_metadata(record.name, record.metadata)
        events = None
        for k, (schema, channel, message) in enumerate(reader.iter_messages()):
            if events is None:
                sample_channel = writer.register_channel(
                    channel.topic,
                    channel.message_encoding,
                    writer.register_schema(schema.name, schema.encoding, schema.data),
                )
                events = writer.register_channel("/qube/event", "json", 0)
            writer.add_message(sample_channel, message.log_time, message.data, message.publish_time, message.sequence)
            if k % 100 == 0:
                writer.add_message(events, message.log_time, b'{"note": "x"}', message.log_time, k)
        writer.finish()
    read = read_episode(rewritten)
    assert_prefix(read, episode, 400)
    assert read.is_complete


def _chunk_spans(path) -> list[tuple[int, int, range]]:
    """Each chunk's byte span in the file and the sample indices it holds (from the MCAP chunk index)."""
    from mcap.reader import make_reader

    with open(path, "rb") as f:
        index = make_reader(f).get_summary().chunk_indexes
    t0 = min(c.message_start_time for c in index)
    return [
        (
            c.chunk_start_offset,
            c.chunk_start_offset + c.chunk_length,
            range(round((c.message_start_time - t0) * 1e-9 * RATE), round((c.message_end_time - t0) * 1e-9 * RATE) + 1),
        )
        for c in index
    ]


@settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(position=st.floats(0, 1), flip=st.integers(1, 255), cut=st.booleans())
# Found by fresh draws: a flip in the length of the message index between two chunks (the chunks after
# it were lost), in a chunk's record type (its samples missing, the file refused), in its compression's
# name (refused), in the status record written last (refused).
@example(position=0.62890625, flip=1, cut=False)
@example(position=7448 / 41224, flip=1, cut=False)
@example(position=7490 / 41224, flip=1, cut=False)
@example(position=39627 / 41224, flip=1, cut=False)
@example(position=6634 / 41224, flip=116, cut=False)  # a message index's length: its framing shifted into a chunk
@example(position=6633 / 41224, flip=5, cut=False)  # a message index read as the footer
def test_damaged_or_cut_files_give_a_prefix_or_a_value_error(tmp_path, position, flip, cut):
    # Whatever happens to the bytes, the reader returns samples it can vouch
    # for or refuses the file with a ValueError: never another exception.
    episode = make_episode(300, seed=1)
    path = tmp_path / "e.mcap"
    if not path.exists():
        with EpisodeWriter(path, episode.metadata, flush_interval_s=0.1) as log:
            log.write_samples(episode)
    data = bytearray(path.read_bytes())
    offset = int(position * (len(data) - 1))
    if cut:
        data = data[:offset]
    else:
        data[offset] ^= flip
    damaged = tmp_path / "damaged.mcap"
    damaged.write_bytes(bytes(data))
    chunks = _chunk_spans(path)
    # Every sample of a chunk the damage missed is recovered (issue 30): a flip costs its chunk, a
    # cut the chunks it runs into; only damage before the first chunk (the episode's metadata) may
    # cost the file.
    intact = [
        k for start, end, samples in chunks if (end <= offset if cut else not start <= offset < end) for k in samples
    ]
    try:
        read = read_quietly(damaged)
    except ValueError:
        assert offset < chunks[0][0], f"refused although the damage at byte {offset} is in the chunks"
        return
    index = np.rint(read.t * RATE).astype(int)
    assert set(intact) <= set(index.tolist()), f"damage at byte {offset} (cut {cut}) lost intact samples"
    # Sample bytes are CRC-checked per chunk, so what is read is never altered: the samples it
    # had, in order, a prefix unless a damaged chunk was skipped (then the note says so).
    assert np.all(np.diff(index) > 0) and (len(index) == 0 or index[0] >= 0)
    for name, value in episode.arrays().items():
        np.testing.assert_array_equal(getattr(read, name), value[index], err_msg=name)
    if "; skipped: " not in read.metadata.salvage_note:
        assert_prefix(read, episode, len(read))


# --- device time (format 1.3) -------------------------------------------------


def test_device_time_round_trips_and_shows_a_gap(tmp_path):
    # A device clock that lost three periods after sample 4, written sample by sample.
    device = np.r_[np.arange(5), np.arange(8, 13)] * (1 / RATE)
    path = tmp_path / "gap.mcap"
    with EpisodeWriter(path, make_metadata()) as log:
        for k, when in enumerate(device):
            log.write_sample(**sample(k), device_time=when)
        log.write_sample(**sample(len(device)))  # no device clock: NaN
    read = read_episode(path)
    np.testing.assert_array_equal(read.device_time[:-1], device)
    assert np.isnan(read.device_time[-1])
    gaps = np.diff(read.device_time[:-1]) * RATE
    assert np.flatnonzero(gaps > 1.5).tolist() == [4] and round(gaps[4]) == 4


def _write_format_1_2(path, episode: Episode) -> None:
    """An episode log as format 1.2 wrote it: the same file without the device_time field."""
    from mcap.writer import Writer

    from qube_koopman.daq.log.metadata import episode_records
    from qube_koopman.daq.log.schema import CDR_LE_HEADER, payload_dtype, sample_fields, state_field

    fields = [f for f in sample_fields(2) if f[0] != "device_time"]
    text = "\n".join(f"{t} {n}" for n, t in fields) + "\n"
    block = np.zeros(len(episode), payload_dtype(fields))
    block["cdr_header"] = np.frombuffer(CDR_LE_HEADER, "<u4")[0]
    for name, _ in fields:
        if name.startswith("controller_state_"):
            block[name] = episode.controller_state[:, int(name.rsplit("_", 1)[1])]
        elif name != "cdr_header":
            block[name] = getattr(episode, name)
    with open(path, "wb") as f:
        writer = Writer(f)
        writer.start()
        channel = writer.register_channel(
            "/qube/sample", "cdr", writer.register_schema("qube_msgs/msg/EpisodeSample", "ros2msg", text.encode())
        )
        for name, record in episode_records(episode.metadata).items():
            if name == "qube.episode":
                record = {**record, "format_version": "1.2"}
            writer.add_metadata(name, record)
        for k, row in enumerate(block):
            writer.add_message(channel, 10**18 + k * 2_000_000, row.tobytes(), 10**18 + k * 2_000_000, k)
        writer.add_metadata("qube.status", {"status": "complete", "reason": "", "n_samples": str(len(episode))})
        writer.finish()
    assert state_field(1) in text and "device_time" not in text


def test_format_1_2_file_still_reads_with_nan_device_time(tmp_path):
    episode = make_episode(300)
    path = tmp_path / "old.mcap"
    _write_format_1_2(path, episode)
    read = read_episode(path)
    assert read.metadata.log_format_version == "1.2" and read.is_complete
    assert np.isnan(read.device_time).all() and len(read) == 300
    for name in SIGNALS:
        if name != "device_time":
            np.testing.assert_array_equal(getattr(read, name), getattr(episode, name))
    np.testing.assert_array_equal(read.controller_state, episode.controller_state)


def test_a_damaged_chunk_size_is_reported_not_allocated(tmp_path):
    """Hypothesis found a flipped byte in a chunk's uncompressed size that made the reader
    reserve gigabytes (MemoryError); it is a damaged chunk like any other."""
    test_damaged_or_cut_files_give_a_prefix_or_a_value_error.hypothesis.inner_test(
        tmp_path=tmp_path, position=0.02, flip=129, cut=False
    )
