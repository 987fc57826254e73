"""Reading episode logs into numpy arrays, salvaging files cut short.

The reader walks the MCAP records itself instead of using
``mcap.reader``: per-message Python objects cost ~30 us each (0.3 s per
10k-sample episode), while the fixed-layout sample messages of a chunk can
be viewed with one ``np.frombuffer``. Walking the records also makes the
salvage of a truncated file exact: a record is used only if it is whole,
and a chunk only if it decompresses and passes its CRC. A damaged chunk whose
record framing is intact (the next record starts where its length says) is
skipped, and every intact chunk after it is read: the gap (which samples are
lost) is reported, and the episode read is marked incomplete. Non-sample
records are parsed with the mcap library's record classes.
"""

from __future__ import annotations

import io
import os
import struct
import warnings
import zlib
from pathlib import Path
from typing import TYPE_CHECKING, TypeVar

import numpy as np

from qube_koopman.core.files import read_bounded_bytes
from qube_koopman.daq.episode import SIGNALS, Episode, EpisodeMetadata
from qube_koopman.daq.log.metadata import EPISODE_RECORD, STATUS_RECORD, metadata_from_records
from qube_koopman.daq.log.schema import (
    CDR_LE_HEADER,
    SAMPLE_TOPIC,
    parse_schema,
    payload_dtype,
    state_field,
)

if TYPE_CHECKING:
    from mcap.records import Schema

__all__ = ["read_episode", "read_episode_metadata", "IncompleteEpisodeWarning"]

_MAGIC = b"\x89MCAP0\r\n"
#: The largest log read whole (an hour at 500 Hz is about 30 MB): no FIFO, device or absurd file.
_MAX_LOG_BYTES = 4 * 2**30
_HEADER, _FOOTER, _SCHEMA, _CHANNEL, _MESSAGE, _CHUNK = 0x01, 0x02, 0x03, 0x04, 0x05, 0x06
_MESSAGE_INDEX, _METADATA, _DATA_END = 0x07, 0x0C, 0x0F
_OPNAMES = {
    0x01: "Header",
    0x02: "Footer",
    0x03: "Schema",
    0x04: "Channel",
    0x05: "Message",
    0x06: "Chunk",
    0x07: "MessageIndex",
    0x08: "ChunkIndex",
    0x09: "Attachment",
    0x0A: "AttachmentIndex",
    0x0B: "Statistics",
    0x0C: "Metadata",
    0x0D: "MetadataIndex",
    0x0E: "SummaryOffset",
    0x0F: "DataEnd",
}
_RECORD_HEAD = struct.Struct("<BQ")
_CHUNK_HEAD = struct.Struct("<QQQII")  # start, end, uncompressed size, crc, compression length
_CDR_LE = int.from_bytes(CDR_LE_HEADER, "little")
#: Sample fields added by a minor version; a file without them reads them as NaN.
_ADDED_FIELDS = frozenset({"device_time"})  # 1.3


#: Largest uncompressed/stored size ratio a chunk may claim before it counts as damaged.
_MAX_EXPANSION = 100_000


class IncompleteEpisodeWarning(UserWarning):
    """A log was cut short or damaged; the episode read holds its readable prefix."""


class _Damaged(Exception):
    """A record or chunk that cannot be used; everything before it can."""


def _message_dtype(payload: np.dtype) -> np.dtype:
    """A whole MCAP Message record (opcode, length, header fields, payload) as one dtype."""
    assert payload.names is not None and payload.fields is not None  # a structured dtype (payload_dtype's)
    names = ["op", "len", "channel", "seq", "log_time", "publish_time", *payload.names]
    formats = ["u1", "<u8", "<u2", "<u4", "<u8", "<u8", *(payload.fields[n][0] for n in payload.names)]
    offsets = [0, 1, 9, 11, 15, 23, *(31 + payload.fields[n][1] for n in payload.names)]
    return np.dtype({"names": names, "formats": formats, "offsets": offsets, "itemsize": 31 + payload.itemsize})


