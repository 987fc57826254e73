"""The C codec and firmware core, compiled with the system C compiler.

The library is built once per session with ``gcc -std=c99 -Wall -Wextra
-Werror -pedantic`` and loaded with ctypes. Checked here:

- byte-identical encoding and decoding against golden_vectors.json (CRC,
  COBS, payloads, frames, rejects, streams with their counters) and the
  QUBE-Servo 2 SPI packing;
- the C and Python stream decoders agree on random and mutated streams
  (frames and every counter);
- the device state machine: handshake, configuration, command application
  at the next tick, watchdog, encoder resets, faults, output overflow;
- a sanitizer (ASan + UBSan) fuzz run of the core, and a syntax check of
  the Arduino sketch against stub Arduino headers.

Skipped, with a message, only when no C compiler is found.
"""

from __future__ import annotations

import os
import shutil
import subprocess
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from qube_koopman.firmware_protocol import (
    MESSAGE_CLASSES,
    Capability,
    Command,
    CommandFlags,
    Config,
    ConfigAck,
    ConfigResult,
    Fault,
    FaultCode,
    Frame,
    Hello,
    HelloReply,
    MessageType,
    Reject,
    Status,
    StreamDecoder,
    Telemetry,
    encode_frame,
    encode_raw_frame,
)
from qube_koopman.firmware_protocol import ccore
from qube_koopman.firmware_protocol.qube_spi import (
    MASK_ENCODER0,
    MASK_ENCODER1,
    MASK_NORMAL,
    SpiCommand,
    SpiResponse,
    pack_spi_response,
    unpack_spi_command,
)
from qube_koopman.firmware_protocol.vectors import load_vectors

from protocol_helpers import messages, u32

VECTORS = load_vectors()
C_DIR = ccore.C_SOURCE_DIR.parent
TESTS_C = Path(__file__).resolve().parent / "protocol_c"


@pytest.fixture(scope="session")
def core(tmp_path_factory) -> ccore.CCore:
    if ccore.find_c_compiler() is None:
        pytest.skip("no C compiler found (set $CC or install gcc/clang): the C codec is not tested")
    return ccore.load(tmp_path_factory.mktemp("qp_build"))


# --- golden vectors -----------------------------------------------------------


def test_crc_and_cobs_vectors(core):
    for v in VECTORS["crc"]:
        assert core.crc16(bytes.fromhex(v["data_hex"])) == v["crc"], v
    for v in VECTORS["cobs"]:
        decoded, encoded = bytes.fromhex(v["decoded_hex"]), bytes.fromhex(v["encoded_hex"])
        assert core.cobs_encode(decoded) == encoded, v
        assert core.cobs_decode(encoded) == decoded, v


def test_cobs_decode_rejects_invalid(core):
    for bad in (b"\x05\x11\x22", b"\x02\x00", b"\x00", b"\x03\x11"):
        assert core.cobs_decode(bad) is None


@given(st.binary(max_size=700))
@settings(max_examples=200)
def test_c_cobs_and_crc_match_python(core, data):
    from qube_koopman.firmware_protocol import cobs_encode, crc16_ccitt_false

    assert core.cobs_encode(data) == cobs_encode(data)
    assert core.cobs_decode(cobs_encode(data)) == data
    assert core.crc16(data) == crc16_ccitt_false(data)


@pytest.mark.parametrize("vector", VECTORS["frames"], ids=lambda v: v["message"])
def test_frame_vectors(core, vector):
    cls = MESSAGE_CLASSES[vector["type"]]
    message = cls(**vector["fields"])
    payload = bytes.fromhex(vector["payload_hex"])
    wire = bytes.fromhex(vector["wire_hex"])
    assert core.pack_message(message) == payload
    assert core.unpack_message(cls, payload) == message
    assert core.encode_frame(vector["type"], vector["seq"], vector["timestamp_us"], payload) == wire
    reason, frame = core.parse_piece(wire[:-1])
    assert reason == Reject.OK
    assert (frame.version, frame.type, frame.seq, frame.timestamp_us) == (
        1,
        vector["type"],
        vector["seq"],
        vector["timestamp_us"],
    )
    assert bytes(frame.payload[: frame.payload_len]) == payload


