"""The streaming decoder: any chunking, garbage, mutations; never raises, counts rejects.

Property tests (hypothesis) over random and mutated streams, plus the golden
streams of golden_vectors.json with their expected counters.
"""

from __future__ import annotations

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from qube_koopman.firmware_protocol import Frame, Hello, StreamDecoder, Telemetry, encode_frame, encode_raw_frame
from qube_koopman.firmware_protocol.frame import MAX_WIRE_SIZE
from qube_koopman.firmware_protocol.vectors import load_vectors

from protocol_helpers import messages, u32

frame_specs = st.lists(st.tuples(messages, u32, u32), min_size=1, max_size=12)


def feed_in_chunks(decoder: StreamDecoder, stream: bytes, cuts: list[int]) -> list[Frame]:
    frames, start = [], 0
    for cut in sorted(set(c % (len(stream) + 1) for c in cuts)) + [len(stream)]:
        frames += decoder.feed(stream[start:cut])
        start = cut
    return frames


@given(frame_specs, st.lists(st.integers(0, 10_000), max_size=20))
def test_round_trip_under_any_chunking(specs, cuts):
    stream = b"".join(encode_frame(m, s, t) for m, s, t in specs)
    decoder = StreamDecoder()
    frames = feed_in_chunks(decoder, stream, cuts)
    assert frames == [Frame(m, s, t) for m, s, t in specs]
    assert decoder.stats.frames == len(specs) and decoder.stats.rejected == 0
    assert decoder.stats.bytes_in == len(stream)


@given(st.binary(max_size=3000), st.lists(st.integers(0, 10_000), max_size=20))
def test_random_bytes_never_raise(data, cuts):
    decoder = StreamDecoder()
    frames = feed_in_chunks(decoder, data, cuts)
    # Random bytes pass a CRC, a version byte, a length field and a type
    # check together far too rarely to ever be seen here.
    assert frames == []
    assert decoder.stats.bytes_in == len(data)


@given(
    st.lists(st.tuples(st.binary(max_size=120), messages, u32, u32), min_size=1, max_size=8),
    st.lists(st.integers(0, 10_000), max_size=10),
)
def test_resynchronizes_after_garbage(items, cuts):
    # Garbage may hold zeros or not; the delimiter a sender puts before a
    # frame after a disturbance is what makes the frame recoverable.
    stream = b"".join(garbage + b"\0" + encode_frame(m, s, t) for garbage, m, s, t in items)
    frames = feed_in_chunks(StreamDecoder(), stream, cuts)
    assert frames == [Frame(m, s, t) for _, m, s, t in items]


mutation = st.one_of(
    st.tuples(st.just("flip"), st.integers(0, 10**6), st.integers(0, 7)),
    st.tuples(st.just("delete"), st.integers(0, 10**6), st.integers(1, 8)),
    st.tuples(st.just("insert"), st.integers(0, 10**6), st.binary(min_size=1, max_size=8)),
    st.tuples(st.just("duplicate"), st.integers(0, 10**6), st.integers(1, 60)),
    st.tuples(st.just("truncate"), st.integers(0, 10**6), st.just(0)),
)


def mutate(stream: bytes, ops) -> bytes:
    data = bytearray(stream)
    for op, pos, arg in ops:
        if not data:
            break
        pos %= len(data)
        if op == "flip":
            data[pos] ^= 1 << arg
        elif op == "delete":
            del data[pos : pos + arg]
        elif op == "insert":
            data[pos:pos] = arg
        elif op == "duplicate":
            data[pos:pos] = data[pos : pos + arg]
        else:
            del data[pos:]
    return bytes(data)


@settings(max_examples=300)
@given(frame_specs, st.lists(mutation, min_size=1, max_size=6), st.lists(st.integers(0, 10_000), max_size=10))
def test_mutated_streams_yield_only_original_frames(specs, ops, cuts):
    originals = [Frame(m, s, t) for m, s, t in specs]
    stream = b"".join(encode_frame(m, s, t) for m, s, t in specs)
    decoder = StreamDecoder()
    frames = feed_in_chunks(decoder, mutate(stream, ops), cuts)
    # "duplicate" can legitimately repeat a whole frame; nothing else may appear.
    assert all(f in originals for f in frames)


@given(st.binary(max_size=600), frame_specs, st.lists(st.integers(0, 2_000), max_size=15))
def test_counters_do_not_depend_on_chunking(garbage, specs, cuts):
    stream = garbage + b"".join(encode_frame(m, s, t) for m, s, t in specs) + garbage
    whole, chunked = StreamDecoder(), StreamDecoder()
    assert whole.feed(stream) == feed_in_chunks(chunked, stream, cuts)
    assert whole.stats == chunked.stats


@pytest.mark.parametrize("vector", load_vectors()["streams"], ids=lambda v: v["name"])
def test_golden_streams(vector):
    decoder = StreamDecoder()
    stream = bytes.fromhex(vector["stream_hex"])
    frames = [f for i in range(len(stream)) for f in decoder.feed(stream[i : i + 1])]  # byte by byte
    expected = [StreamDecoder().feed(bytes.fromhex(h))[0] for h in vector["frames_hex"]]
    assert frames == expected
    stats = decoder.stats.as_dict()
    assert {k: stats[k] for k in vector["counters"]} == vector["counters"]


def test_bad_version_is_counted_and_remembered():
    decoder = StreamDecoder()
    decoder.feed(encode_raw_frame(0x01, 1, 2, b"\0\0\0\0", version=7))
    assert (decoder.stats.bad_version, decoder.stats.last_bad_version) == (1, 7)


def test_each_reject_reason_has_its_counter():
    decoder = StreamDecoder()
    good = encode_frame(Hello(nonce=3), 1, 2)
    decoder.feed(good[:4] + bytes((good[4] ^ 0x40,)) + good[5:])  # payload bit: bad CRC
    decoder.feed(encode_raw_frame(0x01, 1, 2, b"\0\0\0\0", payload_len=3))
    decoder.feed(encode_raw_frame(0x55, 1, 2, b""))
    assert (decoder.stats.bad_crc, decoder.stats.bad_length, decoder.stats.unknown_type) == (1, 1, 1)
    assert decoder.stats.rejected == 3 and decoder.stats.frames == 0


def test_memory_stays_bounded_without_delimiters():
    decoder = StreamDecoder()
    for _ in range(1000):
        assert decoder.feed(b"\x5a" * 1000) == []
    frame = encode_frame(Telemetry(tick=9), 1, 2)
    assert decoder.feed(b"\0" + frame) == [Frame(Telemetry(tick=9), 1, 2)]
    assert decoder.stats.oversize == 1
    assert len(decoder._partial) <= MAX_WIRE_SIZE  # the bound itself, not just the outcome


def test_reset_drops_partial_frame():
    decoder = StreamDecoder()
    frame = encode_frame(Hello(nonce=1), 1, 2)
    decoder.feed(frame[:10])
    decoder.reset()
    assert decoder.feed(frame[10:]) == []
    assert decoder.feed(frame) == [Frame(Hello(nonce=1), 1, 2)]


def test_feed_accepts_any_bytes_like():
    frame = encode_frame(Hello(nonce=1), 1, 2)
    for data in (frame, bytearray(frame), memoryview(frame)):
        assert StreamDecoder().feed(data) == [Frame(Hello(nonce=1), 1, 2)]