_Record = TypeVar("_Record")


def _parse(record_class: type[_Record], body) -> _Record:
    from mcap.data_stream import ReadDataStream
    from mcap.exceptions import McapError

    try:
        # Each mcap record class has a static read(); their base class (the bound it would need) does not.
        return record_class.read(ReadDataStream(io.BytesIO(bytes(body))))  # type: ignore[attr-defined]
    except (McapError, struct.error, UnicodeDecodeError, ValueError) as exc:
        raise _Damaged(f"malformed {record_class.__name__} record ({exc})") from None


class _Pending:
    """A chunk read whole before the sample schema was known: its decompressed records."""

    __slots__ = ("raw",)

    def __init__(self, raw: bytes) -> None:
        self.raw = raw


class _Scan:
    """One pass over a file's records, collecting metadata and sample messages."""

    def __init__(self, where: str, decode_chunks: bool) -> None:
        self.where = where
        self.decode_chunks = decode_chunks
        self.records: dict[str, dict[str, str]] = {}
        self.schemas: dict[int, Schema] = {}
        self.fields: list[tuple[str, str]] | None = None
        self.sample_channel: int | None = None
        self.message_dtype: np.dtype | None = None
        #: The chunks' sample blocks in file order while the records are read, with chunks read before the
        #: sample schema (_Pending) and those that then failed (None); finish() keeps the samples in ``samples``.
        self.blocks: list[np.ndarray | _Pending | None] = []
        self.samples: list[np.ndarray] = []
        self.n_chunks = 0
        self.problem = ""
        #: Damaged chunks skipped: (what was wrong, the index in ``blocks`` the samples after it start at).
        self.gaps: list[tuple[str, int]] = []
        #: Where the last chunk read whole ends (after the magic before any): where a resync searches from.
        self.verified_end = len(_MAGIC)

    def run(self, data: bytes) -> None:
        if len(data) == 0:
            raise ValueError(f"{self.where}: empty file, not an MCAP episode log")
        if data[:8] != _MAGIC:
            raise ValueError(f"{self.where}: not an MCAP file (bad magic bytes)")
        view = memoryview(data)
        pos, n = 8, len(data)
        while True:
            if pos == n:
                self.problem = f"file ends at byte {n} without an MCAP footer"
                return
            if pos + 9 > n:
                self.problem = f"file ends inside a record header at byte {pos}"
                return
            op, length = _RECORD_HEAD.unpack_from(data, pos)
            end = pos + 9 + length
            name = _OPNAMES.get(op, f"0x{op:02x}")
            if end > n:
                problem = f"file ends inside a {name} record at byte {pos} ({n - pos} of {9 + length} bytes present)"
                resumed = self._resync(
                    data,
                    pos,
                    problem,
                    f"a {name} record at byte {pos} claims {9 + length} bytes, past the end of the file",
                )
                if resumed is None:
                    return
                pos = resumed
                continue
            try:
                if op == _FOOTER:
                    if data[end : end + 8] == _MAGIC and end + 8 == n:
                        return
                    # A cut footer, or a flipped record type read as one in the middle of the file.
                    resumed = self._resync(
                        data,
                        pos,
                        "file ends without the closing MCAP magic",
                        f"a Footer record at byte {pos} is not at the end of the file",
                    )
                    if resumed is None:
                        return
                    pos = resumed
                    continue
                self._record(op, view[pos + 9 : end])
                if op == _CHUNK:
                    self.verified_end = end
            except _Damaged as exc:
                problem = f"{name} record at byte {pos} is unusable: {exc}"
                if op == _CHUNK and self._framed_after(data, end):
                    self.gaps.append((problem, len(self.blocks)))
                else:
                    resumed = self._resync(data, pos, problem, problem)
                    if resumed is None:
                        return
                    pos = resumed
                    continue
            pos = end

    def _resync(self, data: bytes, pos: int, problem: str, damage: str) -> int | None:
        """After the record at ``pos`` broke the framing, where reading goes on: the end of the next sound chunk.

        A flipped length field (a chunk's, or a message index's between two chunks) leaves no
        way to know where the next record starts. The next chunk is found by trying each 0x06
        byte after ``pos`` whose length frames a record and whose contents pass the CRC check
        (a false start does not), so the samples of every chunk the damage missed are read. The
        skipped bytes count as a gap (their samples, if any, lost), noted with ``damage``. None,
        and ``problem`` noted, when no sound chunk follows (a cut file) or chunks are not being
        decoded.
        """
        # From the end of the last chunk read whole: a damaged length may have framed the records after
        # it anywhere, even past the next chunk's start.
        n, start = len(data), self.verified_end
        while self.decode_chunks:
            at = data.find(bytes([_CHUNK]), start, n - 9)
            if at < 0:
                break
            start = at + 1
            (length,) = struct.unpack_from("<Q", data, at + 1)
            end = at + 9 + length
            if end > n or not self._framed_after(data, end) or struct.unpack_from("<I", data, at + 33)[0] == 0:
                continue  # no CRC to vouch for a chunk found by search
            gap = len(self.blocks)
            try:
                self._chunk(memoryview(data)[at + 9 : end])  # adds its samples only once every check passed
            except _Damaged:
                continue
            self.n_chunks += 1
            self.verified_end = end
            if damage:
                self.gaps.append((f"{damage}; reading resumed at the chunk at byte {at}", gap))
            return end
        self.problem = problem
        return None

    @staticmethod
    def _framed_after(data: bytes, end: int) -> bool:
        """Whether a record (of a known kind) or the end of the file follows a damaged one at ``end``.

        Then the damage is inside the record, its length field sound, and the records after it
        can be read; otherwise nothing after it can be trusted to start where it seems to.
        """
        return end == len(data) or (end + 9 <= len(data) and data[end] in _OPNAMES)

    def gap_notes(self, n_recorded: str | None) -> list[str]:
        """One line per skipped chunk: what was wrong, which samples are lost, how many were read after.

        Parameters
        ----------
        n_recorded : str or None
            The status record's sample count, if it survived (it tells what a gap at the end lost).
        """
        notes = []
        for problem, i in self.gaps:
            first = int(self.samples[i - 1]["seq"][-1]) + 1 if i > 0 else 0
            after = sum(len(b) for b in self.samples[i:])
            last: int | None
            if i < len(self.samples):
                last = int(self.samples[i]["seq"][0]) - 1
            else:
                last = int(n_recorded) - 1 if n_recorded and n_recorded.isdigit() else None
            if last is None:
                lost = f"the samples from {first} on lost"
            else:
                lost = f"samples {first} to {last} lost" if last >= first else "no samples lost"
            notes.append(f"{problem}; skipped: {lost}, {after} read after it")
        return notes

    def _record(self, op: int, body: memoryview) -> None:
        from mcap.records import Channel, Metadata, Schema

        if op == _CHUNK:
            self.n_chunks += 1
            if self.decode_chunks:
                self._chunk(body)
        elif op == _MESSAGE_INDEX:
            # Its length is checkable (channel, then 16-byte entries): a damaged one is caught here,
            # not many records later when the framing it shifted finally breaks.
            if len(body) < 6 or len(body) != 6 + struct.unpack_from("<I", body, 2)[0] or (len(body) - 6) % 16:
                raise _Damaged("its length does not match its entries")
        elif op == _METADATA:
            record = _parse(Metadata, body)
            self.records[record.name] = record.metadata
        elif op == _SCHEMA:
            schema = _parse(Schema, body)
            self.schemas[schema.id] = schema
        elif op == _CHANNEL:
            self._channel(_parse(Channel, body))
        elif op == _MESSAGE and self.decode_chunks:
            # An unchunked file (never written by daq.log, but valid MCAP).
            blocks: list[np.ndarray] = []
            head = bytes(_RECORD_HEAD.pack(op, len(body))) + bytes(body)
            self._chunk_records(head, blocks)
            self.blocks.extend(blocks)

    def _channel(self, channel) -> None:
        if channel.topic != SAMPLE_TOPIC or self.sample_channel is not None:
            return
        schema = self.schemas.get(channel.schema_id)
        if schema is None or schema.encoding != "ros2msg" or channel.message_encoding != "cdr":
            raise ValueError(
                f"{self.where}: channel {SAMPLE_TOPIC} is not ros2msg/cdr with its "
                f"schema; this is not an episode log this reader understands"
            )
        try:
            self.fields = parse_schema(schema.data.decode())
        except (UnicodeDecodeError, ValueError) as exc:
            raise ValueError(f"{self.where}: sample schema: {exc}") from None
        self.sample_channel = channel.id
        self.message_dtype = _message_dtype(payload_dtype(self.fields))
        for i, block in enumerate(self.blocks):  # chunks read before the schema was known
            if isinstance(block, _Pending):
                decoded: list[np.ndarray] = []
                try:
                    self._chunk_records(block.raw, decoded)
                except _Damaged as exc:
                    self.gaps.append((f"a chunk read before its schema is unusable: {exc}", i))
                    decoded = []
                self.blocks[i] = np.concatenate(decoded) if decoded else None

    def finish(self) -> None:
        """Keep the samples (drop chunks whose schema never came, empty ones) in ``samples``; gaps kept in place."""
        kept: list[np.ndarray] = []
        where: list[int] = []
        for block in self.blocks:
            where.append(len(kept))
            if isinstance(block, np.ndarray) and len(block):
                kept.append(block)
        where.append(len(kept))
        self.gaps = sorted(((problem, where[i]) for problem, i in self.gaps), key=lambda gap: gap[1])
        self.samples = kept

    def _chunk(self, body: memoryview) -> None:
        import lz4.frame
        import zstandard

        try:
            _, _, size, crc, clen = _CHUNK_HEAD.unpack_from(body, 0)
            compression = bytes(body[32 : 32 + clen]).decode()
            (records_len,) = struct.unpack_from("<Q", body, 32 + clen)
        except (struct.error, UnicodeDecodeError) as exc:
            raise _Damaged(f"malformed chunk header ({exc})") from None
        start = 40 + clen
        if start + records_len > len(body):
            raise _Damaged("records overrun the chunk")
        packed = body[start : start + records_len]
        # A damaged size field must not make the decompressor reserve gigabytes (hypothesis found
        # a flipped byte that did: MemoryError). The bound is far above any real chunk's
        # expansion; past it the chunk counts as damaged, like a failed CRC.
        if size > _MAX_EXPANSION * max(records_len, 1) + 4096:
            raise _Damaged(f"implausible uncompressed size {size} for {records_len} stored bytes")
        try:
            if compression == "zstd":
                raw = zstandard.ZstdDecompressor().decompress(packed, max_output_size=size)
            elif compression == "lz4":
                raw = lz4.frame.decompress(packed)
            elif compression == "":
                raw = bytes(packed)
            else:  # not written by any MCAP writer this reader knows: a damaged name, or a file it cannot read
                raise _Damaged(f"unsupported chunk compression {compression!r}")
        except (zstandard.ZstdError, RuntimeError, MemoryError) as exc:
            raise _Damaged(f"cannot decompress ({type(exc).__name__}: {exc})") from None
        if len(raw) != size or (crc and zlib.crc32(raw) != crc):
            raise _Damaged("contents fail the size or CRC check")
        blocks: list[np.ndarray] = []
        self._chunk_records(raw, blocks)
        if self.message_dtype is None:
            # The sample schema's chunk (the first) was damaged: keep this one's records until the
            # summary's copy of the schema and channel comes (see _channel), in its place in order.
            self.blocks.append(_Pending(raw))
            return
        # Only a chunk read whole counts.
        self.blocks.extend(blocks)

    def _chunk_records(self, buf: bytes, blocks: list[np.ndarray]) -> None:
        n, pos = len(buf), 0
        offsets: list[int] = []
        tried_bulk = False
        while pos < n:
            if pos + 9 > n:
                raise _Damaged("chunk ends inside a record header")
            op, length = _RECORD_HEAD.unpack_from(buf, pos)
            end = pos + 9 + length
            if end > n:
                raise _Damaged("chunk ends inside a record")
            if op == _MESSAGE and self.message_dtype is not None:
                (channel,) = struct.unpack_from("<H", buf, pos + 9)
                if channel == self.sample_channel:
                    if end - pos != self.message_dtype.itemsize:
                        raise _Damaged(
                            f"sample message of {length} bytes, the schema needs {self.message_dtype.itemsize - 9}"
                        )
                    if not tried_bulk:
                        # Usually the rest of the chunk is sample messages only: view them all at once.
                        tried_bulk = True
                        bulk = self._bulk(buf, pos)
                        if bulk is not None:
                            blocks.append(bulk)
                            return
                    offsets.append(pos)
            elif op in (_SCHEMA, _CHANNEL, _METADATA):
                self._record(op, memoryview(buf)[pos + 9 : end])
            pos = end
        if offsets:
            assert self.message_dtype is not None  # offsets are kept only for the sample channel's messages
            size = self.message_dtype.itemsize
            index = np.asarray(offsets)[:, None] + np.arange(size)
            blocks.append(np.frombuffer(buf, np.uint8)[index].view(self.message_dtype).reshape(-1))

    def _bulk(self, buf: bytes, pos: int) -> np.ndarray | None:
        assert self.message_dtype is not None  # called for the sample channel's messages only
        size = self.message_dtype.itemsize
        count, rest = divmod(len(buf) - pos, size)
        if rest:
            return None
        block = np.frombuffer(buf, self.message_dtype, count, pos)
        if (
            (block["op"] == _MESSAGE).all()
            and (block["len"] == size - 9).all()
            and (block["channel"] == self.sample_channel).all()
        ):
            return block
        return None


