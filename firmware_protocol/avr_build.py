"""Build the bridge sketch for the Arduino Uno (ATmega328P) without the Arduino IDE.

Uses Debian's packages: ``gcc-avr`` (avr-gcc 5.4), ``avr-libc`` and
``arduino-core-avr`` (the Arduino core 1.8.7 and its SPI library under
``/usr/share/arduino/hardware/arduino/avr``). The core, the SPI library, the
firmware's C sources and the sketch are compiled with ``-Os``, link-time
optimization and section garbage collection, as the IDE does. Builds are
cached by a hash of every source and flag, like :mod:`firmware_protocol.ccore`.

Nothing is built at import time: call :func:`cached_firmware`.
"""

from __future__ import annotations

import hashlib
import os
import shutil
import subprocess
import tempfile
from dataclasses import dataclass
from pathlib import Path

from .ccore import C_SOURCE_DIR, cache_root

__all__ = [
    "ARDUINO_AVR",
    "SKETCH",
    "AvrToolsMissing",
    "FirmwareSizes",
    "avr_tools_missing",
    "build_firmware",
    "cached_firmware",
    "firmware_sizes",
    "symbol_address",
]

ARDUINO_AVR = Path(os.environ.get("ARDUINO_AVR", "/usr/share/arduino/hardware/arduino/avr"))
SKETCH = C_SOURCE_DIR.parent / "examples" / "qube_bridge" / "qube_bridge.ino"
F_CPU = 16_000_000
_COMMON = (
    "-mmcu=atmega328p",
    f"-DF_CPU={F_CPU}L",
    "-DARDUINO=10807",
    "-DARDUINO_AVR_UNO",
    "-DARDUINO_ARCH_AVR",
    "-Os",
    "-flto",
    "-ffunction-sections",
    "-fdata-sections",
    "-Wall",
    # Debian's core 1.8.7 with avr-gcc 5.4: WString.cpp needs it.
    "-DDECIMAL_DIG=__DECIMAL_DIG__",
)
_CXX = ("-std=gnu++11", "-fno-exceptions", "-fno-threadsafe-statics")
_TOOLS = ("avr-gcc", "avr-g++", "avr-gcc-ar", "avr-size", "avr-objcopy", "avr-nm")
_INSTALL = "apt-get install gcc-avr avr-libc arduino-core-avr (or tools/install_system_deps.sh)"


class AvrToolsMissing(RuntimeError):
    """The AVR tool chain or the Arduino core is not installed."""


def avr_tools_missing() -> list[str]:
    """Names of the missing tools or folders (empty when the firmware can be built)."""
    missing = [tool for tool in _TOOLS if shutil.which(tool) is None]
    if not (ARDUINO_AVR / "cores" / "arduino" / "Arduino.h").is_file():
        missing.append(f"Arduino AVR core ({ARDUINO_AVR})")
    return missing


def _sources(source_dir: Path = C_SOURCE_DIR) -> list[Path]:
    core = ARDUINO_AVR / "cores" / "arduino"
    return sorted(
        [
            *core.glob("*.c"),
            *core.glob("*.cpp"),
            *core.glob("*.S"),
            ARDUINO_AVR / "libraries" / "SPI" / "src" / "SPI.cpp",
            *Path(source_dir).glob("*.c"),
        ]
    )


def _includes(source_dir: Path = C_SOURCE_DIR) -> tuple[str, ...]:
    return (
        f"-I{ARDUINO_AVR / 'cores' / 'arduino'}",
        f"-I{ARDUINO_AVR / 'variants' / 'standard'}",
        f"-I{ARDUINO_AVR / 'libraries' / 'SPI' / 'src'}",
        f"-I{source_dir}",
    )


def _run(cmd: list[str]) -> None:
    proc = subprocess.run(cmd, capture_output=True, text=True, check=False)
    if proc.returncode != 0:
        raise RuntimeError(f"AVR build failed ({' '.join(cmd)}):\n{proc.stdout}{proc.stderr}")