def test_unpack_rejects_wrong_sizes(core):
    for cls in MESSAGE_CLASSES.values():
        assert core.unpack_message(cls, bytes(cls.SIZE + 1)) is None
        assert core.unpack_message(cls, bytes(cls.SIZE - 1)) is None


@pytest.mark.parametrize("vector", VECTORS["rejects"], ids=lambda v: v["name"])
def test_reject_vectors(core, vector):
    reason, _ = core.parse_piece(bytes.fromhex(vector["piece_hex"]))
    assert reason == Reject[vector["reason"]]


@pytest.mark.parametrize("vector", VECTORS["streams"], ids=lambda v: v["name"])
def test_stream_vectors(core, vector):
    decoder = ccore.CDecoder(core)
    frames = decoder.feed(bytes.fromhex(vector["stream_hex"]))
    expected = []
    for h in vector["frames_hex"]:
        f = StreamDecoder().feed(bytes.fromhex(h))[0]
        expected.append((f.message.TYPE, f.seq, f.timestamp_us, f.message.pack()))
    assert frames == expected
    counters = decoder.counters.as_dict()
    assert {k: counters[k] for k in vector["counters"]} == vector["counters"]


def test_motor_word_vectors(core):
    for v in VECTORS["motor_word"]:
        assert core.motor_word(v["millivolts"], v["enable"]) == v["word"], v


def test_motor_word_equals_python_for_every_millivolt_value(core):
    # The C core divides by 24 with a multiply and a shift: every value, both signs, past the clamp.
    from qube_koopman.firmware_protocol.qube_spi import motor_word

    for mv in range(-15_100, 15_101):
        assert core.motor_word(mv, True) == motor_word(mv, True), mv


def test_spi_vectors(core):
    for v in VECTORS["spi_command"]:
        assert core.spi_pack_command(SpiCommand(**v["fields"])).hex() == v["bytes_hex"], v
    for v in VECTORS["spi_response"]:
        assert core.spi_unpack_response(bytes.fromhex(v["bytes_hex"])) == SpiResponse(**v["fields"]), v


# --- C and Python decoders agree ----------------------------------------------


def _python_view(frames: list[Frame]):
    return [(f.message.TYPE, f.seq, f.timestamp_us, f.message.pack()) for f in frames]


@settings(max_examples=150)
@given(
    st.lists(st.one_of(st.binary(max_size=90), st.tuples(messages, u32, u32)), max_size=10),
    st.lists(st.tuples(st.integers(0, 10**6), st.integers(0, 7)), max_size=5),
)
def test_c_and_python_decoders_agree(core, parts, flips):
    stream = bytearray(b"".join(p if isinstance(p, bytes) else encode_frame(*p) for p in parts))
    for pos, bit in flips:
        if stream:
            stream[pos % len(stream)] ^= 1 << bit
    py, c = StreamDecoder(), ccore.CDecoder(core)
    assert c.feed(bytes(stream)) == _python_view(py.feed(bytes(stream)))
    assert c.counters.as_dict() == py.stats.as_dict()


@settings(max_examples=100)
@given(
    st.lists(st.one_of(st.binary(max_size=200), st.tuples(messages, u32, u32)), max_size=10),
    st.lists(st.integers(1, 40), max_size=8),
)
def test_device_receive_counts_as_the_python_decoder(core, parts, cuts):
    # qd_receive copies runs between delimiters at once (qp_decoder_append): same counters as byte by
    # byte, however the stream is cut into receive calls (oversize pieces included).
    stream = b"".join(p if isinstance(p, bytes) else encode_frame(*p) for p in parts)
    py, dev = StreamDecoder(), ccore.CDevice(core)
    py.feed(stream)
    pos = 0
    for cut in [*cuts, len(stream)]:
        dev.receive(stream[pos : pos + cut], 0)
        pos += cut
    dev.receive(stream[pos:], 0)
    assert dev.rx_counters.as_dict() == py.stats.as_dict()


# --- the device state machine -------------------------------------------------

QUBE_OK = SpiResponse(module_id=777, encoder0=-5, encoder1=1024, tach_raw=0x123, status=0, current_raw=8190)


