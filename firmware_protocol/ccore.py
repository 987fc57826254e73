"""Build the C codec and firmware core as a shared library and call it from Python.

The same C files run on the bridge microcontroller; here they are compiled
with the system C compiler so tests can check them against the golden
vectors and an emulated bridge can run the real firmware logic. Nothing is
built at import time: call ``build_library`` (or ``load``) explicitly.
"""

from __future__ import annotations

import ctypes
import hashlib
import os
import shutil
import subprocess
import tempfile
from pathlib import Path

from .messages import Message
from .qube_spi import SPI_SIZE, SpiCommand, SpiResponse

__all__ = [
    "C_SOURCE_DIR",
    "C_FLAGS",
    "CompilerNotFound",
    "find_c_compiler",
    "build_library",
    "cached_library",
    "CCore",
    "CDecoder",
    "CDevice",
    "Counters",
    "message_struct",
    "load",
]

C_SOURCE_DIR = Path(__file__).resolve().parent / "c" / "src"
C_FLAGS = ("-std=c99", "-Wall", "-Wextra", "-Werror", "-pedantic")
_U8P = ctypes.POINTER(ctypes.c_uint8)


class CompilerNotFound(RuntimeError):
    """No C compiler: set $CC or install gcc/clang."""


def find_c_compiler() -> str | None:
    """The C compiler to use: $CC if set, else the first of cc, gcc, clang on PATH."""
    if os.environ.get("CC"):
        return os.environ["CC"]
    for name in ("cc", "gcc", "clang"):
        path = shutil.which(name)
        if path:
            return path
    return None


def _required_compiler() -> str:
    cc = find_c_compiler()
    if cc is None:
        raise CompilerNotFound("no C compiler found: set $CC or install gcc or clang")
    return cc


def build_library(out_dir: str | os.PathLike, *, extra_flags: tuple[str, ...] = ()) -> Path:
    """Compile ``c/src/*.c`` into a shared library in ``out_dir``.

    Parameters
    ----------
    out_dir : path
        Directory for the library (created if missing).
    extra_flags : tuple of str
        Added to the command line (e.g. ``("-O0", "-g")``).

    Returns
    -------
    Path
        The library file.

    Raises
    ------
    CompilerNotFound
        If no C compiler is available.
    RuntimeError
        If compilation fails (the message holds the compiler's output).
    """
    cc = _required_compiler()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    lib = out / "libqubeproto.so"
    sources = sorted(str(p) for p in C_SOURCE_DIR.glob("*.c"))
    cmd = [cc, *C_FLAGS, "-O2", "-shared", "-fPIC", *extra_flags, "-o", str(lib), *sources]
    proc = subprocess.run(cmd, capture_output=True, text=True, check=False)
    if proc.returncode != 0:
        raise RuntimeError(f"C build failed ({' '.join(cmd)}):\n{proc.stdout}{proc.stderr}")
    return lib


def cache_root() -> Path:
    """Where the C builds are cached: :func:`qube_koopman.core.files.cache_root`.

    Shared with the AVR firmware's builds (:mod:`~qube_koopman.firmware_protocol.avr_build`,
    :mod:`~qube_koopman.sim.bridge.avr`); not created here.
    """
    from qube_koopman.core.files import cache_root as toolkit_cache

    return toolkit_cache()


def cached_library(cache_dir: str | os.PathLike | None = None) -> Path:
    """``build_library`` once per version of the C sources, then reuse the build.

    The library goes to ``<cache_dir>/ccore-<hash>/`` where the hash covers
    the sources, the flags and the compiler, so an edited source or another
    compiler gets a fresh build. Concurrent callers are safe: each builds in
    its own folder and the first finished build is moved into place.

    Parameters
    ----------
    cache_dir : path, optional
        Default ``$XDG_CACHE_HOME/qube-koopman`` (``~/.cache/qube-koopman``);
        a temporary folder when that cannot be written.

    Returns
    -------
    Path
        The library file.

    Raises
    ------
    CompilerNotFound, RuntimeError
        As ``build_library``.
    """
    cc = _required_compiler()
    digest = hashlib.sha256("\0".join((cc, *C_FLAGS)).encode())
    for path in sorted(C_SOURCE_DIR.glob("*.[ch]")):
        digest.update(path.name.encode() + b"\0" + path.read_bytes())
    root = Path(cache_dir) if cache_dir is not None else cache_root()
    final = root / f"ccore-{digest.hexdigest()[:16]}" / "libqubeproto.so"
    if final.is_file():
        return final
    try:
        final.parent.mkdir(parents=True, exist_ok=True)
        scratch = Path(tempfile.mkdtemp(dir=final.parent, prefix="build-"))
    except OSError:
        return build_library(tempfile.mkdtemp(prefix="qube-ccore-"))
    try:
        os.replace(build_library(scratch), final)
    finally:
        shutil.rmtree(scratch, ignore_errors=True)
    return final


