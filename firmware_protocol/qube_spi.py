"""The QUBE-Servo 2's 17-byte SPI transaction and its unit conversions.

One full-duplex transfer per tick (1 MHz, MSB first, SPI mode 2, as Quanser's
Arduino sample code for the QUBE-Servo 2 does it). Multi-byte fields are big-endian here, unlike the host protocol.

Bytes the bridge (master) sends::

    0 mode (1)   1 zero   2 write mask   3-4 LED red   5-6 LED green
    7-8 LED blue   9-11 encoder 0 preset   12-14 encoder 1 preset
    15-16 motor command (bit 15 amplifier enable, bits 14-0 signed PWM)

Bytes the QUBE (slave) returns in the same transfer::

    0-1 module id (777)   2-4 encoder 0   5-7 encoder 1   8-10 tachometer
    11 status   12-13 current sense   14-16 unused

The firmware packs commands and unpacks responses (``c/src/qp_qube.c``);
these Python functions do both directions, so an emulated QUBE can answer
the firmware core and tests can check the C code byte for byte.
"""

from __future__ import annotations

from dataclasses import dataclass

from .messages import LED_MAX, MAX_MILLIVOLTS

__all__ = [
    "SPI_SIZE",
    "SPI_MODE_BYTE",
    "MASK_MOTOR",
    "MASK_LED",
    "MASK_ENCODER0",
    "MASK_ENCODER1",
    "MASK_NORMAL",
    "MOTOR_ENABLE",
    "MILLIVOLTS_PER_PWM",
    "SpiCommand",
    "SpiResponse",
    "pack_spi_command",
    "unpack_spi_command",
    "pack_spi_response",
    "unpack_spi_response",
    "motor_word",
    "motor_word_pwm",
    "current_amps",
    "counts_to_radians",
]

SPI_SIZE = 17
SPI_MODE_BYTE = 1
MASK_MOTOR = 0b0000_0011
MASK_LED = 0b0001_1100
MASK_ENCODER0 = 0b0010_0000
MASK_ENCODER1 = 0b0100_0000
MASK_NORMAL = MASK_MOTOR | MASK_LED
MOTOR_ENABLE = 0x8000
# Quanser scales volts by 625/15 PWM counts per volt: 24 mV per count.
MILLIVOLTS_PER_PWM = 24
ENCODER_COUNTS_PER_REV = 2048

_U24 = 0xFFFFFF


def _sign24(value: int) -> int:
    return ((value & _U24) ^ 0x800000) - 0x800000


@dataclass(frozen=True)
class SpiCommand:
    """What the bridge writes to the QUBE in one transaction."""

    write_mask: int = MASK_NORMAL
    led_red: int = 0
    led_green: int = 0
    led_blue: int = 0
    encoder0_preset: int = 0
    encoder1_preset: int = 0
    motor: int = 0


@dataclass(frozen=True)
class SpiResponse:
    """What the QUBE returns in one transaction (encoders sign-extended)."""

    module_id: int = 777
    encoder0: int = 0
    encoder1: int = 0
    tach_raw: int = 0
    status: int = 0
    current_raw: int = 0


def _check(name: str, value: int, low: int, high: int) -> None:
    if not isinstance(value, int) or isinstance(value, bool) or not low <= value <= high:
        raise ValueError(f"{name} = {value!r} is outside [{low}, {high}]")


# One table per direction, used by both pack and unpack so they cannot
# disagree: (field, byte offset, width in bytes, signed, accepted range).
_COMMAND_LAYOUT = (
    ("write_mask", 2, 1, False, (0, 0x7F)),
    ("led_red", 3, 2, False, (0, LED_MAX)),
    ("led_green", 5, 2, False, (0, LED_MAX)),
    ("led_blue", 7, 2, False, (0, LED_MAX)),
    ("encoder0_preset", 9, 3, True, (-0x800000, 0x7FFFFF)),
    ("encoder1_preset", 12, 3, True, (-0x800000, 0x7FFFFF)),
    ("motor", 15, 2, False, (0, 0xFFFF)),
)
# Encoder counts wider than 24 bits are accepted and wrap, as the QUBE's
# counters do, so an emulated QUBE can hand over its unbounded counts.
_RESPONSE_LAYOUT = (
    ("module_id", 0, 2, False, (0, 0xFFFF)),
    ("encoder0", 2, 3, True, (-(1 << 31), (1 << 31) - 1)),
    ("encoder1", 5, 3, True, (-(1 << 31), (1 << 31) - 1)),
    ("tach_raw", 8, 3, False, (0, _U24)),
    ("status", 11, 1, False, (0, 0xFF)),
    ("current_raw", 12, 2, False, (0, 0xFFFF)),
)


