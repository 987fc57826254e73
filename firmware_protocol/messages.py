"""Message types of protocol version 1 and their fixed little-endian payloads.

Each message is a frozen dataclass whose fields, in declaration order, are
the payload's fields; its ``LAYOUT`` names the ``struct`` code of each field
and any range narrower than the code's own. ``pack`` checks every field and
raises ``ValueError`` naming the bad one; ``unpack`` never checks ranges, so
a decoder can hand over whatever a peer sent (the device clamps what it
applies). PROTOCOL.md is the normative description; the tables here and in
``c/src/qp_protocol.h`` must agree with it.
"""

from __future__ import annotations

import struct
from dataclasses import Field, dataclass, fields
from enum import IntEnum, IntFlag
from typing import Any, ClassVar, TypeVar

__all__ = [
    "PROTOCOL_VERSION",
    "MAX_PAYLOAD",
    "FIRMWARE_VERSION",
    "MODULE_ID_QUBE_SERVO_2",
    "MAX_MILLIVOLTS",
    "LED_MAX",
    "DEFAULT_RATE_HZ",
    "DEFAULT_WATCHDOG_TICKS",
    "COMMAND_FLAGS_MASK",
    "MessageType",
    "Capability",
    "CommandFlags",
    "Status",
    "FaultCode",
    "ConfigResult",
    "Message",
    "Hello",
    "HelloReply",
    "Config",
    "ConfigAck",
    "Command",
    "Telemetry",
    "Fault",
    "MESSAGE_CLASSES",
    "config_problem",
]

PROTOCOL_VERSION = 1
# Version 1 payloads fit in 64 bytes, so the firmware's buffers stay small
# enough for an 8-bit AVR with 2 KiB of RAM.
MAX_PAYLOAD = 64
FIRMWARE_VERSION = (1, 0, 0)
MODULE_ID_QUBE_SERVO_2 = 777
# The QUBE-Servo 2 amplifier saturates at 15 V (Quanser's sample code scales volts by 625/15 to
# a PWM of +-999, 100 % of 24 V, and clamps at +-15 V; the paper's rig stayed within +-10 V).
MAX_MILLIVOLTS = 15000
LED_MAX = 999

DEFAULT_RATE_HZ = 500
DEFAULT_WATCHDOG_TICKS = 5
RATE_HZ_RANGE = (10, 1000)
WATCHDOG_TICKS_RANGE = (1, 1000)


class MessageType(IntEnum):
    """Frame type byte; bit 7 set means device to host."""

    HELLO = 0x01
    CONFIG = 0x02
    COMMAND = 0x03
    HELLO_REPLY = 0x81
    CONFIG_ACK = 0x82
    TELEMETRY = 0x83
    FAULT = 0x84


class Capability(IntFlag):
    """Bits of ``HelloReply.capabilities``."""

    TELEMETRY = 1 << 0
    WATCHDOG = 1 << 1
    ENCODER_RESET = 1 << 2
    LED = 1 << 3
    CURRENT_SENSE = 1 << 4
    TACHOMETER = 1 << 5
    CONFIGURABLE_RATE = 1 << 6
    EMULATED = 1 << 7  # the firmware core runs in a simulator, not on a board


class CommandFlags(IntFlag):
    """Bits of ``Command.flags``."""

    AMP_ENABLE = 1 << 0
    RESET_ENCODER0 = 1 << 1
    RESET_ENCODER1 = 1 << 2


COMMAND_FLAGS_MASK = 0x07  # bits 3-7 of Command.flags are reserved (zero)


class Status(IntFlag):
    """Bits of ``Telemetry.status``; bits 0-2 are the QUBE-Servo 2's own status byte."""

    AMP_FAULT = 1 << 0
    STALL_DETECTED = 1 << 1
    STALL_ERROR = 1 << 2
    WATCHDOG_TRIPPED = 1 << 3
    AMP_ENABLED = 1 << 4
    SATURATED = 1 << 5
    BAD_MODULE_ID = 1 << 6
    TICK_OVERRUN = 1 << 7
    ENCODER_RESET = 1 << 8
    TX_OVERFLOW = 1 << 9


