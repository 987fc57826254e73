"""Golden test vectors shared by the Python and C codecs.

``golden_vectors.json`` (next to this file) is the artifact both codecs are
tested against. Its sections and where their values come from:

- ``crc``, ``cobs``: published reference values (CRC catalogue check value;
  the examples of the COBS article on Wikipedia), each entry naming its source.
- ``motor_word``, ``spi_command``, ``spi_response``: bytes worked out by hand
  from the QUBE-Servo 2 SPI description of Quanser's Arduino sample code.
- ``frames``, ``rejects``, ``streams``: produced by the Python encoder when
  protocol version 1 was frozen. They pin the format down so that neither
  codec can drift; ``tests/firmware_protocol/test_protocol_codec.py`` also assembles one frame
  by hand from PROTOCOL.md to check the encoder that made them.

Regenerate only for a deliberate protocol change (with a version bump):
``python -m qube_koopman.firmware_protocol.vectors --write``. Without ``--write`` the
command reports whether the file is current.
"""

from __future__ import annotations

import argparse
import json
from dataclasses import asdict
from pathlib import Path

__all__ = ["VECTORS_PATH", "load_vectors", "build_vectors", "main"]

VECTORS_PATH = Path(__file__).resolve().parent / "golden_vectors.json"

_WIKI = "Wikipedia, 'Consistent Overhead Byte Stuffing', encoding examples"


def load_vectors(path: str | Path = VECTORS_PATH) -> dict:
    """The golden vectors as plain data."""
    return json.loads(Path(path).read_text(encoding="utf-8"))


def _crc_vectors() -> list[dict]:
    return [
        {
            "data_hex": b"123456789".hex(),
            "crc": 0x29B1,
            "source": "CRC-16/CCITT-FALSE check value (RevEng CRC catalogue; lammertbies.nl calculator)",
        },
        {"data_hex": "", "crc": 0xFFFF, "source": "no data leaves the initial value"},
        {"data_hex": b"A".hex(), "crc": 0xB915, "source": "bitwise shift-register definition"},
        {"data_hex": (b"A" * 256).hex(), "crc": 0xEA0B, "source": "bitwise shift-register definition"},
    ]


def _cobs_vectors() -> list[dict]:
    run = bytes(range(1, 255))
    examples = [
        ("00", "0101"),
        ("0000", "010101"),
        ("001100", "01021101"),
        ("11220033", "0311220233"),
        ("11223344", "0511223344"),
        ("11000000", "0211010101"),
        (run.hex(), "ff" + run.hex()),
        ((b"\0" + run).hex(), "01ff" + run.hex()),
        ((run + b"\xff").hex(), "ff" + run.hex() + "02ff"),
        ((run[1:] + b"\xff\0").hex(), "ff" + run[1:].hex() + "ff0101"),
        ((run[2:] + b"\xff\0\x01").hex(), "fe" + run[2:].hex() + "ff0201"),
    ]
    return [{"decoded_hex": d, "encoded_hex": e, "source": _WIKI} for d, e in examples]


def _motor_vectors() -> list[dict]:
    src = "PWM = mV * 625 / 15000 = mV / 24, rounded half away from zero, clamped to +-625 (15 V)"
    rows = [
        (10000, True, 0x81A1, "10 V: 416.67 -> 417 = 0x1A1, enable bit 15"),
        (-10000, True, 0xFE5F, "-10 V: -417, 15-bit two's complement 0x7E5F, enable bit 15"),
        (15000, True, 0x8271, "15 V: 625 = 0x271"),
        (20000, True, 0x8271, "above 15 V saturates at 625"),
        (-15000, True, 0xFD8F, "-625 = 0x7D8F in 15 bits"),
        (12, True, 0x8001, "0.5 count rounds away from zero"),
        (-12, True, 0xFFFF, "-0.5 count rounds away from zero: -1"),
        (11, True, 0x8000, "below half a count"),
        (0, True, 0x8000, "enabled at 0 V"),
        (5000, False, 0x0000, "disabled: word 0, also clears a stall error"),
    ]
    return [{"millivolts": mv, "enable": en, "word": w, "why": why, "source": src} for mv, en, w, why in rows]


