"""CRC-16/CCITT-FALSE, the checksum of every frame.

Polynomial 0x1021, initial value 0xFFFF, no reflection, no final XOR (check
value 0x29B1 for ``b"123456789"``). The standard library's
``binascii.crc_hqx`` computes exactly this non-reflected 0x1021 CRC from a
given start value, in C, which keeps the streaming decoder fast.
"""

from __future__ import annotations

from binascii import crc_hqx

__all__ = ["CRC_INIT", "crc16_ccitt_false"]

CRC_INIT = 0xFFFF


def crc16_ccitt_false(data: bytes | bytearray | memoryview, value: int = CRC_INIT) -> int:
    """CRC-16/CCITT-FALSE of ``data``.

    Parameters
    ----------
    data : bytes-like
        The bytes to check.
    value : int, optional
        Running CRC to continue from (default: the initial value 0xFFFF), so
        ``crc(a + b) == crc(b, crc(a))``.

    Returns
    -------
    int
        The 16-bit CRC.

    Examples
    --------
    The standard check value, and the same CRC continued over two pieces:

    >>> hex(crc16_ccitt_false(b"123456789"))
    '0x29b1'
    >>> hex(crc16_ccitt_false(b"6789", crc16_ccitt_false(b"12345")))
    '0x29b1'
    """
    return crc_hqx(data, value)
