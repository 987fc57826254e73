"""Decoder throughput of the bridge protocol, in frames per second.

Feeds a stream of telemetry frames (random field values) to each decoder in
chunks of random size, as a serial port delivers them, and reports the median
of several runs. Decoders compared in the same run:

- ``StreamDecoder``: this package's decoder (splits chunks on 0x00 in C,
  parses each piece);
- ``byte loop``: the textbook reference, one Python step per byte, same
  piece parser;
- ``C decoder (ctypes)``: the firmware's C decoder through
  ``qp_decoder_feed`` (skipped without a C compiler); with small chunks the
  cost of a ctypes call per chunk, not the C code, sets its rate.

The need is 500 frames/s (one telemetry frame per 500 Hz tick); the table
gives each decoder's margin over it and the share of one core it would use at
500 Hz. Usage: ``python bench/bench_protocol.py [--frames N] [--runs R]``.
"""

from __future__ import annotations

import argparse
import random
import statistics
import tempfile
import time


def make_stream(n_frames: int, seed: int) -> bytes:
    """``n_frames`` telemetry frames with random values, as the device sends them."""
    from qube_koopman.firmware_protocol import Telemetry, encode_frame

    rng = random.Random(seed)
    frames = []
    for k in range(n_frames):
        t = Telemetry(
            tick=k,
            encoder0=rng.randint(-3000, 3000),
            encoder1=rng.randint(-3000, 3000),
            tach_raw=rng.getrandbits(24),
            current_raw=rng.randint(7000, 9000),
            status=0x10,
            last_command_seq=k,
            applied_millivolts=rng.randint(-10000, 10000),
            motor_word=rng.getrandbits(16),
            command_age=rng.randint(0, 2),
        )
        frames.append(encode_frame(t, k, (2000 * k) & 0xFFFFFFFF))
    return b"".join(frames)


def chunked(stream: bytes, low: int, high: int, seed: int) -> list[bytes]:
    """``stream`` cut into chunks of random size in [low, high]."""
    rng = random.Random(seed)
    chunks, pos = [], 0
    while pos < len(stream):
        size = rng.randint(low, high)
        chunks.append(stream[pos : pos + size])
        pos += size
    return chunks


class ByteLoopDecoder:
    """Reference: the obvious byte-at-a-time decoder (same piece parser)."""

    def __init__(self) -> None:
        from qube_koopman.firmware_protocol.frame import MAX_WIRE_SIZE, parse_piece

        self._parse, self._max = parse_piece, MAX_WIRE_SIZE
        self._buf = bytearray()

    def feed(self, data: bytes) -> list:
        from qube_koopman.firmware_protocol import Frame

        out = []
        buf = self._buf
        for byte in data:
            if byte:
                if len(buf) <= self._max:
                    buf.append(byte)
                continue
            if buf:
                result = self._parse(bytes(buf))
                if isinstance(result, Frame):
                    out.append(result)
                buf.clear()
        return out


def time_decoder(make, chunks: list[bytes], expected: int, runs: int) -> tuple[float, float]:
    """Median frames/s over ``runs`` fresh decoders, and the spread (max - min) / median.

    Checks that every frame came out.
    """
    rates = []
    for _ in range(runs):
        decoder = make()
        count = 0
        start = time.perf_counter()
        for chunk in chunks:
            count += len(decoder.feed(chunk))
        elapsed = time.perf_counter() - start
        if count != expected:
            raise RuntimeError(f"{make.__name__}: decoded {count} frames, expected {expected}")
        rates.append(expected / elapsed)
    median = statistics.median(rates)
    return median, (max(rates) - min(rates)) / median


def c_decoder_factory(build_dir: str):
    """A factory of C decoders, or None without a C compiler."""
    from qube_koopman.firmware_protocol import ccore

    if ccore.find_c_compiler() is None:
        return None
    core = ccore.load(build_dir)

    def c_decoder():
        return ccore.CDecoder(core)

    return c_decoder


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description="Decoder throughput of the bridge protocol.")
    parser.add_argument("--frames", type=int, default=20_000, help="telemetry frames per run (default 20000)")
    parser.add_argument("--runs", type=int, default=7, help="runs per cell; the median is reported (default 7)")
    parser.add_argument("--seed", type=int, default=1)
    args = parser.parse_args(argv)

    from qube_koopman.firmware_protocol import StreamDecoder

    stream = make_stream(args.frames, args.seed)
    chunkings = [("1-16 B", 1, 16), ("1-64 B", 1, 64), ("1-512 B", 1, 512), ("1-4096 B", 1, 4096)]
    with tempfile.TemporaryDirectory() as build_dir:
        decoders = [("StreamDecoder", StreamDecoder), ("byte loop (reference)", ByteLoopDecoder)]
        c_factory = c_decoder_factory(build_dir)
        if c_factory is not None:
            decoders.append(("C decoder (ctypes)", c_factory))

        print(
            f"{args.frames} telemetry frames ({len(stream) / args.frames:.0f} bytes each), "
            f"median of {args.runs} runs; need: 500 frames/s\n"
        )
        header = (
            f"{'chunks':>10} | {'decoder':<22} | {'frames/s':>10} | {'spread':>6} | {'x need':>7} | "
            f"{'core @500Hz':>11} | {'vs ref':>6}"
        )
        print(header)
        print("-" * len(header))
        for label, low, high in chunkings:
            chunks = chunked(stream, low, high, args.seed)
            rates = {name: time_decoder(make, chunks, args.frames, args.runs) for name, make in decoders}
            reference = rates["byte loop (reference)"][0]
            for name, (rate, spread) in rates.items():
                print(
                    f"{label:>10} | {name:<22} | {rate:>10,.0f} | {100 * spread:>5.0f}% | {rate / 500:>7,.0f} | "
                    f"{100 * 500 / rate:>10.2f}% | {rate / reference:>5.1f}x"
                )
        print("\nspread: (max - min) / median over the runs; large values mean a busy machine.")
        if c_factory is None:
            print("\n(no C compiler: C decoder not measured)")


if __name__ == "__main__":
    main()
