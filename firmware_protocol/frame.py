"""Frames: header + payload, COBS-encoded, CRC trailer, 0x00 delimiter.

On the wire a frame is ``E + K + b"\\x00"`` where ``E`` is the COBS encoding
of ``header + payload`` and ``K`` is the CRC-16/CCITT-FALSE of ``E`` in three
bytes that are never zero. The CRC covers the encoded bytes, not the decoded
ones, because a single flipped bit in a COBS code byte moves zeros around and
becomes a many-bit error after decoding, where a CRC guarantees nothing; over
the wire bytes its guarantee (every error of up to 3 bits) holds as sent.
See PROTOCOL.md, "Why the CRC covers the encoded bytes".
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from enum import IntEnum

from .cobs import CobsError, cobs_decode, cobs_encode
from .crc import crc16_ccitt_false
from .messages import MAX_PAYLOAD, MESSAGE_CLASSES, PROTOCOL_VERSION, Message

__all__ = [
    "HEADER",
    "HEADER_SIZE",
    "TRAILER_SIZE",
    "MIN_WIRE_SIZE",
    "MAX_WIRE_SIZE",
    "Frame",
    "Reject",
    "encode_frame",
    "encode_raw_frame",
    "crc_trailer",
    "parse_piece",
]

# version, type, seq, timestamp_us, payload_len
HEADER = struct.Struct("<BBIIB")
HEADER_SIZE = HEADER.size
TRAILER_SIZE = 3
# COBS adds one byte per started 254 bytes; a version-1 body is at most 75.
MIN_WIRE_SIZE = HEADER_SIZE + 1 + TRAILER_SIZE
MAX_WIRE_SIZE = HEADER_SIZE + MAX_PAYLOAD + 1 + TRAILER_SIZE

_U32 = 0xFFFFFFFF


class Reject(IntEnum):
    """Why a received piece is not a frame; also the decoder's counter names."""

    OK = 0
    BAD_CRC = 1
    BAD_COBS = 2
    BAD_LENGTH = 3
    BAD_VERSION = 4
    UNKNOWN_TYPE = 5
    OVERSIZE = 6


@dataclass(frozen=True)
class Frame:
    """A decoded frame.

    Parameters
    ----------
    message : Message
        The payload, as its message class.
    seq : int
        The sender's frame counter (for a command: the command's sequence number).
    timestamp_us : int
        The sender's clock in microseconds (32 bits, wraps after 71.6 min).
    version : int
        Protocol version of the frame.
    """

    message: Message
    seq: int
    timestamp_us: int
    version: int = PROTOCOL_VERSION


def crc_trailer(encoded: bytes | bytearray | memoryview) -> bytes:
    """The 3-byte, zero-free CRC trailer ``K`` of COBS bytes ``encoded``.

    The CRC's 16 bits go 7, 7 and 2 to a byte, least significant first, each
    byte with bit 7 set; bits 2-6 of the last byte are zero.
    """
    crc = crc16_ccitt_false(encoded)
    return bytes((0x80 | (crc & 0x7F), 0x80 | ((crc >> 7) & 0x7F), 0x80 | (crc >> 14)))


def _check_u32(name: str, value: int) -> None:
    if not isinstance(value, int) or isinstance(value, bool) or not 0 <= value <= _U32:
        raise ValueError(f"{name} must be an integer in [0, 2**32 - 1], got {value!r}")


def encode_raw_frame(
    msg_type: int,
    seq: int,
    timestamp_us: int,
    payload: bytes,
    *,
    version: int = PROTOCOL_VERSION,
    payload_len: int | None = None,
) -> bytes:
    """Wire bytes of a frame from raw parts, delimiter included.

    The escape hatch for tests and fault injection: any type, version and
    length field can be sent, even ones a receiver must reject.

    Parameters
    ----------
    msg_type, version : int
        Header bytes (0..255).
    seq, timestamp_us : int
        Header fields (0..2**32 - 1).
    payload : bytes
        At most ``MAX_PAYLOAD`` bytes.
    payload_len : int, optional
        Value of the length field; default ``len(payload)``.

    Raises
    ------
    ValueError
        If a field is out of range or the payload is too long.
    """
    for name, value in (("msg_type", msg_type), ("version", version)):
        if not isinstance(value, int) or not 0 <= value <= 0xFF:
            raise ValueError(f"{name} must be a byte value, got {value!r}")
    _check_u32("seq", seq)
    _check_u32("timestamp_us", timestamp_us)
    if len(payload) > MAX_PAYLOAD:
        raise ValueError(f"payload has {len(payload)} bytes, at most {MAX_PAYLOAD} allowed")
    length = len(payload) if payload_len is None else payload_len
    if not isinstance(length, int) or not 0 <= length <= 0xFF:
        raise ValueError(f"payload_len must be a byte value, got {length!r}")
    encoded = cobs_encode(HEADER.pack(version, msg_type, seq, timestamp_us, length) + bytes(payload))
    return encoded + crc_trailer(encoded) + b"\0"


def encode_frame(message: Message, seq: int, timestamp_us: int) -> bytes:
    """Wire bytes of one frame carrying ``message``, delimiter included.

    Parameters
    ----------
    message : Message
        Any message of ``firmware_protocol.messages``.
    seq : int
        Sender's frame counter, 0..2**32 - 1 (for a command, its sequence number).
    timestamp_us : int
        Sender's clock in microseconds, 0..2**32 - 1 (mask with 0xFFFFFFFF).

    Raises
    ------
    ValueError
        If ``message`` is not a message or a field is out of range.
    """
    if not isinstance(message, Message):
        raise ValueError(f"message must be a firmware_protocol message, got {type(message).__name__}")
    return encode_raw_frame(message.TYPE, seq, timestamp_us, message.pack())


def parse_piece(piece: bytes | bytearray | memoryview) -> Frame | Reject:
    """Decode the bytes between two delimiters; never raises.

    Parameters
    ----------
    piece : bytes-like
        The COBS-encoded bytes of one frame, without its 0x00 delimiters.

    Returns
    -------
    Frame or Reject
        The frame, or the first reason it is not one, checked in the order
        size, CRC, COBS, version, length, type, payload size.
    """
    size = len(piece)
    if size > MAX_WIRE_SIZE:
        return Reject.OVERSIZE
    if size < MIN_WIRE_SIZE:
        return Reject.BAD_LENGTH
    k0, k1, k2 = piece[-3], piece[-2], piece[-1]
    if not (k0 & k1 & 0x80) or (k2 & 0xFC) != 0x80:
        return Reject.BAD_CRC
    encoded = piece[:-3]
    if crc16_ccitt_false(encoded) != (k0 & 0x7F) | ((k1 & 0x7F) << 7) | ((k2 & 0x03) << 14):
        return Reject.BAD_CRC
    try:
        body = cobs_decode(encoded)
    except CobsError:
        return Reject.BAD_COBS
    if not body or body[0] != PROTOCOL_VERSION:
        return Reject.BAD_VERSION
    if len(body) < HEADER_SIZE:
        return Reject.BAD_LENGTH
    version, msg_type, seq, timestamp_us, payload_len = HEADER.unpack_from(body)
    if payload_len != len(body) - HEADER_SIZE:
        return Reject.BAD_LENGTH
    cls = MESSAGE_CLASSES.get(msg_type)
    if cls is None:
        return Reject.UNKNOWN_TYPE
    if payload_len != cls.SIZE:
        return Reject.BAD_LENGTH
    return Frame(cls.unpack(body[HEADER_SIZE:]), seq, timestamp_us, version)
