"""Python codec of the bridge protocol: CRC, COBS, messages, frames, SPI packing.

Reference values come from outside the code under test: the CRC catalogue's
check value and a textbook bitwise CRC, the COBS examples on Wikipedia, SPI
bytes worked out by hand (golden_vectors.json), and one frame assembled here
byte by byte from PROTOCOL.md.
"""

from __future__ import annotations

import struct

import pytest
from hypothesis import given
from hypothesis import strategies as st

from qube_koopman.firmware_protocol import (
    MESSAGE_CLASSES,
    CobsError,
    Command,
    CommandFlags,
    Config,
    Fault,
    Frame,
    Hello,
    Reject,
    Telemetry,
    cobs_decode,
    cobs_encode,
    crc16_ccitt_false,
    encode_frame,
    encode_raw_frame,
    parse_piece,
)
from qube_koopman.firmware_protocol.frame import MAX_WIRE_SIZE, MIN_WIRE_SIZE
from qube_koopman.firmware_protocol.messages import MAX_PAYLOAD, config_problem, ConfigResult
from qube_koopman.firmware_protocol.qube_spi import (
    SpiCommand,
    SpiResponse,
    current_amps,
    motor_word,
    pack_spi_command,
    pack_spi_response,
    unpack_spi_command,
    unpack_spi_response,
)
from qube_koopman.firmware_protocol.vectors import load_vectors

VECTORS = load_vectors()


def crc_bitwise(data: bytes) -> int:
    """CRC-16/CCITT-FALSE straight from its definition: MSB-first shift register."""
    crc = 0xFFFF
    for byte in data:
        for bit in range(7, -1, -1):
            feedback = ((crc >> 15) & 1) ^ ((byte >> bit) & 1)
            crc = ((crc << 1) & 0xFFFF) ^ (0x1021 if feedback else 0)
    return crc


# --- CRC --------------------------------------------------------------------


def test_crc_check_value():
    assert crc16_ccitt_false(b"123456789") == 0x29B1


@pytest.mark.parametrize("vector", VECTORS["crc"], ids=lambda v: v["source"][:30])
def test_crc_vectors(vector):
    data = bytes.fromhex(vector["data_hex"])
    assert crc16_ccitt_false(data) == vector["crc"]
    assert crc_bitwise(data) == vector["crc"]


@given(st.binary(max_size=300), st.binary(max_size=50))
def test_crc_matches_bitwise_definition_and_continues(a, b):
    assert crc16_ccitt_false(a + b) == crc_bitwise(a + b)
    assert crc16_ccitt_false(b, crc16_ccitt_false(a)) == crc16_ccitt_false(a + b)


# --- COBS -------------------------------------------------------------------


@pytest.mark.parametrize("vector", VECTORS["cobs"], ids=lambda v: v["decoded_hex"][:12])
def test_cobs_wikipedia_examples(vector):
    decoded, encoded = bytes.fromhex(vector["decoded_hex"]), bytes.fromhex(vector["encoded_hex"])
    assert cobs_encode(decoded) == encoded
    assert cobs_decode(encoded) == decoded


@given(st.binary(max_size=1200))
def test_cobs_round_trip_has_no_zero_and_bounded_overhead(data):
    encoded = cobs_encode(data)
    assert 0 not in encoded
    assert len(encoded) <= len(data) + len(data) // 254 + 1
    assert cobs_decode(encoded) == data


@pytest.mark.parametrize("bad", [b"\x05\x11\x22", b"\x02\x00", b"\x00", b"\x03\x11"])
def test_cobs_decode_rejects_invalid(bad):
    with pytest.raises(CobsError):
        cobs_decode(bad)


# --- messages ---------------------------------------------------------------


def test_payload_sizes_match_the_spec():
    # PROTOCOL.md, "Messages": the payload size of every type.
    sizes = {cls.__name__: cls.SIZE for cls in MESSAGE_CLASSES.values()}
    assert sizes == {
        "Hello": 4,
        "HelloReply": 20,
        "Config": 6,
        "ConfigAck": 7,
        "Command": 9,
        "Telemetry": 30,
        "Fault": 9,
    }
    assert max(sizes.values()) <= MAX_PAYLOAD


