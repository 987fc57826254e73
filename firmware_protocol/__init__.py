"""Wire protocol between the host and the QUBE-Servo bridge firmware.

Version 1: COBS-framed, little-endian binary frames with a CRC-16/CCITT-FALSE
trailer (PROTOCOL.md is the specification). This package holds the Python
codec (``encode_frame``, ``StreamDecoder``), the message classes, the
QUBE-Servo 2 SPI transaction (``qube_spi``), the golden test vectors shared
with the C codec, and the C codec and firmware core in ``c/`` (built and
loaded through ``firmware_protocol.ccore``). Standard library only.
"""

from .cobs import CobsError, cobs_decode, cobs_encode
from .crc import crc16_ccitt_false
from .decoder import DecoderStats, StreamDecoder
from .frame import Frame, Reject, encode_frame, encode_raw_frame, parse_piece
from .messages import (
    MESSAGE_CLASSES,
    PROTOCOL_VERSION,
    Capability,
    Command,
    CommandFlags,
    Config,
    ConfigAck,
    ConfigResult,
    Fault,
    FaultCode,
    Hello,
    HelloReply,
    Message,
    MessageType,
    Status,
    Telemetry,
)

__all__ = [
    "PROTOCOL_VERSION",
    "MESSAGE_CLASSES",
    "Capability",
    "CobsError",
    "Command",
    "CommandFlags",
    "Config",
    "ConfigAck",
    "ConfigResult",
    "DecoderStats",
    "Fault",
    "FaultCode",
    "Frame",
    "Hello",
    "HelloReply",
    "Message",
    "MessageType",
    "Reject",
    "Status",
    "StreamDecoder",
    "Telemetry",
    "cobs_decode",
    "cobs_encode",
    "crc16_ccitt_false",
    "encode_frame",
    "encode_raw_frame",
    "parse_piece",
]