class Rig:
    """The C firmware core with a Python host on the other side of the wire."""

    def __init__(self, core: ccore.CCore) -> None:
        self.dev = ccore.CDevice(core)
        self.host = StreamDecoder()
        self.now = 0
        self.seq = 0

    def send(self, message, seq: int | None = None) -> list[Frame]:
        self.seq = self.seq + 1 if seq is None else seq
        self.dev.receive(encode_frame(message, self.seq, 0), self.now)
        return self.read()

    def read(self) -> list[Frame]:
        return self.host.feed(self.dev.take_output())

    def tick(self, resp: SpiResponse = QUBE_OK, *, late: int = 0) -> tuple[SpiCommand, list[Frame]]:
        self.now += self.dev.period_us * (1 + late)
        spi = unpack_spi_command(self.dev.tick(self.now, pack_spi_response(resp)))
        return spi, self.read()

    def connect(self) -> HelloReply:
        self.read()
        (reply,) = self.send(Hello(nonce=0xC0FFEE))
        return reply.message


def telemetry(frames: list[Frame]) -> Telemetry:
    (t,) = [f.message for f in frames if isinstance(f.message, Telemetry)]
    return t


def faults(frames: list[Frame]) -> list[Fault]:
    return [f.message for f in frames if isinstance(f.message, Fault)]


@pytest.fixture
def rig(core) -> Rig:
    return Rig(core)


def test_silent_and_safe_before_hello(rig):
    assert rig.dev.take_output() == b"\0"  # leading delimiter flushes the host's partial frame
    for _ in range(5):
        spi, frames = rig.tick()
        assert frames == []
        assert spi.motor == 0 and spi.write_mask == MASK_NORMAL
        assert (spi.led_red, spi.led_green, spi.led_blue) == (0, 0, 999)  # blue: idle


def test_hello_reply(rig):
    rig.tick()
    reply = rig.connect()
    assert reply == HelloReply(
        nonce=0xC0FFEE,
        protocol_version=1,
        firmware_major=1,
        firmware_minor=0,
        firmware_patch=0,
        capabilities=0x7F,
        rate_hz=500,
        watchdog_ticks=5,
        max_millivolts=15000,
        module_id=777,
    )
    assert not reply.capabilities & Capability.EMULATED


def test_emulated_capability(core):
    dev = ccore.CDevice(core, extra_capabilities=Capability.EMULATED)
    dev.receive(encode_frame(Hello(), 1, 0), 0)
    (frame,) = StreamDecoder().feed(dev.take_output())
    assert frame.message.capabilities & Capability.EMULATED


def test_telemetry_every_tick_carries_the_spi_readings(rig):
    rig.connect()
    seqs = []
    for k in range(4):
        resp = SpiResponse(
            module_id=777, encoder0=-k, encoder1=(1 << 23) - 1, tach_raw=0xABCDEF, status=0b010, current_raw=9000 + k
        )
        _, frames = rig.tick(resp)
        (frame,) = frames
        seqs.append(frame.seq)
        assert frame.timestamp_us == rig.now
        assert frame.message == Telemetry(
            tick=k,
            encoder0=-k,
            encoder1=(1 << 23) - 1,
            tach_raw=0xABCDEF,
            current_raw=9000 + k,
            status=Status.STALL_DETECTED,
            last_command_seq=0,
            applied_millivolts=0,
            motor_word=0,
            command_age=0xFFFF,
        )
    assert seqs == list(range(seqs[0], seqs[0] + 4))


def test_newest_command_is_applied_at_the_next_tick(rig):
    rig.connect()
    rig.tick()
    rig.send(Command(millivolts=1000, flags=CommandFlags.AMP_ENABLE), seq=10)
    rig.send(Command(millivolts=-10000, flags=CommandFlags.AMP_ENABLE, led_green=500), seq=11)
    spi, frames = rig.tick()
    assert spi.motor == 0xFE5F  # -10 V (golden motor word), not the overtaken +1 V
    assert (spi.led_red, spi.led_green, spi.led_blue) == (0, 500, 0)
    t = telemetry(frames)
    assert (t.last_command_seq, t.applied_millivolts, t.motor_word, t.command_age) == (11, -10000, 0xFE5F, 0)
    assert t.status == Status.AMP_ENABLED