def test_telemetry_layout_is_little_endian_in_field_order():
    t = Telemetry(
        tick=0x01020304,
        encoder0=-2,
        encoder1=0x0A0B0C0D,
        tach_raw=0x123456,
        current_raw=0x1FFE,
        status=0x0210,
        last_command_seq=0xA1B2C3D4,
        applied_millivolts=-1,
        motor_word=0x81A1,
        command_age=3,
    )
    expected = (
        bytes.fromhex("04030201")
        + bytes.fromhex("feffffff")
        + bytes.fromhex("0d0c0b0a")
        + bytes.fromhex("56341200")
        + bytes.fromhex("fe1f")
        + bytes.fromhex("1002")
        + bytes.fromhex("d4c3b2a1")
        + bytes.fromhex("ffff")
        + bytes.fromhex("a181")
        + bytes.fromhex("0300")
    )
    assert t.pack() == expected
    assert Telemetry.unpack(expected) == t


@pytest.mark.parametrize(
    "message, field",
    [
        (Command(millivolts=15001), "millivolts"),
        (Command(millivolts=-15001), "millivolts"),
        (Command(led_red=1000), "led_red"),
        (Command(flags=0x08), "flags"),
        (Config(rate_hz=2000), "rate_hz"),
        (Config(rate_hz=300), "rate_hz"),  # 1e6 / 300 is not whole microseconds
        (Config(watchdog_ticks=0), "watchdog_ticks"),
        (Config(max_millivolts=16000), "max_millivolts"),
        (Hello(nonce=-1), "nonce"),
        (Hello(nonce=1 << 32), "nonce"),
        (Hello(nonce=1.0), "nonce"),
        (Hello(nonce=True), "nonce"),
        (Telemetry(tach_raw=1 << 24), "tach_raw"),
        (Fault(code=256), "code"),
    ],
)
def test_pack_rejects_bad_fields_naming_them(message, field):
    with pytest.raises(ValueError, match=field):
        message.pack()


def test_config_problem_agrees_with_pack():
    assert config_problem(500, 5, 15000) is ConfigResult.OK
    assert config_problem(300, 5, 15000) is ConfigResult.BAD_RATE
    assert config_problem(500, 0, 15000) is ConfigResult.BAD_WATCHDOG
    assert config_problem(500, 5, 15001) is ConfigResult.BAD_VOLTAGE


def test_unpack_rejects_wrong_size():
    with pytest.raises(ValueError, match="9 bytes"):
        Command.unpack(b"\0" * 8)


# --- frames -----------------------------------------------------------------


def test_frame_assembled_by_hand_from_the_spec():
    """HELLO, seq 1, timestamp 1000, nonce 0x12345678, built from PROTOCOL.md alone."""
    body = bytes([1, 0x01]) + (1).to_bytes(4, "little") + (1000).to_bytes(4, "little") + bytes([4])
    body += bytes.fromhex("78563412")
    # COBS by hand: zeros at body offsets 3, 4, 5, 8, 9 leave the runs
    # [01 01 01] [] [] [e8 03] [] [04 78 56 34 12], each coded as its length + 1.
    encoded = bytes.fromhex("04010101010103e80301060478563412")
    assert cobs_decode(encoded) == body
    crc = crc_bitwise(encoded)
    trailer = bytes([0x80 | (crc & 0x7F), 0x80 | ((crc >> 7) & 0x7F), 0x80 | (crc >> 14)])
    assert encode_frame(Hello(nonce=0x12345678), seq=1, timestamp_us=1000) == encoded + trailer + b"\0"


@pytest.mark.parametrize("vector", VECTORS["frames"], ids=lambda v: v["message"])
def test_golden_frames_encode_and_decode(vector):
    cls = MESSAGE_CLASSES[vector["type"]]
    message = cls(**vector["fields"])
    wire = bytes.fromhex(vector["wire_hex"])
    assert message.pack().hex() == vector["payload_hex"]
    assert encode_frame(message, vector["seq"], vector["timestamp_us"]) == wire
    assert wire[-1] == 0 and 0 not in wire[:-1]
    assert parse_piece(wire[:-1]) == Frame(message, vector["seq"], vector["timestamp_us"])