class Counters(ctypes.Structure):
    """Mirror of ``qp_counters`` (field names as in ``DecoderStats``)."""

    _fields_ = [
        (name, ctypes.c_uint32)
        for name in (
            "frames",
            "bad_crc",
            "bad_cobs",
            "bad_length",
            "bad_version",
            "unknown_type",
            "oversize",
            "last_bad_version",
            "bytes_in",
        )
    ]

    def as_dict(self) -> dict[str, int]:
        """Plain-data form, comparable with ``DecoderStats.as_dict()``."""
        return {name: getattr(self, name) for name, *_ in self._fields_}


class CFrame(ctypes.Structure):
    """Mirror of ``qp_frame``."""

    _fields_ = [
        ("version", ctypes.c_uint8),
        ("type", ctypes.c_uint8),
        ("seq", ctypes.c_uint32),
        ("timestamp_us", ctypes.c_uint32),
        ("payload_len", ctypes.c_uint8),
        ("payload", ctypes.c_uint8 * 64),
    ]


_CTYPE = {"B": ctypes.c_uint8, "H": ctypes.c_uint16, "h": ctypes.c_int16, "I": ctypes.c_uint32, "i": ctypes.c_int32}


def _snake(name: str) -> str:
    return "".join("_" + c.lower() if c.isupper() else c for c in name).lstrip("_")


def message_struct(cls: type[Message]) -> type[ctypes.Structure]:
    """ctypes mirror of a message's C struct (``qp_<snake_name>``).

    The C structs declare the payload fields in payload order with the same
    fixed-width types, so the mirror follows from the Python layout.
    """
    return type(
        f"qp_{_snake(cls.__name__)}",
        (ctypes.Structure,),
        {"_fields_": [(name, _CTYPE[code]) for name, (code, _) in zip(cls.field_ranges(), cls.LAYOUT)]},
    )


class SpiCommandStruct(ctypes.Structure):
    """Mirror of ``qp_spi_command``."""

    _fields_ = [
        ("write_mask", ctypes.c_uint8),
        ("led_red", ctypes.c_uint16),
        ("led_green", ctypes.c_uint16),
        ("led_blue", ctypes.c_uint16),
        ("encoder0_preset", ctypes.c_int32),
        ("encoder1_preset", ctypes.c_int32),
        ("motor", ctypes.c_uint16),
    ]


class SpiResponseStruct(ctypes.Structure):
    """Mirror of ``qp_spi_response``."""

    _fields_ = [
        ("module_id", ctypes.c_uint16),
        ("encoder0", ctypes.c_int32),
        ("encoder1", ctypes.c_int32),
        ("tach_raw", ctypes.c_uint32),
        ("status", ctypes.c_uint8),
        ("current_raw", ctypes.c_uint16),
    ]


def _buf(data: bytes):
    return (ctypes.c_uint8 * max(1, len(data))).from_buffer_copy(data or b"\0")