def _scan(path: str | os.PathLike, decode_chunks: bool) -> tuple[_Scan, EpisodeMetadata]:
    path = Path(path)
    scan = _Scan(str(path), decode_chunks)
    scan.run(read_bounded_bytes(path, _MAX_LOG_BYTES, "episode log"))
    scan.finish()
    if EPISODE_RECORD not in scan.records and scan.problem:
        raise ValueError(f"{path}: unreadable episode log: {scan.problem}, before any episode metadata")
    ok, jumps = _in_sequence(scan.samples, {i for _, i in scan.gaps})
    if not ok:
        raise ValueError(f"{path}: sample sequence numbers are not 0, 1, 2, ... (samples duplicated or out of order)")
    scan.gaps = sorted(
        scan.gaps
        + [
            ("records between two chunks are not what they were written as (a damaged record type or length)", i)
            for i in jumps
        ],
        key=lambda gap: gap[1],
    )
    status = scan.records.get(STATUS_RECORD)
    if decode_chunks and status is not None and not scan.problem and not scan.gaps:
        n = sum(len(b) for b in scan.samples)
        if status.get("n_samples") != str(n):
            scan.problem = f"status record counts {status.get('n_samples')} samples, the file holds {n}"
    notes = [
        *scan.gap_notes(None if status is None else status.get("n_samples")),
        *([scan.problem] if scan.problem else []),
    ]
    try:
        return scan, metadata_from_records(scan.records, str(path), salvage_note="; ".join(notes))
    except ValueError as exc:
        if status is None:
            raise
        # The status record is written last and not CRC-checked: a flip there must not cost the samples.
        del scan.records[STATUS_RECORD]
        notes.append(f"the status record is unreadable ({str(exc).removeprefix(f'{path}: ')}); status unknown")
        return scan, metadata_from_records(scan.records, str(path), salvage_note="; ".join(notes))


