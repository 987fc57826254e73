"""An MCAP writer that adds messages in blocks: mcap's ``Writer``'s file, byte for byte.

Why not ``mcap.writer.Writer`` itself: it serializes each message in Python (a dataclass, five
``struct.pack`` calls and an index entry per message, about 20 us), which was 70 % of importing
the paper's 48 episodes and a third of ``qube-run``'s tick in its writer thread. Here a chunk's
message records are packed at once with numpy (one structured array, its bytes), as are their
message index entries. Everything else is mcap's own: its record classes serialize the header,
schemas, channels, metadata, chunks, indexes, statistics and footer, in the order and with the
offsets its ``Writer`` (mcap 1.6, default options: 1 MiB chunks, every index, repeated schemas
and channels, statistics, summary offsets, chunk and summary CRCs, no data-section CRC) gives
them; ``tests/daq/test_mcap_writer.py`` checks the files are identical.
"""

from __future__ import annotations

import struct
import zlib
from typing import IO, Any

import numpy as np

__all__ = ["BlockWriter", "CHUNK_SIZE", "COMPRESSIONS", "message_records"]

#: The chunks' compressions.
COMPRESSIONS = ("zstd", "lz4", "none")
#: Uncompressed bytes after which a chunk is closed (mcap's ``Writer`` default).
CHUNK_SIZE = 1024 * 1024
_MAGIC = struct.pack("<8B", 137, 77, 67, 65, 80, 48, 13, 10)
_MESSAGE_OPCODE = 0x05
_MESSAGE_INDEX_OPCODE = 0x07
_HEAD = 1 + 8  # a record's opcode and length
_MESSAGE_FIELDS = 2 + 4 + 8 + 8  # channel id, sequence, log time, publish time


def message_records(channel_id: int, sequences: np.ndarray, log_times: np.ndarray, payloads: np.ndarray) -> bytes:
    """MCAP message records, concatenated: each message's publish time is its log time.

    Parameters
    ----------
    channel_id : int
    sequences, log_times : ndarray of int of shape (n,)
    payloads : ndarray of uint8 of shape (n, size)
        Each message's data, all of one size.

    Returns
    -------
    bytes
        What ``mcap.records.Message(...).write`` writes for each, in order.
    """
    size = payloads.shape[1]
    records = np.empty(
        len(log_times),
        np.dtype(
            [
                ("opcode", "u1"),
                ("length", "<u8"),
                ("channel", "<u2"),
                ("sequence", "<u4"),
                ("log_time", "<u8"),
                ("publish_time", "<u8"),
                ("data", f"V{size}"),
            ]
        ),
    )
    records["opcode"] = _MESSAGE_OPCODE
    records["length"] = _MESSAGE_FIELDS + size
    records["channel"] = channel_id
    records["sequence"] = sequences
    records["log_time"] = log_times
    records["publish_time"] = log_times
    records["data"] = np.ascontiguousarray(payloads).view(f"V{size}")[:, 0]
    return records.tobytes()


def _message_index(channel_id: int, log_times: np.ndarray, offsets: np.ndarray) -> bytes:
    """The message index record of one channel's messages in a chunk (``mcap.records.MessageIndex``)."""
    entries = np.empty((len(log_times), 2), "<u8")
    entries[:, 0], entries[:, 1] = log_times, offsets
    body = struct.pack("<HI", channel_id, entries.nbytes) + entries.tobytes()
    return struct.pack("<BQ", _MESSAGE_INDEX_OPCODE, len(body)) + body


class _Chunk:
    """The chunk being built: its records' bytes and, per channel, its messages' times and offsets."""

    def __init__(self) -> None:
        self.parts: list[bytes] = []
        self.size = 0
        self.indices: dict[int, tuple[list[np.ndarray], list[np.ndarray]]] = {}
        self.start_time = 0
        self.end_time = 0
        self.n_messages = 0

    def add_record(self, data: bytes) -> None:
        self.parts.append(data)
        self.size += len(data)

    def add_messages(self, channel_id: int, records: bytes, log_times: np.ndarray, record_size: int) -> None:
        n = len(log_times)
        offsets = self.size + record_size * np.arange(n, dtype=np.uint64)
        times, places = self.indices.setdefault(channel_id, ([], []))
        times.append(log_times)
        places.append(offsets)
        first, last = int(log_times.min()), int(log_times.max())
        self.start_time = first if self.n_messages == 0 else min(self.start_time, first)
        self.end_time = max(self.end_time, last)
        self.n_messages += n
        self.add_record(records)