def test_watchdog_trips_after_five_silent_ticks_and_latches(rig):
    rig.connect()
    rig.send(Command(millivolts=3000, flags=CommandFlags.AMP_ENABLE))
    words = []
    for _ in range(5):
        spi, frames = rig.tick()
        words.append(spi.motor)
        assert faults(frames) == []
    assert all(w & 0x8000 for w in words)  # the command holds for 5 ticks = 10 ms
    spi, frames = rig.tick()
    assert spi.motor == 0
    assert faults(frames) == [Fault(code=FaultCode.WATCHDOG_TRIPPED, tick=5, value=5)]
    t = telemetry(frames)
    assert t.status & Status.WATCHDOG_TRIPPED and t.applied_millivolts == 0 and t.command_age == 5
    assert (spi.led_red, spi.led_green, spi.led_blue) == (999, 0, 0)
    # Latched: an enabling command is not obeyed, and the trip is reported once.
    rig.send(Command(millivolts=3000, flags=CommandFlags.AMP_ENABLE))
    spi, frames = rig.tick()
    assert spi.motor == 0 and telemetry(frames).status & Status.WATCHDOG_TRIPPED and faults(frames) == []
    # Cleared by commanding the amplifier off, then obeyed again.
    rig.send(Command())
    spi, frames = rig.tick()
    assert spi.motor == 0 and not telemetry(frames).status & Status.WATCHDOG_TRIPPED
    rig.send(Command(millivolts=3000, flags=CommandFlags.AMP_ENABLE))
    spi, _ = rig.tick()
    assert spi.motor == 0x8000 | 125


def test_commands_every_tick_keep_the_watchdog_quiet(rig):
    rig.connect()
    for k in range(50):
        rig.send(Command(millivolts=24 * k, flags=CommandFlags.AMP_ENABLE))
        spi, frames = rig.tick()
        assert spi.motor == 0x8000 | k and faults(frames) == []


def test_configuration(rig):
    rig.connect()
    (ack,) = rig.send(Config(rate_hz=250, watchdog_ticks=10, max_millivolts=10000))
    assert ack.message == ConfigAck(result=ConfigResult.OK, rate_hz=250, watchdog_ticks=10, max_millivolts=10000)
    assert rig.dev.period_us == 4000
    # Refused (1e6 / 300 is not whole microseconds): nothing changes.
    rig.dev.receive(encode_raw_frame(MessageType.CONFIG, 50, 0, (300).to_bytes(2, "little") + bytes(4)), 0)
    (ack,) = rig.read()
    assert ack.message == ConfigAck(result=ConfigResult.BAD_RATE, rate_hz=250, watchdog_ticks=10, max_millivolts=10000)
    # The limit saturates, and the watchdog now waits 10 ticks.
    rig.send(Command(millivolts=-12000, flags=CommandFlags.AMP_ENABLE))
    spi, frames = rig.tick()
    t = telemetry(frames)
    assert t.applied_millivolts == -10000 and t.status & Status.SATURATED
    assert spi.motor == 0x8000 | (-417 & 0x7FFF)
    for _ in range(9):
        spi, frames = rig.tick()
        assert spi.motor & 0x8000 and not faults(frames)
    _, frames = rig.tick()
    assert [f.code for f in faults(frames)] == [FaultCode.WATCHDOG_TRIPPED]


def test_encoder_resets_are_one_shot_and_not_lost(rig):
    rig.connect()
    rig.send(Command(flags=CommandFlags.RESET_ENCODER0))
    rig.send(Command(flags=CommandFlags.RESET_ENCODER1))
    spi, frames = rig.tick()
    assert spi.write_mask == MASK_NORMAL | MASK_ENCODER0 | MASK_ENCODER1
    assert (spi.encoder0_preset, spi.encoder1_preset) == (0, 0)
    assert telemetry(frames).status & Status.ENCODER_RESET
    rig.send(Command())
    spi, frames = rig.tick()
    assert spi.write_mask == MASK_NORMAL and not telemetry(frames).status & Status.ENCODER_RESET