def _spi_vectors() -> tuple[list[dict], list[dict]]:
    src = "Quanser QUBE-Servo 2 Arduino sample code: big-endian fields"
    commands = [
        (
            {
                "write_mask": 0x1F,
                "led_red": 999,
                "led_green": 0,
                "led_blue": 0,
                "encoder0_preset": 0,
                "encoder1_preset": 0,
                "motor": 0x8000,
            },
            "01001f03e7000000000000000000008000",
            "normal mask 0b00011111, red LED 999 = 0x03E7, enabled at 0 V",
        ),
        (
            {
                "write_mask": 0x7F,
                "led_red": 0,
                "led_green": 999,
                "led_blue": 0,
                "encoder0_preset": 0,
                "encoder1_preset": 0,
                "motor": 0x0000,
            },
            "01007f000003e700000000000000000000",
            "encoder reset mask 0b01111111, both presets 0, amplifier off",
        ),
        (
            {
                "write_mask": 0x1F,
                "led_red": 1,
                "led_green": 2,
                "led_blue": 3,
                "encoder0_preset": -1,
                "encoder1_preset": 0x123456,
                "motor": 0xFE5F,
            },
            "01001f000100020003ffffff123456fe5f",
            "preset -1 is 24-bit 0xFFFFFF; -10 V motor word",
        ),
    ]
    responses = [
        (
            "0309ffffff0008007fffff051ffe000000",
            {
                "module_id": 777,
                "encoder0": -1,
                "encoder1": 2048,
                "tach_raw": 0x7FFFFF,
                "status": 5,
                "current_raw": 8190,
            },
            "id 777 = 0x0309; 0xFFFFFF is -1; 2048 counts = one turn; status amp fault + stall error; "
            "current 8190 = 0 A",
        ),
        (
            "00008000007fffff000000000000000000",
            {"module_id": 0, "encoder0": -8388608, "encoder1": 8388607, "tach_raw": 0, "status": 0, "current_raw": 0},
            "24-bit extremes; id 0 (no QUBE answering)",
        ),
    ]
    return (
        [{"fields": f, "bytes_hex": b, "why": why, "source": src} for f, b, why in commands],
        [{"bytes_hex": b, "fields": f, "why": why, "source": src} for b, f, why in responses],
    )


def _frame_messages():
    from . import messages as m

    return [
        (m.Hello(nonce=0x12345678), 1, 1000),
        (m.Hello(), 0, 0),
        (m.HelloReply(nonce=0x12345678, capabilities=0x7F, module_id=777), 0, 0xFFFFFFFF),
        (m.Config(rate_hz=500, watchdog_ticks=5, max_millivolts=10000), 2, 2000),
        (m.Config(rate_hz=1000, watchdog_ticks=1000, max_millivolts=0), 0xFFFFFFFF, 1),
        (m.ConfigAck(result=m.ConfigResult.BAD_RATE), 3, 3000),
        (m.Command(millivolts=-10000, flags=m.CommandFlags.AMP_ENABLE, led_green=999), 7, 123456789),
        (m.Command(millivolts=15000, flags=7, led_red=999, led_green=999, led_blue=999), 0x01000000, 0),
        (m.Command(), 0, 0),
        (
            m.Telemetry(
                tick=42,
                encoder0=-1,
                encoder1=2048,
                tach_raw=0x7FFFFF,
                current_raw=8190,
                status=m.Status.AMP_ENABLED,
                last_command_seq=41,
                applied_millivolts=-2500,
                motor_word=0xFF98,
                command_age=1,
            ),
            43,
            84000,
        ),
        (
            m.Telemetry(
                tick=0xFFFFFFFF,
                encoder0=-(1 << 31),
                encoder1=(1 << 31) - 1,
                tach_raw=0xFFFFFF,
                current_raw=0xFFFF,
                status=0xFFFF,
                last_command_seq=0xFFFFFFFF,
                applied_millivolts=-32768,
                motor_word=0xFFFF,
                command_age=0xFFFF,
            ),
            0xFFFFFFFF,
            0xFFFFFFFF,
        ),
        (m.Telemetry(), 0, 0),
        (m.Fault(code=m.FaultCode.WATCHDOG_TRIPPED, tick=1000, value=5), 9, 2_000_000),
    ]


def _frame_vectors() -> list[dict]:
    from .frame import encode_frame

    out = []
    for msg, seq, ts in _frame_messages():
        out.append(
            {
                "message": type(msg).__name__,
                "type": int(msg.TYPE),
                "seq": seq,
                "timestamp_us": ts,
                "fields": {k: int(v) for k, v in asdict(msg).items()},
                "payload_hex": msg.pack().hex(),
                "wire_hex": encode_frame(msg, seq, ts).hex(),
            }
        )
    return out