@pytest.mark.parametrize("vector", VECTORS["rejects"], ids=lambda v: v["name"])
def test_golden_rejects(vector):
    assert parse_piece(bytes.fromhex(vector["piece_hex"])) is Reject[vector["reason"]]


def test_telemetry_frame_is_46_bytes_on_the_wire():
    # PROTOCOL.md's bandwidth figure: 46 bytes x 500 Hz = 23 kB/s.
    assert len(encode_frame(Telemetry(), 0, 0)) == 46


def test_wire_size_bounds():
    assert MIN_WIRE_SIZE == len(encode_raw_frame(0x7F, 0, 0, b"")) - 1
    assert MAX_WIRE_SIZE == len(encode_raw_frame(0x7F, 0, 0, b"\1" * MAX_PAYLOAD)) - 1


@pytest.mark.parametrize(
    "kwargs, name",
    [
        ({"seq": -1, "timestamp_us": 0}, "seq"),
        ({"seq": 1 << 32, "timestamp_us": 0}, "seq"),
        ({"seq": 0, "timestamp_us": 1 << 32}, "timestamp_us"),
        ({"seq": 0, "timestamp_us": 0.5}, "timestamp_us"),
    ],
)
def test_encode_frame_rejects_bad_header_fields(kwargs, name):
    with pytest.raises(ValueError, match=name):
        encode_frame(Hello(), **kwargs)


def test_encode_frame_rejects_non_messages_and_long_payloads():
    with pytest.raises(ValueError, match="message"):
        encode_frame(b"\x01", 0, 0)
    with pytest.raises(ValueError, match="payload"):
        encode_raw_frame(1, 0, 0, b"\0" * (MAX_PAYLOAD + 1))
    with pytest.raises(ValueError, match="version"):
        encode_raw_frame(1, 0, 0, b"", version=256)


# --- QUBE-Servo 2 SPI transaction ---------------------------------------------


@pytest.mark.parametrize("vector", VECTORS["motor_word"], ids=lambda v: v["why"][:25])
def test_motor_word_vectors(vector):
    assert motor_word(vector["millivolts"], vector["enable"]) == vector["word"]


@pytest.mark.parametrize("vector", VECTORS["spi_command"], ids=lambda v: v["why"][:25])
def test_spi_command_vectors(vector):
    cmd = SpiCommand(**vector["fields"])
    assert pack_spi_command(cmd).hex() == vector["bytes_hex"]
    assert unpack_spi_command(bytes.fromhex(vector["bytes_hex"])) == cmd


@pytest.mark.parametrize("vector", VECTORS["spi_response"], ids=lambda v: v["why"][:25])
def test_spi_response_vectors(vector):
    resp = SpiResponse(**vector["fields"])
    assert unpack_spi_response(bytes.fromhex(vector["bytes_hex"])) == resp
    assert pack_spi_response(resp).hex() == vector["bytes_hex"]


def test_spi_response_encoders_wrap_at_24_bits():
    # The QUBE's counters are 24 bits: an emulated one must wrap like them.
    wrapped = unpack_spi_response(pack_spi_response(SpiResponse(encoder0=(1 << 23), encoder1=-(1 << 23) - 1)))
    assert (wrapped.encoder0, wrapped.encoder1) == (-(1 << 23), (1 << 23) - 1)


def test_spi_rejects_bad_values():
    with pytest.raises(ValueError, match="led_red"):
        pack_spi_command(SpiCommand(led_red=1000))
    with pytest.raises(ValueError, match="17 bytes"):
        unpack_spi_response(b"\0" * 16)


def test_current_conversion_zero_and_scale():
    assert current_amps(8190) == 0.0
    assert current_amps(8190 + 2 * 4095) == pytest.approx(3.3 / 4)


def test_command_flags_values():
    # The C header and PROTOCOL.md use the same bit numbers.
    assert (CommandFlags.AMP_ENABLE, CommandFlags.RESET_ENCODER0, CommandFlags.RESET_ENCODER1) == (1, 2, 4)
    assert struct.calcsize("<hBHHH") == Command.SIZE