def build_firmware(
    out_dir: str | os.PathLike,
    *,
    sketch: str | os.PathLike = SKETCH,
    source_dir: str | os.PathLike = C_SOURCE_DIR,
    extra_flags: tuple[str, ...] = (),
) -> Path:
    """Compile and link the sketch for the Uno; writes ``qube_bridge.elf`` and ``.hex``.

    Parameters
    ----------
    out_dir : path
        Directory for objects and images (created if missing).
    sketch : path
        The ``.ino`` file (default: the project's bridge sketch).
    source_dir : path
        The firmware core's C sources (default: this package's ``c/src``).
    extra_flags : tuple of str
        Added to every compile and the link.

    Returns
    -------
    Path
        The ELF file (the HEX file is beside it).

    Raises
    ------
    AvrToolsMissing
        If avr-gcc or the Arduino core is not installed.
    RuntimeError
        If a compile or the link fails (the message holds the compiler's output).
    """
    missing = avr_tools_missing()
    if missing:
        raise AvrToolsMissing(f"cannot build the AVR firmware, missing: {', '.join(missing)}; {_INSTALL}")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    flags = (*_COMMON, *_includes(Path(source_dir)), *extra_flags)
    objects = []
    for i, src in enumerate([*_sources(Path(source_dir)), Path(sketch)]):
        obj = out / f"{i:02d}-{src.name}.o"
        if src.suffix == ".c":
            cmd = ["avr-gcc", *flags, "-std=gnu11"]
        elif src.suffix == ".S":
            cmd = ["avr-gcc", *flags, "-x", "assembler-with-cpp"]
        elif src.suffix == ".ino":
            cmd = ["avr-g++", *flags, *_CXX, "-x", "c++", "-include", "Arduino.h"]
        else:
            cmd = ["avr-g++", *flags, *_CXX]
        _run([*cmd, "-c", str(src), "-o", str(obj)])
        objects.append(str(obj))
    # The core goes in an archive, as the IDE does: only the objects the
    # sketch needs are linked (a sketch may define its own UART interrupts).
    core = out / "core.a"
    core.unlink(missing_ok=True)
    _run(["avr-gcc-ar", "rcs", str(core), *objects[:-1]])
    elf = out / "qube_bridge.elf"
    _run(["avr-gcc", *flags, "-fuse-linker-plugin", "-Wl,--gc-sections", "-o", str(elf), objects[-1], str(core), "-lm"])
    _run(["avr-objcopy", "-O", "ihex", "-R", ".eeprom", str(elf), str(elf.with_suffix(".hex"))])
    return elf


def cached_firmware(cache_dir: str | os.PathLike | None = None, *, sketch: str | os.PathLike = SKETCH) -> Path:
    """``build_firmware`` once per version of the sources, flags and compiler; then reuse it.

    Parameters
    ----------
    cache_dir : path, optional
        Default ``$XDG_CACHE_HOME/qube-koopman``.
    sketch : path
        The ``.ino`` file.

    Returns
    -------
    Path
        The ELF file.
    """
    missing = avr_tools_missing()
    if missing:
        raise AvrToolsMissing(f"cannot build the AVR firmware, missing: {', '.join(missing)}; {_INSTALL}")
    version = subprocess.run(["avr-gcc", "--version"], capture_output=True, text=True, check=False).stdout
    digest = hashlib.sha256("\0".join((version, *_COMMON, *_CXX)).encode())
    for path in [*_sources(), *sorted(C_SOURCE_DIR.glob("*.h")), Path(sketch)]:
        digest.update(str(path).encode() + b"\0" + path.read_bytes())
    root = Path(cache_dir) if cache_dir is not None else cache_root()
    final = root / f"avr-{digest.hexdigest()[:16]}"
    elf = final / "qube_bridge.elf"
    if elf.is_file():
        return elf
    final.parent.mkdir(parents=True, exist_ok=True)
    scratch = Path(tempfile.mkdtemp(dir=final.parent, prefix="avr-build-"))
    try:
        build_firmware(scratch, sketch=sketch)
        try:
            os.replace(scratch, final)
        except OSError:  # another process finished first
            pass
    finally:
        shutil.rmtree(scratch, ignore_errors=True)
    return elf


@dataclass(frozen=True)
class FirmwareSizes:
    """Memory use of a built image, in bytes (from ``avr-size``)."""

    text: int
    data: int
    bss: int

    @property
    def flash(self) -> int:
        """Program memory: code and constants plus the initial values of data."""
        return self.text + self.data

    @property
    def static_ram(self) -> int:
        """RAM taken before the stack: initialized data and bss."""
        return self.data + self.bss


def firmware_sizes(elf: str | os.PathLike) -> FirmwareSizes:
    """Sizes of an ELF image built by :func:`build_firmware`."""
    out = subprocess.run(["avr-size", str(elf)], capture_output=True, text=True, check=True).stdout
    text, data, bss = (int(v) for v in out.splitlines()[1].split()[:3])
    return FirmwareSizes(text, data, bss)


def symbol_address(elf: str | os.PathLike, name: str) -> int:
    """Address of a symbol (data addresses without avr-gcc's 0x800000 offset)."""
    out = subprocess.run(["avr-nm", str(elf)], capture_output=True, text=True, check=True).stdout
    for line in out.splitlines():
        parts = line.split()
        if len(parts) == 3 and parts[2] == name:
            return int(parts[0], 16) & 0xFFFF
    raise KeyError(f"{name} not in {elf}")