class BlockWriter:
    """Write an MCAP file as ``mcap.writer.Writer(stream, compression=...)`` does, messages in blocks.

    Parameters
    ----------
    stream : binary file object
        Open for writing, positioned at its start (``tell`` gives the offsets).
    compression : {"zstd", "lz4", "none"}
        Of the chunks.
    """

    def __init__(self, stream: IO[bytes], compression: str = "zstd") -> None:
        from mcap.records import Statistics

        if compression not in COMPRESSIONS:
            raise ValueError(f"compression must be one of {', '.join(COMPRESSIONS)}, got {compression!r}")
        self._stream = stream
        self._compression = compression
        self._schemas: list[Any] = []
        self._channels: list[Any] = []
        self._chunk_indices: list[Any] = []
        self._metadata_indices: list[Any] = []
        self._chunk = _Chunk()
        self._statistics = Statistics(
            message_count=0,
            schema_count=0,
            channel_count=0,
            attachment_count=0,
            metadata_count=0,
            chunk_count=0,
            message_start_time=0,
            message_end_time=0,
            channel_message_counts={},
        )

    @staticmethod
    def _bytes(record) -> bytes:
        from mcap.data_stream import RecordBuilder

        builder = RecordBuilder()
        record.write(builder)
        return builder.end()

    def start(self, profile: str = "", library: str = "") -> None:
        """The magic and the header record."""
        from mcap.records import Header

        self._stream.write(_MAGIC)
        self._stream.write(self._bytes(Header(profile=profile, library=library)))

    def register_schema(self, name: str, encoding: str, data: bytes) -> int:
        """A schema (into the chunk being built, as mcap's writer puts it); its id."""
        from mcap.records import Schema

        schema = Schema(id=len(self._schemas) + 1, name=name, encoding=encoding, data=data)
        self._schemas.append(schema)
        self._statistics.schema_count += 1
        self._add_to_chunk(self._bytes(schema))
        return schema.id

    def register_channel(self, topic: str, message_encoding: str, schema_id: int, metadata=None) -> int:
        """A channel (into the chunk being built); its id."""
        from mcap.records import Channel

        channel = Channel(
            id=len(self._channels) + 1,
            topic=topic,
            message_encoding=message_encoding,
            schema_id=schema_id,
            metadata=dict(metadata or {}),
        )
        self._channels.append(channel)
        self._statistics.channel_count += 1
        self._add_to_chunk(self._bytes(channel))
        return channel.id

    def add_metadata(self, name: str, data: dict[str, str]) -> None:
        """A metadata record, written at once outside the chunks, and its index."""
        from mcap.records import Metadata, MetadataIndex

        offset = self._stream.tell()
        record = self._bytes(Metadata(name=name, metadata=data))
        self._statistics.metadata_count += 1
        self._metadata_indices.append(MetadataIndex(offset=offset, length=len(record), name=name))
        self._stream.write(record)

    def add_messages(self, channel_id: int, first_sequence: int, log_times, payloads: np.ndarray) -> None:
        """Messages of one channel, in order: ``payloads`` (n, size) bytes, sequence numbers from ``first_sequence``.

        A chunk closes after the message that takes it past :data:`CHUNK_SIZE` bytes, as in
        mcap's writer.
        """
        log_times = np.asarray(log_times, dtype=np.uint64)
        n = len(log_times)
        if not n:
            return
        payloads = np.asarray(payloads, dtype=np.uint8).reshape(n, -1)  # n > 0 here
        record_size = _HEAD + _MESSAGE_FIELDS + payloads.shape[1]
        stats = self._statistics
        first, last = int(log_times.min()), int(log_times.max())
        stats.message_start_time = first if stats.message_count == 0 else min(stats.message_start_time, first)
        stats.message_end_time = max(stats.message_end_time, last)
        stats.channel_message_counts[channel_id] = stats.channel_message_counts.get(channel_id, 0) + n
        stats.message_count += n
        sequences = (first_sequence + np.arange(n)) % 2**32
        k = 0
        while k < n:
            # Messages until the one that takes the chunk past its size (all, when none does).
            room = CHUNK_SIZE - self._chunk.size
            take = min(n - k, max(room, 0) // record_size + 1)
            part = slice(k, k + take)
            records = message_records(channel_id, sequences[part], log_times[part], payloads[part])
            self._chunk.add_messages(channel_id, records, log_times[part], record_size)
            k += take
            if self._chunk.size > CHUNK_SIZE:
                self._finish_chunk()

    def _add_to_chunk(self, record: bytes) -> None:
        self._chunk.add_record(record)
        if self._chunk.size > CHUNK_SIZE:
            self._finish_chunk()

    def _finish_chunk(self) -> None:
        from mcap.records import Chunk, ChunkIndex

        chunk = self._chunk
        if chunk.n_messages == 0:  # schemas and channels wait for the first message, as in mcap's writer
            return
        self._statistics.chunk_count += 1
        data = b"".join(chunk.parts)
        if self._compression == "zstd":
            import zstandard

            compressed = zstandard.compress(data)
        elif self._compression == "lz4":
            import lz4.frame

            compressed = lz4.frame.compress(data)
        else:
            compressed = data
        record = Chunk(
            compression="" if self._compression == "none" else self._compression,
            data=compressed,
            message_start_time=chunk.start_time,
            message_end_time=chunk.end_time,
            uncompressed_crc=zlib.crc32(data),
            uncompressed_size=len(data),
        )
        start = self._stream.tell()
        written = self._bytes(record)
        self._stream.write(written)
        indices_start = self._stream.tell()
        offsets: dict[int, int] = {}
        indices: list[bytes] = []
        for channel_id, (times, places) in chunk.indices.items():
            offsets[channel_id] = indices_start + sum(len(index) for index in indices)
            indices.append(_message_index(channel_id, np.concatenate(times), np.concatenate(places)))
        index_bytes = b"".join(indices)
        self._stream.write(index_bytes)
        self._chunk_indices.append(
            ChunkIndex(
                message_start_time=chunk.start_time,
                message_end_time=chunk.end_time,
                chunk_start_offset=start,
                chunk_length=len(written),
                message_index_offsets=offsets,
                message_index_length=len(index_bytes),
                compression=record.compression,
                compressed_size=len(compressed),
                uncompressed_size=len(data),
            )
        )
        self._chunk = _Chunk()

    def flush(self) -> None:
        """Close the chunk in progress (if it holds a message) and flush the stream, as mcap's ``Writer.flush``."""
        self._finish_chunk()
        self._stream.flush()

    def finish(self) -> None:
        """The last chunk, the data end, the summary with its offsets, the footer and the closing magic."""
        from mcap.data_stream import RecordBuilder
        from mcap.opcode import Opcode
        from mcap.records import DataEnd, Footer, SummaryOffset

        self._finish_chunk()
        self._stream.write(self._bytes(DataEnd(0)))
        summary_start = self._stream.tell()
        summary = RecordBuilder()
        groups = [
            (Opcode.SCHEMA, self._schemas),
            (Opcode.CHANNEL, self._channels),
            (Opcode.STATISTICS, [self._statistics]),
            (Opcode.CHUNK_INDEX, self._chunk_indices),
            (Opcode.ATTACHMENT_INDEX, []),
            (Opcode.METADATA_INDEX, self._metadata_indices),
        ]
        summary_offsets = []
        for opcode, records in groups:
            group_start = summary.count
            for record in records:
                record.write(summary)
            summary_offsets.append(
                SummaryOffset(
                    group_opcode=opcode,
                    group_start=summary_start + group_start,
                    group_length=summary.count - group_start,
                )
            )
        offsets_start = summary_start + summary.count
        for offset in summary_offsets:
            offset.write(summary)
        data = summary.end()
        crc = zlib.crc32(data)
        crc = zlib.crc32(struct.pack("<BQQQ", Opcode.FOOTER, 8 + 8 + 4, summary_start, offsets_start), crc)
        self._stream.write(data)
        self._stream.write(
            self._bytes(Footer(summary_start=summary_start, summary_offset_start=offsets_start, summary_crc=crc))
        )
        self._stream.write(_MAGIC)