class FaultCode(IntEnum):
    """``Fault.code``: what happened; ``Fault.value`` carries the detail named here."""

    WATCHDOG_TRIPPED = 1  # value: the watchdog timeout in ticks
    AMP_FAULT = 2  # value: the QUBE status byte
    STALL_ERROR = 3  # value: the QUBE status byte
    BAD_MODULE_ID = 4  # value: the module id read over SPI
    TICK_OVERRUN = 5  # value: periods missed
    BAD_VERSION = 6  # value: the protocol version of the rejected frame
    NOT_CONNECTED = 7  # value: the type of the frame that came before HELLO
    RX_ERRORS = 8  # value: the device's total count of rejected frames


class ConfigResult(IntEnum):
    """``ConfigAck.result``."""

    OK = 0
    BAD_RATE = 1
    BAD_WATCHDOG = 2
    BAD_VOLTAGE = 3


_CODE_RANGES = {
    "B": (0, 0xFF),
    "H": (0, 0xFFFF),
    "h": (-0x8000, 0x7FFF),
    "I": (0, 0xFFFFFFFF),
    "i": (-0x80000000, 0x7FFFFFFF),
}


_M = TypeVar("_M", bound="Message")


class Message:
    """Base of all messages: packing driven by the subclass's ``LAYOUT``."""

    TYPE: ClassVar[MessageType]
    # (struct code, narrower (low, high) or None) per dataclass field, in order.
    LAYOUT: ClassVar[tuple[tuple[str, tuple[int, int] | None], ...]]
    STRUCT: ClassVar[struct.Struct]
    SIZE: ClassVar[int]
    # Every subclass is a dataclass (the base is not: it has no fields); declared so that fields() accepts one.
    __dataclass_fields__: ClassVar[dict[str, Field[Any]]]

    def __init_subclass__(cls, **kwargs) -> None:
        super().__init_subclass__(**kwargs)
        cls.STRUCT = struct.Struct("<" + "".join(code for code, _ in cls.LAYOUT))
        cls.SIZE = cls.STRUCT.size

    def pack(self) -> bytes:
        """The payload bytes.

        Raises
        ------
        ValueError
            If a field is not an integer or is outside its range.
        """
        values = []
        for field, (code, narrow) in zip(fields(self), self.LAYOUT):
            value = getattr(self, field.name)
            if not isinstance(value, int) or isinstance(value, bool):
                raise ValueError(f"{type(self).__name__}.{field.name} must be an integer, got {value!r}")
            low, high = narrow or _CODE_RANGES[code]
            if not low <= value <= high:
                raise ValueError(f"{type(self).__name__}.{field.name} = {value} is outside [{low}, {high}]")
            values.append(value)
        self._check()
        return self.STRUCT.pack(*values)

    def _check(self) -> None:
        """Cross-field checks beyond per-field ranges (none by default)."""

    @classmethod
    def field_ranges(cls) -> dict[str, tuple[int, int]]:
        """Inclusive (low, high) that ``pack`` accepts for each field, in payload order."""
        return {f.name: narrow or _CODE_RANGES[code] for f, (code, narrow) in zip(fields(cls), cls.LAYOUT)}

    @classmethod
    def unpack(cls: type[_M], payload: bytes | bytearray | memoryview) -> _M:
        """Rebuild a message from exactly ``SIZE`` payload bytes (no range checks).

        Raises
        ------
        ValueError
            If the payload does not have exactly ``SIZE`` bytes.
        """
        if len(payload) != cls.SIZE:
            raise ValueError(f"{cls.__name__} payload must be {cls.SIZE} bytes, got {len(payload)}")
        return cls(*cls.STRUCT.unpack(payload))


