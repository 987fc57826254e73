"""The streaming decoder: arbitrary byte chunks in, valid frames out.

A serial port delivers whatever the OS has buffered: half a frame, three
frames, garbage after a reconnect. The decoder keeps the bytes since the
last 0x00, hands every complete piece to ``parse_piece`` and counts what it
rejects. It never raises on bytes; a piece that outgrows the largest frame
is dropped until the next delimiter, so memory stays bounded.
"""

from __future__ import annotations

from dataclasses import dataclass, fields

from .frame import MAX_WIRE_SIZE, Frame, Reject, parse_piece

__all__ = ["DecoderStats", "StreamDecoder"]


@dataclass
class DecoderStats:
    """Counters of a ``StreamDecoder`` (the C decoder keeps the same ones).

    Parameters
    ----------
    frames : int
        Valid frames delivered.
    bad_crc, bad_cobs, bad_length, bad_version, unknown_type, oversize : int
        Pieces rejected, by reason (see ``Reject``).
    last_bad_version : int
        Version byte of the last frame rejected for its version (0: none), so
        a host can say which protocol the other end speaks.
    bytes_in : int
        Bytes fed so far.
    """

    frames: int = 0
    bad_crc: int = 0
    bad_cobs: int = 0
    bad_length: int = 0
    bad_version: int = 0
    unknown_type: int = 0
    oversize: int = 0
    last_bad_version: int = 0
    bytes_in: int = 0

    @property
    def rejected(self) -> int:
        """Total pieces rejected for any reason."""
        return self.bad_crc + self.bad_cobs + self.bad_length + self.bad_version + self.unknown_type + self.oversize

    def as_dict(self) -> dict[str, int]:
        """Plain-data form (for logs)."""
        return {f.name: getattr(self, f.name) for f in fields(self)}


_COUNTER: dict[Reject, str] = {reason: reason.name.lower() for reason in Reject if reason is not Reject.OK}


class StreamDecoder:
    """Incremental frame decoder.

    Examples
    --------
    >>> from qube_koopman.firmware_protocol import Hello, encode_frame
    >>> decoder = StreamDecoder()
    >>> wire = encode_frame(Hello(nonce=7), seq=1, timestamp_us=0)
    >>> decoder.feed(wire[:5]), [f.message for f in decoder.feed(wire[5:])]
    ([], [Hello(nonce=7)])
    """

    def __init__(self) -> None:
        self.stats = DecoderStats()
        self._partial = bytearray()
        self._overflowed = False

    def reset(self) -> None:
        """Forget any partial frame (counters are kept)."""
        self._partial.clear()
        self._overflowed = False

    def feed(self, data: bytes | bytearray | memoryview) -> list[Frame]:
        """Consume a chunk; return the frames it completes, in order.

        Parameters
        ----------
        data : bytes-like
            Any bytes, of any length.

        Returns
        -------
        list of Frame
            Frames whose delimiter is in ``data``; rejected pieces are counted
            in ``stats``.
        """
        data = bytes(data)
        self.stats.bytes_in += len(data)
        if 0 not in data:
            self._append(data)
            return []
        pieces = data.split(b"\0")
        self._append(pieces[0])
        pieces[0] = bytes(self._partial)
        if self._overflowed:
            pieces[0] = b""  # counted once already, when it overflowed
        self._partial.clear()
        self._overflowed = False
        tail = pieces.pop()
        frames = []
        stats = self.stats
        for piece in pieces:
            if not piece:
                continue  # extra delimiters are idle fill, not errors
            result = parse_piece(piece)
            if isinstance(result, Frame):
                stats.frames += 1
                frames.append(result)
                continue
            name = _COUNTER[result]
            setattr(stats, name, getattr(stats, name) + 1)
            if result is Reject.BAD_VERSION:
                stats.last_bad_version = _version_of(piece)
        self._append(tail)
        return frames

    def _append(self, data: bytes) -> None:
        if self._overflowed:
            return
        self._partial += data
        if len(self._partial) > MAX_WIRE_SIZE:
            self.stats.oversize += 1
            self._partial.clear()
            self._overflowed = True


def _version_of(piece: bytes) -> int:
    """Version byte of a CRC-valid piece (its first decoded byte)."""
    # The first COBS byte is a code: if it is 1 the first decoded byte is a
    # zero, otherwise it is the next raw byte.
    return 0 if piece[0] == 1 else piece[1]
