"""Consistent Overhead Byte Stuffing (Cheshire and Baker, 1999).

COBS rewrites a byte string so that it contains no 0x00, at a cost of one
byte per started block of 254 bytes; 0x00 is then free to delimit frames.
This is the canonical variant: a final block of exactly 254 non-zero bytes
gets no trailing code byte (``cobs_encode(bytes(range(1, 255)))`` is 255
bytes), as in the examples of the COBS article on Wikipedia.
"""

from __future__ import annotations

__all__ = ["CobsError", "cobs_encode", "cobs_decode"]

_MAX_RUN = 254


class CobsError(ValueError):
    """The input is not a valid COBS encoding."""


def cobs_encode(data: bytes | bytearray | memoryview) -> bytes:
    """Encode ``data`` so that the result contains no 0x00 byte.

    Parameters
    ----------
    data : bytes-like
        Any bytes, zeros included.

    Returns
    -------
    bytes
        The COBS encoding, without a frame delimiter.

    Examples
    --------
    >>> cobs_encode(b"\\x11\\x00\\x22")
    b'\\x02\\x11\\x02"'
    """
    out = bytearray()
    runs = bytes(data).split(b"\0")
    last = len(runs) - 1
    for index, run in enumerate(runs):
        # A code byte 0xFF means "254 bytes, no zero follows"; any other code
        # n means "n - 1 bytes, then a zero", except at the very end.
        while len(run) >= _MAX_RUN:
            out.append(0xFF)
            out += run[:_MAX_RUN]
            run = run[_MAX_RUN:]
            if not run and index == last:
                return bytes(out)
        out.append(len(run) + 1)
        out += run
    return bytes(out)


def cobs_decode(data: bytes | bytearray | memoryview) -> bytes:
    """Decode a COBS encoding (without its delimiter).

    Parameters
    ----------
    data : bytes-like
        A COBS encoding: no 0x00 bytes, every block complete.

    Returns
    -------
    bytes
        The original bytes.

    Raises
    ------
    CobsError
        If ``data`` contains 0x00 or a code byte points past its end.

    Examples
    --------
    >>> cobs_decode(b"\\x02\\x11\\x02\\x22")
    b'\\x11\\x00"'
    """
    data = bytes(data)
    if 0 in data:
        raise CobsError("COBS data contains a 0x00 byte")
    out = bytearray()
    end = len(data)
    pos = 0
    while pos < end:
        code = data[pos]
        stop = pos + code
        if stop > end:
            raise CobsError(f"COBS block at offset {pos} needs {code - 1} bytes, only {end - pos - 1} left")
        out += data[pos + 1 : stop]
        pos = stop
        if code != 0xFF and pos < end:
            out.append(0)
    return bytes(out)