@dataclass(frozen=True)
class Hello(Message):
    """Host to device: open a session. The device answers with ``HelloReply``.

    A HELLO resets the session: amplifier off, watchdog disarmed and cleared,
    tick counter zero, then telemetry every tick.

    Parameters
    ----------
    nonce : int
        Echoed in the reply, to pair them.
    """

    TYPE: ClassVar[MessageType] = MessageType.HELLO
    LAYOUT: ClassVar = (("I", None),)

    nonce: int = 0


@dataclass(frozen=True)
class HelloReply(Message):
    """Device to host: versions, capabilities and the current configuration.

    Parameters
    ----------
    nonce : int
        The HELLO's.
    protocol_version : int
        The protocol the firmware speaks.
    firmware_major, firmware_minor, firmware_patch : int
        The firmware's version.
    capabilities : int
        :class:`Capability` bits.
    rate_hz, watchdog_ticks, max_millivolts : int
        The configuration in force.
    module_id : int
        The last module id read over SPI (777 for a QUBE-Servo 2; 0 before the first tick).
    """

    TYPE: ClassVar[MessageType] = MessageType.HELLO_REPLY
    LAYOUT: ClassVar = (
        ("I", None),
        ("B", None),
        ("B", None),
        ("B", None),
        ("B", None),
        ("I", None),
        ("H", None),
        ("H", None),
        ("H", None),
        ("H", None),
    )

    nonce: int = 0
    protocol_version: int = PROTOCOL_VERSION
    firmware_major: int = FIRMWARE_VERSION[0]
    firmware_minor: int = FIRMWARE_VERSION[1]
    firmware_patch: int = FIRMWARE_VERSION[2]
    capabilities: int = 0
    rate_hz: int = DEFAULT_RATE_HZ
    watchdog_ticks: int = DEFAULT_WATCHDOG_TICKS
    max_millivolts: int = MAX_MILLIVOLTS
    module_id: int = 0


def config_problem(rate_hz: int, watchdog_ticks: int, max_millivolts: int) -> ConfigResult:
    """Why the device would refuse a configuration (``ConfigResult.OK`` if it would not).

    The tick period must be a whole number of microseconds, so ``rate_hz``
    must divide 1,000,000.
    """
    if not (RATE_HZ_RANGE[0] <= rate_hz <= RATE_HZ_RANGE[1]) or 1_000_000 % rate_hz:
        return ConfigResult.BAD_RATE
    if not WATCHDOG_TICKS_RANGE[0] <= watchdog_ticks <= WATCHDOG_TICKS_RANGE[1]:
        return ConfigResult.BAD_WATCHDOG
    if not 0 <= max_millivolts <= MAX_MILLIVOLTS:
        return ConfigResult.BAD_VOLTAGE
    return ConfigResult.OK


@dataclass(frozen=True)
class Config(Message):
    """Host to device: tick rate, watchdog timeout and voltage limit.

    The device answers with ``ConfigAck``; a refused configuration changes
    nothing.

    Parameters
    ----------
    rate_hz : int
        Tick rate, 10-1000 Hz and dividing 1,000,000 (a whole period in µs).
    watchdog_ticks : int
        Ticks without a command before the amplifier is switched off, 1-1000.
    max_millivolts : int
        Voltage limit, 0-15000 mV: commands beyond it are clamped.
    """

    TYPE: ClassVar[MessageType] = MessageType.CONFIG
    LAYOUT: ClassVar = (("H", RATE_HZ_RANGE), ("H", WATCHDOG_TICKS_RANGE), ("H", (0, MAX_MILLIVOLTS)))

    rate_hz: int = DEFAULT_RATE_HZ
    watchdog_ticks: int = DEFAULT_WATCHDOG_TICKS
    max_millivolts: int = MAX_MILLIVOLTS

    def _check(self) -> None:
        if config_problem(self.rate_hz, self.watchdog_ticks, self.max_millivolts) is ConfigResult.BAD_RATE:
            raise ValueError(
                f"Config.rate_hz = {self.rate_hz} does not divide 1000000 (the tick period must be whole microseconds)"
            )