def test_led_values_are_clamped(rig):
    rig.connect()
    payload = (
        (0).to_bytes(2, "little", signed=True)
        + bytes([0])
        + b"".join(v.to_bytes(2, "little") for v in (1200, 999, 0xFFFF))
    )
    rig.dev.receive(encode_raw_frame(MessageType.COMMAND, 1, 0, payload), 0)
    spi, _ = rig.tick()
    assert (spi.led_red, spi.led_green, spi.led_blue) == (999, 999, 999)


def test_qube_faults_are_reported_on_their_rising_edge(rig):
    rig.connect()
    faulty = SpiResponse(module_id=777, status=0b101)
    _, frames = rig.tick(faulty)
    assert [(f.code, f.value) for f in faults(frames)] == [(FaultCode.AMP_FAULT, 5), (FaultCode.STALL_ERROR, 5)]
    assert telemetry(frames).status == Status.AMP_FAULT | Status.STALL_ERROR
    _, frames = rig.tick(faulty)
    assert faults(frames) == [] and telemetry(frames).status == Status.AMP_FAULT | Status.STALL_ERROR
    _, frames = rig.tick(SpiResponse(module_id=0xFFFF))
    assert [(f.code, f.value) for f in faults(frames)] == [(FaultCode.BAD_MODULE_ID, 0xFFFF)]
    assert telemetry(frames).status & Status.BAD_MODULE_ID


def test_commands_before_hello_are_refused(rig):
    rig.read()
    frames = rig.send(Command(millivolts=5000, flags=CommandFlags.AMP_ENABLE))
    assert [(f.message.code, f.message.value) for f in frames] == [(FaultCode.NOT_CONNECTED, MessageType.COMMAND)]
    spi, _ = rig.tick()
    assert spi.motor == 0


def test_other_protocol_versions_are_answered(rig):
    rig.read()
    rig.dev.receive(encode_raw_frame(MessageType.HELLO, 1, 0, bytes(4), version=2), 0)
    (frame,) = rig.read()
    assert (frame.message.code, frame.message.value) == (FaultCode.BAD_VERSION, 2)


def test_late_ticks_and_receive_errors_are_reported(rig):
    rig.connect()
    rig.tick()
    _, frames = rig.tick(late=2)
    assert [(f.code, f.value) for f in faults(frames)] == [(FaultCode.TICK_OVERRUN, 2)]
    assert telemetry(frames).status & Status.TICK_OVERRUN
    bad = bytearray(encode_frame(Command(), 9, 0))
    bad[4] ^= 0x10
    rig.dev.receive(bytes(bad) * 3, rig.now)
    _, frames = rig.tick()
    assert [(f.code, f.value) for f in faults(frames)] == [(FaultCode.RX_ERRORS, 3)]
    assert rig.dev.rx_counters.bad_crc == 3


def test_output_overflow_drops_whole_frames_and_says_so(rig):
    rig.connect()
    for _ in range(12):  # 12 x 46 bytes > the 256-byte queue
        rig.now += rig.dev.period_us
        rig.dev.tick(rig.now, pack_spi_response(QUBE_OK))
    frames = rig.read()
    assert rig.host.stats.rejected == 0
    assert [f.message.tick for f in frames] == [0, 1, 2, 3, 4]
    _, frames = rig.tick()
    t = telemetry(frames)
    assert t.status & Status.TX_OVERFLOW and t.tick == 12
    assert frames[0].seq - 5 == 12 - 5 + 1  # the dropped frames used sequence numbers


def test_hello_starts_a_new_session(rig):
    rig.connect()
    rig.send(Command(millivolts=3000, flags=CommandFlags.AMP_ENABLE))
    for _ in range(8):
        rig.tick()
    rig.send(Config(rate_hz=1000, watchdog_ticks=3, max_millivolts=0))
    reply = rig.connect()
    assert (reply.rate_hz, reply.watchdog_ticks, reply.max_millivolts) == (500, 5, 15000)
    spi, frames = rig.tick()
    t = telemetry(frames)
    assert spi.motor == 0 and t.tick == 0 and t.status == 0 and t.command_age == 0xFFFF