def _reject_vectors() -> list[dict]:
    from .cobs import cobs_encode
    from .frame import HEADER, crc_trailer, encode_frame, encode_raw_frame
    from .messages import Hello, MessageType

    good = encode_frame(Hello(nonce=1), 5, 6)[:-1]
    flipped = bytearray(good)
    flipped[3] ^= 0x10
    bad_cobs_body = bytes((0x20,)) + bytes(range(1, 15))  # code 0x20 points past the end
    rows = [
        ("crc mismatch (one bit flipped)", bytes(flipped), "BAD_CRC"),
        ("trailer byte without bit 7", good[:-3] + bytes((good[-3] & 0x7F,)) + good[-2:], "BAD_CRC"),
        ("trailer third byte with bits 2-6 set", good[:-1] + bytes((good[-1] | 0x04,)), "BAD_CRC"),
        ("COBS code points past the end", bad_cobs_body + crc_trailer(bad_cobs_body), "BAD_COBS"),
        ("version 2", encode_raw_frame(MessageType.HELLO, 1, 2, b"\1\0\0\0", version=2)[:-1], "BAD_VERSION"),
        ("version 0", encode_raw_frame(MessageType.HELLO, 1, 2, b"\1\0\0\0", version=0)[:-1], "BAD_VERSION"),
        (
            "length field larger than payload",
            encode_raw_frame(MessageType.HELLO, 1, 2, b"\1\0\0\0", payload_len=5)[:-1],
            "BAD_LENGTH",
        ),
        ("payload size wrong for the type", encode_raw_frame(MessageType.HELLO, 1, 2, b"\1\0\0")[:-1], "BAD_LENGTH"),
        ("header cut short", _short_header(cobs_encode, crc_trailer), "BAD_LENGTH"),
        ("too short to be a frame", bytes((1, 0x81, 0x80)), "BAD_LENGTH"),
        ("unknown type 0x7F", encode_raw_frame(0x7F, 1, 2, b"")[:-1], "UNKNOWN_TYPE"),
        ("longer than the largest frame", b"\x01" * 80, "OVERSIZE"),
    ]
    assert HEADER.size == 11
    return [{"name": name, "piece_hex": piece.hex(), "reason": reason} for name, piece, reason in rows]


def _short_header(cobs_encode, crc_trailer) -> bytes:
    encoded = cobs_encode(bytes((1, 1, 0, 0, 0, 0, 0, 0, 0, 0)) + bytes(3))[:12]
    return encoded + crc_trailer(encoded)


def _stream_vectors() -> list[dict]:
    from .frame import encode_frame
    from .messages import Command, Hello, Telemetry

    a = encode_frame(Hello(nonce=1), 1, 10)
    b = encode_frame(Command(millivolts=500, flags=1), 2, 20)
    assert b[5] == 0x01  # a COBS code byte: one flip makes it a delimiter
    c = encode_frame(Telemetry(tick=3), 3, 30)
    rows = [
        ("garbage, then a delimiter, then frames", b"\x13\x37\xff\x00" + a + b, [a, b], {"bad_length": 1}),
        ("frame glued to preceding garbage is lost, next one survives", b"\x55\x66" + a + c, [c], {"bad_crc": 1}),
        ("extra delimiters are idle fill", b"\x00\x00" + a + b"\x00\x00\x00" + c, [a, c], {}),
        ("oversize run then resync", b"\x7e" * 300 + b"\x00" + b, [b], {"oversize": 1}),
        ("corrupted frame between good ones", a + b[:5] + bytes((b[5] ^ 0x02,)) + b[6:] + c, [a, c], {"bad_crc": 1}),
        (
            "a flip that makes a 0x00 splits the frame; both halves rejected",
            a + b[:5] + bytes((b[5] ^ 0x01,)) + b[6:] + c,
            [a, c],
            {"bad_length": 1, "bad_crc": 1},
        ),
        ("truncated frame at the end stays pending", a + c[:-7], [a], {}),
    ]
    out = []
    for name, stream, frames, counters in rows:
        expected = {
            "frames": len(frames),
            "bad_crc": 0,
            "bad_cobs": 0,
            "bad_length": 0,
            "bad_version": 0,
            "unknown_type": 0,
            "oversize": 0,
        }
        expected.update(counters)
        out.append(
            {"name": name, "stream_hex": stream.hex(), "frames_hex": [f.hex() for f in frames], "counters": expected}
        )
    return out


def build_vectors() -> dict:
    """The full vectors document, as the current Python codec produces it."""
    from .messages import PROTOCOL_VERSION

    commands, responses = _spi_vectors()
    return {
        "description": "Golden vectors of the host <-> QUBE bridge protocol; see firmware_protocol/vectors.py",
        "protocol_version": PROTOCOL_VERSION,
        "crc": _crc_vectors(),
        "cobs": _cobs_vectors(),
        "motor_word": _motor_vectors(),
        "spi_command": commands,
        "spi_response": responses,
        "frames": _frame_vectors(),
        "rejects": _reject_vectors(),
        "streams": _stream_vectors(),
    }


def _dump(doc: dict) -> str:
    return json.dumps(doc, indent=1) + "\n"


def main(argv: list[str] | None = None) -> int:
    """Check (default) or rewrite (``--write``) ``golden_vectors.json``."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--write", action="store_true", help="rewrite the file (protocol changes only)")
    args = parser.parse_args(argv)
    text = _dump(build_vectors())
    if args.write:
        VECTORS_PATH.write_text(text, encoding="utf-8")
        print(f"wrote {VECTORS_PATH}")
        return 0
    current = VECTORS_PATH.exists() and VECTORS_PATH.read_text(encoding="utf-8") == text
    print(f"{VECTORS_PATH} is {'current' if current else 'DIFFERENT from what the codec produces'}")
    return 0 if current else 1


if __name__ == "__main__":
    raise SystemExit(main())