@dataclass(frozen=True)
class ConfigAck(Message):
    """Device to host: the result of a ``Config`` and the configuration now in force.

    Parameters
    ----------
    result : int
        :class:`ConfigResult`: OK, or the first problem found.
    rate_hz, watchdog_ticks, max_millivolts : int
        The configuration in force after the request.
    """

    TYPE: ClassVar[MessageType] = MessageType.CONFIG_ACK
    LAYOUT: ClassVar = (("B", None), ("H", None), ("H", None), ("H", None))

    result: int = ConfigResult.OK
    rate_hz: int = DEFAULT_RATE_HZ
    watchdog_ticks: int = DEFAULT_WATCHDOG_TICKS
    max_millivolts: int = MAX_MILLIVOLTS


@dataclass(frozen=True)
class Command(Message):
    """Host to device: the motor voltage and outputs to apply at the next tick.

    The command's sequence number is its frame's ``seq``. Encoder resets are
    one-shot: they are applied at the next tick only.

    Parameters
    ----------
    millivolts : int
        Motor voltage, -15000..15000 mV.
    flags : int
        :class:`CommandFlags`: amplifier enable, encoder 0 reset, encoder 1 reset.
    led_red, led_green, led_blue : int
        LED colour, 0-999 each.
    """

    TYPE: ClassVar[MessageType] = MessageType.COMMAND
    LAYOUT: ClassVar = (
        ("h", (-MAX_MILLIVOLTS, MAX_MILLIVOLTS)),
        ("B", (0, COMMAND_FLAGS_MASK)),
        ("H", (0, LED_MAX)),
        ("H", (0, LED_MAX)),
        ("H", (0, LED_MAX)),
    )

    millivolts: int = 0
    flags: int = 0
    led_red: int = 0
    led_green: int = 0
    led_blue: int = 0


@dataclass(frozen=True)
class Telemetry(Message):
    """Device to host, every tick: what was measured and what was applied.

    Parameters
    ----------
    tick : int
        Periods since the HELLO that opened the session (a gap counts lost periods).
    encoder0, encoder1 : int
        Motor (arm) and pendulum encoder counts, sign-extended from the QUBE's 24 bits.
    tach_raw : int
        The QUBE's raw 24-bit tachometer word.
    current_raw : int
        Raw current sense.
    status : int
        :class:`Status` bits.
    last_command_seq : int
        ``seq`` of the newest command received (0: none).
    applied_millivolts : int
        Voltage applied at this tick, after the limit and the watchdog.
    motor_word : int
        The 16-bit motor command sent to the QUBE at this tick.
    command_age : int
        Ticks since the newest command arrived; 0xFFFF: none yet in this session.
    """

    TYPE: ClassVar[MessageType] = MessageType.TELEMETRY
    LAYOUT: ClassVar = (
        ("I", None),
        ("i", None),
        ("i", None),
        ("I", (0, 0xFFFFFF)),
        ("H", None),
        ("H", None),
        ("I", None),
        ("h", None),
        ("H", None),
        ("H", None),
    )

    tick: int = 0
    encoder0: int = 0
    encoder1: int = 0
    tach_raw: int = 0
    current_raw: int = 0
    status: int = 0
    last_command_seq: int = 0
    applied_millivolts: int = 0
    motor_word: int = 0
    command_age: int = 0


@dataclass(frozen=True)
class Fault(Message):
    """Device to host: something went wrong (sent once, on the event).

    Parameters
    ----------
    code : int
        :class:`FaultCode`.
    tick : int
        The session's tick counter at the event.
    value : int
        Detail, per code (PROTOCOL.md).
    """

    TYPE: ClassVar[MessageType] = MessageType.FAULT
    LAYOUT: ClassVar = (("B", None), ("I", None), ("I", None))

    code: int = 0
    tick: int = 0
    value: int = 0


MESSAGE_CLASSES: dict[int, type[Message]] = {
    cls.TYPE: cls for cls in (Hello, HelloReply, Config, ConfigAck, Command, Telemetry, Fault)
}