class CCore:
    """The loaded library with typed entry points.

    Parameters
    ----------
    path : path
        A library made by ``build_library``.
    """

    def __init__(self, path: str | os.PathLike) -> None:
        lib = ctypes.CDLL(str(path))
        sig = {
            "qp_crc16": (ctypes.c_uint16, [ctypes.c_uint16, _U8P, ctypes.c_size_t]),
            "qp_cobs_encode": (ctypes.c_size_t, [_U8P, ctypes.c_size_t, _U8P, ctypes.c_size_t]),
            "qp_cobs_decode": (ctypes.c_long, [_U8P, ctypes.c_size_t, _U8P, ctypes.c_size_t]),
            "qp_encode_frame": (
                ctypes.c_size_t,
                [ctypes.c_uint8, ctypes.c_uint32, ctypes.c_uint32, _U8P, ctypes.c_size_t, _U8P, ctypes.c_size_t],
            ),
            "qp_parse_piece": (ctypes.c_int, [_U8P, ctypes.c_size_t, ctypes.POINTER(CFrame)]),
            "qp_decoder_init": (None, [ctypes.c_void_p]),
            "qp_decoder_size": (ctypes.c_size_t, []),
            "qp_decoder_counters": (ctypes.POINTER(Counters), [ctypes.c_void_p]),
            "qp_decoder_push": (ctypes.c_int, [ctypes.c_void_p, ctypes.c_uint8, ctypes.POINTER(CFrame)]),
            "qp_decoder_feed": (
                ctypes.c_size_t,
                [ctypes.c_void_p, _U8P, ctypes.c_size_t, ctypes.POINTER(CFrame), ctypes.c_size_t],
            ),
            "qp_spi_pack_command": (None, [ctypes.c_void_p, _U8P]),
            "qp_spi_unpack_response": (None, [_U8P, ctypes.c_void_p]),
            "qp_motor_word": (ctypes.c_uint16, [ctypes.c_int32, ctypes.c_int]),
            "qd_device_size": (ctypes.c_size_t, []),
            "qd_init": (None, [ctypes.c_void_p, ctypes.c_uint32]),
            "qd_receive": (None, [ctypes.c_void_p, _U8P, ctypes.c_size_t, ctypes.c_uint32]),
            "qd_tick_begin": (None, [ctypes.c_void_p, ctypes.c_uint32, _U8P]),
            "qd_tick_end": (None, [ctypes.c_void_p, _U8P]),
            "qd_take_output": (ctypes.c_size_t, [ctypes.c_void_p, _U8P, ctypes.c_size_t]),
            "qd_pending_output": (ctypes.c_size_t, [ctypes.c_void_p]),
            "qd_period_us": (ctypes.c_uint32, [ctypes.c_void_p]),
            "qd_rx_counters": (ctypes.POINTER(Counters), [ctypes.c_void_p]),
        }
        for name, (restype, argtypes) in sig.items():
            fn = getattr(lib, name)
            fn.restype, fn.argtypes = restype, argtypes
        self.lib = lib

    def crc16(self, data: bytes, value: int = 0xFFFF) -> int:
        """``qp_crc16``."""
        return self.lib.qp_crc16(value, _buf(data), len(data))

    def cobs_encode(self, data: bytes) -> bytes:
        """``qp_cobs_encode``."""
        cap = len(data) + len(data) // 254 + 2
        out = (ctypes.c_uint8 * cap)()
        n = self.lib.qp_cobs_encode(_buf(data), len(data), out, cap)
        return bytes(out[:n])

    def cobs_decode(self, data: bytes) -> bytes | None:
        """``qp_cobs_decode``; None where the C code reports an invalid encoding."""
        out = (ctypes.c_uint8 * max(1, len(data)))()
        n = self.lib.qp_cobs_decode(_buf(data), len(data), out, len(data))
        return None if n < 0 else bytes(out[:n])

    def encode_frame(self, msg_type: int, seq: int, timestamp_us: int, payload: bytes) -> bytes:
        """``qp_encode_frame``: wire bytes, delimiter included (b"" if refused)."""
        out = (ctypes.c_uint8 * 128)()
        n = self.lib.qp_encode_frame(msg_type, seq, timestamp_us, _buf(payload), len(payload), out, 128)
        return bytes(out[:n])

    def parse_piece(self, piece: bytes) -> tuple[int, CFrame]:
        """``qp_parse_piece``: (reject code, frame); the frame is valid when the code is 0."""
        frame = CFrame()
        return self.lib.qp_parse_piece(_buf(piece), len(piece), ctypes.byref(frame)), frame

    def motor_word(self, millivolts: int, enable: bool) -> int:
        """``qp_motor_word``."""
        return self.lib.qp_motor_word(millivolts, int(enable))

    def pack_message(self, message: Message) -> bytes:
        """Payload bytes from the C ``qp_pack_<type>`` (no range checks in C)."""
        struct_cls = message_struct(type(message))
        c_msg = struct_cls(*(getattr(message, name) for name, *_ in struct_cls._fields_))
        out = (ctypes.c_uint8 * 64)()
        n = getattr(self.lib, f"qp_pack_{_snake(type(message).__name__)}")(ctypes.byref(c_msg), out)
        return bytes(out[:n])

    def unpack_message(self, cls: type[Message], payload: bytes) -> Message | None:
        """Message from the C ``qp_unpack_<type>``; None where C reports a wrong size."""
        c_msg = message_struct(cls)()
        if getattr(self.lib, f"qp_unpack_{_snake(cls.__name__)}")(_buf(payload), len(payload), ctypes.byref(c_msg)):
            return None
        return cls(*(getattr(c_msg, name) for name, *_ in c_msg._fields_))

    def spi_pack_command(self, cmd: SpiCommand) -> bytes:
        """``qp_spi_pack_command``."""
        c_cmd = SpiCommandStruct(*(getattr(cmd, name) for name, *_ in SpiCommandStruct._fields_))
        out = (ctypes.c_uint8 * SPI_SIZE)()
        self.lib.qp_spi_pack_command(ctypes.byref(c_cmd), out)
        return bytes(out)

    def spi_unpack_response(self, data: bytes) -> SpiResponse:
        """``qp_spi_unpack_response``."""
        if len(data) != SPI_SIZE:
            raise ValueError(f"an SPI transaction is {SPI_SIZE} bytes, got {len(data)}")
        c_resp = SpiResponseStruct()
        self.lib.qp_spi_unpack_response(_buf(data), ctypes.byref(c_resp))
        return SpiResponse(*(getattr(c_resp, name) for name, *_ in SpiResponseStruct._fields_))