def _in_sequence(blocks: list[np.ndarray], gaps: set[int]) -> tuple[bool, list[int]]:
    """Whether sample sequence numbers run 0, 1, 2, ... only ever jumping forward, and where they jump.

    Returns
    -------
    ok : bool
        False for a duplicated or out-of-order sample, or a block not numbered consecutively.
    jumps : list of int
        Blocks that start past the sample expected with no skipped damage noted before them: the
        bytes before them framed as records of another kind (a flipped record type), so their
        samples are missing without a chunk having failed a check.
    """
    expected = 0
    jumps: list[int] = []
    for i, block in enumerate(blocks):
        seq = block["seq"]
        if len(seq) == 0:
            continue
        start = int(seq[0])
        if start < expected or not np.array_equal(seq, start + np.arange(len(seq))):
            return False, jumps
        if start > expected and i not in gaps:
            jumps.append(i)
        expected = start + len(seq)
    return True, jumps


def read_episode_metadata(path: str | os.PathLike) -> EpisodeMetadata:
    """Metadata of an episode log, without decoding its samples.

    Chunks are not decompressed, so a damaged chunk is not noticed here
    (:func:`read_episode` checks every one); a truncated file is.

    Parameters
    ----------
    path : str or path-like
        The episode log.

    Returns
    -------
    EpisodeMetadata

    Raises
    ------
    ValueError
        Naming the file, if it is not an MCAP episode log or has an
        unsupported format version.
    """
    return _scan(path, decode_chunks=False)[1]