@settings(max_examples=100)
@given(st.binary(max_size=400))
def test_random_bytes_never_enable_the_motor(core, data):
    dev = ccore.CDevice(core)
    dev.receive(encode_frame(Hello(), 1, 0), 0)
    dev.receive(data, 0)
    for k in range(1, 8):
        assert unpack_spi_command(dev.tick(2000 * k, pack_spi_response(QUBE_OK))).motor == 0
    decoder = StreamDecoder()
    decoder.feed(dev.take_output())
    assert decoder.stats.rejected == 0


# --- sanitizers and the Arduino sketch ----------------------------------------


def test_core_under_sanitizers(tmp_path):
    cc = ccore.find_c_compiler()
    if cc is None:
        pytest.skip("no C compiler found (set $CC or install gcc/clang)")
    exe = tmp_path / "fuzz_core"
    cmd = [
        cc,
        *ccore.C_FLAGS,
        "-O1",
        "-g",
        "-fsanitize=address,undefined",
        "-fno-sanitize-recover=all",
        f"-I{ccore.C_SOURCE_DIR}",
        str(TESTS_C / "fuzz_core.c"),
        *map(str, sorted(ccore.C_SOURCE_DIR.glob("*.c"))),
        "-o",
        str(exe),
    ]
    build = subprocess.run(cmd, capture_output=True, text=True)
    if build.returncode != 0 and "sanitize" in build.stderr:
        pytest.skip(f"the compiler has no ASan/UBSan runtime: {build.stderr.strip()[:200]}")
    assert build.returncode == 0, build.stderr
    run = subprocess.run([str(exe), "100000"], capture_output=True, text=True, timeout=120)
    assert run.returncode == 0 and run.stdout.startswith("OK"), run.stdout + run.stderr


def test_core_compiles_for_a_16_bit_int_avr(tmp_path):
    """Optional: the core is meant for 8-bit AVRs (16-bit int, 2 KiB RAM) too."""
    avr_gcc = shutil.which("avr-gcc")
    if avr_gcc is None:
        pytest.skip("avr-gcc not installed (Debian: gcc-avr avr-libc): AVR portability not checked")
    main = tmp_path / "main.c"
    main.write_text(
        '#include "qp_device.h"\nstatic qd_device dev;\n'
        "int main(void) { uint8_t tx[17], rx[17] = {3, 9}; qd_init(&dev, 0);\n"
        "qd_tick_begin(&dev, 0, tx); qd_tick_end(&dev, rx); return (int)qd_pending_output(&dev); }\n"
    )
    elf = tmp_path / "core.elf"
    cmd = [
        avr_gcc,
        "-mmcu=atmega328p",
        "-Os",
        *ccore.C_FLAGS,
        f"-I{ccore.C_SOURCE_DIR}",
        str(main),
        *map(str, sorted(ccore.C_SOURCE_DIR.glob("*.c"))),
        "-o",
        str(elf),
    ]
    proc = subprocess.run(cmd, capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    size = subprocess.run(["avr-size", str(elf)], capture_output=True, text=True).stdout.split("\n")[1].split()
    text, data, bss = map(int, size[:3])
    assert text < 16 * 1024 and data + bss < 1024  # leaves the Arduino core most of 32 KiB / 2 KiB


def test_arduino_sketch_compiles_cleanly_for_the_uno():
    """The sketch against the real Arduino core and avr-libc, warnings as errors.

    (It drives the ATmega328P's registers directly, so stub headers no longer
    describe it; tests/firmware_protocol/test_avr.py builds and runs it.)
    """
    from qube_koopman.firmware_protocol import avr_build as avr

    missing = avr.avr_tools_missing()
    if missing:
        message = f"the AVR tool chain is missing ({', '.join(missing)}): run tools/install_system_deps.sh"
        if os.environ.get("CI", "").lower() == "true":
            pytest.fail(message)
        pytest.skip(message)
    cmd = [
        "avr-g++",
        *avr._COMMON,
        *avr._includes(),
        *avr._CXX,
        "-Wextra",
        "-Werror",
        "-fsyntax-only",
        "-x",
        "c++",
        "-include",
        "Arduino.h",
        str(avr.SKETCH),
    ]
    proc = subprocess.run(cmd, capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