class CDecoder:
    """A ``qp_decoder`` fed from Python (one C call per byte)."""

    def __init__(self, core: CCore) -> None:
        self._core = core
        self._mem = _opaque(core.lib.qp_decoder_size())
        core.lib.qp_decoder_init(self._mem)
        self.count = 0
        self._frames = (CFrame * 256)()  # reused: allocating per call would dominate small chunks

    def feed(self, data: bytes, max_frames: int = 256) -> list[tuple[int, int, int, bytes]]:
        """Push bytes; return ``(type, seq, timestamp_us, payload)`` of each valid frame.

        At most ``max_frames`` are returned; ``count`` says how many there were.
        """
        if len(self._frames) < max_frames:
            self._frames = (CFrame * max_frames)()
        frames = self._frames
        self.count = self._core.lib.qp_decoder_feed(self._mem, _buf(data), len(data), frames, max_frames)
        return [
            (f.type, f.seq, f.timestamp_us, bytes(f.payload[: f.payload_len]))
            for f in frames[: min(self.count, max_frames)]
        ]

    @property
    def counters(self) -> Counters:
        """The C decoder's counters (a copy)."""
        return _copy_counters(self._core.lib.qp_decoder_counters(self._mem))


def _opaque(size: int):
    # 8-byte aligned storage for a C struct of only integers and bytes.
    return (ctypes.c_uint64 * ((size + 7) // 8))()


def _copy_counters(pointer) -> Counters:
    return Counters.from_buffer_copy(ctypes.string_at(pointer, ctypes.sizeof(Counters)))


class CDevice:
    """The firmware core (``qd_device``) driven from Python.

    Parameters
    ----------
    core : CCore
        The loaded library.
    extra_capabilities : int
        OR-ed into the advertised capabilities (``Capability.EMULATED`` for a simulator).
    """

    def __init__(self, core: CCore, extra_capabilities: int = 0) -> None:
        self._core = core
        self._mem = _opaque(core.lib.qd_device_size())
        core.lib.qd_init(self._mem, extra_capabilities)
        self._out = (ctypes.c_uint8 * 4096)()
        self._tx = (ctypes.c_uint8 * SPI_SIZE)()

    def receive(self, data: bytes, now_us: int) -> None:
        """Bytes from the host, at device time ``now_us``."""
        self._core.lib.qd_receive(self._mem, _buf(data), len(data), now_us & 0xFFFFFFFF)

    def tick_begin(self, now_us: int) -> bytes:
        """Start a tick; returns the 17 SPI bytes the bridge sends."""
        self._core.lib.qd_tick_begin(self._mem, now_us & 0xFFFFFFFF, self._tx)
        return bytes(self._tx)

    def tick_end(self, spi_rx: bytes) -> None:
        """Finish a tick with the 17 bytes the QUBE returned."""
        if len(spi_rx) != SPI_SIZE:
            raise ValueError(f"an SPI transaction is {SPI_SIZE} bytes, got {len(spi_rx)}")
        self._core.lib.qd_tick_end(self._mem, _buf(spi_rx))

    def tick(self, now_us: int, spi_rx: bytes) -> bytes:
        """One whole tick with a given QUBE response; returns the SPI bytes sent."""
        tx = self.tick_begin(now_us)
        self.tick_end(spi_rx)
        return tx

    def take_output(self) -> bytes:
        """All bytes waiting for the host."""
        chunks: list[bytes] = []
        while True:
            n = self._core.lib.qd_take_output(self._mem, self._out, len(self._out))
            if n == 0:
                return b"".join(chunks)
            chunks.append(bytes(self._out[:n]))

    @property
    def period_us(self) -> int:
        """Tick period the device asks of its glue."""
        return self._core.lib.qd_period_us(self._mem)

    @property
    def rx_counters(self) -> Counters:
        """Counters of the device's frame decoder (a copy)."""
        return _copy_counters(self._core.lib.qd_rx_counters(self._mem))


def load(out_dir: str | os.PathLike) -> CCore:
    """``build_library(out_dir)`` and load it."""
    return CCore(build_library(out_dir))