def read_episode(path: str | os.PathLike, *, warn: bool = True) -> Episode:
    """Read an episode log into arrays.

    A file cut short (the writer was killed) or damaged is read up to its
    last whole chunk: the episode then has ``metadata.salvaged = True``,
    ``metadata.salvage_note`` saying what was wrong, and status
    ``"incomplete"`` unless the final status record survived. A damaged
    chunk inside the file is skipped and the chunks after it read: the
    samples then jump over the gap (``t`` shows it), the salvage note names
    the samples lost, and the status is ``"incomplete"`` (its reason gives
    the final status the log recorded, if it did).

    Parameters
    ----------
    path : str or Path
        The ``.mcap`` file.
    warn : bool
        Issue an :class:`IncompleteEpisodeWarning` for a salvaged file.

    Returns
    -------
    Episode

    Raises
    ------
    ValueError
        Naming the file and the problem: not MCAP, not an episode log, an
        unsupported format version, or a sample schema missing fields.
    OSError
        If the file cannot be read.
    """
    scan, meta = _scan(path, decode_chunks=True)
    where = str(path)
    k = meta.controller.system.n_states
    ticks = meta.controller.tick_fields
    present = set(SIGNALS) if scan.fields is None else set(dict(scan.fields))
    if scan.fields is not None:
        missing = [
            name
            for name in (*SIGNALS, *map(state_field, range(k)), *ticks, "saturation")
            if name not in present and name not in _ADDED_FIELDS
        ]
        if missing:
            raise ValueError(f"{where}: sample schema misses fields {', '.join(missing)}")
    blocks = scan.samples
    if blocks:

        def column(name: str) -> np.ndarray:
            return blocks[0][name] if len(blocks) == 1 else np.concatenate([b[name] for b in blocks])

        if not (column("cdr_header") == _CDR_LE).all():
            raise ValueError(f"{where}: sample messages are not plain little-endian CDR")
        arrays = {name: column(name) for name in (*SIGNALS, "saturation") if name in present or name == "saturation"}
        state = np.column_stack([column(state_field(i)) for i in range(k)]) if k else np.empty((len(arrays["t"]), 0))
        record = np.column_stack([column(name) for name in ticks]) if ticks else None
    else:
        arrays = {name: np.empty(0) for name in SIGNALS}
        arrays["saturation"] = np.empty(0, np.int8)
        state = np.empty((0, k))
        record = np.empty((0, len(ticks))) if ticks else None
    episode = Episode(metadata=meta, controller_state=state, controller_record=record, **arrays)
    if meta.salvaged and warn:
        warnings.warn(
            f"{where}: {meta.salvage_note}; read {len(episode)} samples (status {meta.status})",
            IncompleteEpisodeWarning,
            stacklevel=2,
        )
    return episode