def _pack(obj, layout, head: bytes) -> bytes:
    out = bytearray(SPI_SIZE)
    out[: len(head)] = head
    for name, offset, width, _, (low, high) in layout:
        value = getattr(obj, name)
        _check(name, value, low, high)
        out[offset : offset + width] = (value & ((1 << 8 * width) - 1)).to_bytes(width, "big")
    return bytes(out)


def _unpack(cls, layout, data: bytes):
    if len(data) != SPI_SIZE:
        raise ValueError(f"an SPI transaction is {SPI_SIZE} bytes, got {len(data)}")
    values = {}
    for name, offset, width, signed, _ in layout:
        value = int.from_bytes(data[offset : offset + width], "big")
        values[name] = _sign24(value) if signed else value
    return cls(**values)


def pack_spi_command(cmd: SpiCommand) -> bytes:
    """The 17 bytes the bridge sends.

    Raises
    ------
    ValueError
        If a field does not fit its bits (presets are 24-bit signed, LEDs 0..999).
    """
    return _pack(cmd, _COMMAND_LAYOUT, bytes((SPI_MODE_BYTE, 0)))


def unpack_spi_command(data: bytes) -> SpiCommand:
    """Read the bridge's 17 bytes (as an emulated QUBE does); no range checks.

    Raises
    ------
    ValueError
        If ``data`` is not 17 bytes.
    """
    return _unpack(SpiCommand, _COMMAND_LAYOUT, data)


def pack_spi_response(resp: SpiResponse) -> bytes:
    """The 17 bytes a QUBE returns (for an emulated QUBE); bytes 14-16 are zero.

    Raises
    ------
    ValueError
        If a field is not an integer or does not fit its bits.
    """
    return _pack(resp, _RESPONSE_LAYOUT, b"")


def unpack_spi_response(data: bytes) -> SpiResponse:
    """Read a QUBE's 17 bytes; encoders are sign-extended from 24 bits.

    Raises
    ------
    ValueError
        If ``data`` is not 17 bytes.
    """
    return _unpack(SpiResponse, _RESPONSE_LAYOUT, data)


def motor_word_pwm(millivolts: int) -> int:
    """Signed PWM count for a voltage: ``millivolts / 24`` rounded half away from zero.

    ``millivolts`` is clamped to +-15000 first, so the result is within +-625
    (15 V, where Quanser's own code saturates).
    """
    mv = max(-MAX_MILLIVOLTS, min(MAX_MILLIVOLTS, int(millivolts)))
    pwm = (abs(mv) + MILLIVOLTS_PER_PWM // 2) // MILLIVOLTS_PER_PWM
    return pwm if mv >= 0 else -pwm


def motor_word(millivolts: int, enable: bool) -> int:
    """The 16-bit motor command: enable bit 15 and 15-bit two's complement PWM.

    A disabled amplifier gets the word 0 whatever the voltage: bit 15 clear
    is also what clears the QUBE's latched stall error.
    """
    if not enable:
        return 0
    return MOTOR_ENABLE | (motor_word_pwm(millivolts) & 0x7FFF)


def current_amps(current_raw: int) -> float:
    """Motor current in amperes: ``(3.3 / (4 * 4095)) * (raw / 2 - 4095)`` (Quanser's sample code)."""
    return (3.3 / (4 * 4095)) * (current_raw / 2 - 4095)


def counts_to_radians(counts: int) -> float:
    """Encoder counts to radians (2048 counts per revolution)."""
    return counts * (2.0 * 3.141592653589793 / ENCODER_COUNTS_PER_REV)
