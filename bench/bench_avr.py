"""Cycles per tick of the bridge firmware on the emulated ATmega328P, before and after.

Runs the sketch and core of a reference commit (default: 89b7e0d, the
HardwareSerial sketch polling micros()) and the current ones on simavr in
simulated time, with a COMMAND every 2 ms as the host loop sends them, and
prints ticks per simulated second, busy cycles per tick (cycles not spent in
sleep, the mean and the worst mean of 10 consecutive ticks; the reference
never sleeps, so its figure is the whole period and its cost shows as the
period it really achieves) and a flat profile: running
cycles per tick by function (self time; ISRs are named by vector).

Target: at most 60 % of the 32,000-cycle tick (19,200) with a command every tick; the
current firmware's worst single tick is also found over 16 command arrival phases.

Usage: python bench/bench_avr.py [--reference COMMIT] [--seconds S]
"""

from __future__ import annotations

import argparse
import bisect
import subprocess
import tempfile
from pathlib import Path

from qube_koopman.firmware_protocol import Command, Hello, StreamDecoder, encode_frame
from qube_koopman.firmware_protocol.avr_build import F_CPU, SKETCH, build_firmware, cached_firmware, firmware_sizes
from qube_koopman.sim.bridge.avr import AvrBridge

REPO = Path(__file__).resolve().parents[1]
BUDGET = F_CPU // 500
VECTORS = {
    "__vector_11": "TIMER1_COMPA ISR",
    "__vector_16": "TIMER0_OVF ISR (millis)",
    "__vector_18": "USART_RX ISR",
    "__vector_19": "USART_UDRE ISR",
}


def reference_elf(commit: str, out: Path) -> Path:
    """Build the sketch and C core of ``commit``."""
    src = out / "src"
    src.mkdir(parents=True)
    names = subprocess.run(
        ["git", "ls-tree", "--name-only", f"{commit}:firmware_protocol/c/src"],
        cwd=REPO,
        capture_output=True,
        text=True,
        check=True,
    ).stdout.split()
    for name in names:
        (src / name).write_bytes(
            subprocess.run(
                ["git", "show", f"{commit}:firmware_protocol/c/src/{name}"], cwd=REPO, capture_output=True, check=True
            ).stdout
        )
    sketch = out / "qube_bridge.ino"
    sketch.write_bytes(
        subprocess.run(
            ["git", "show", f"{commit}:{SKETCH.relative_to(REPO)}"], cwd=REPO, capture_output=True, check=True
        ).stdout
    )
    return build_firmware(out / "build", sketch=sketch, source_dir=src)


def symbols(elf: Path) -> tuple[list[int], list[str]]:
    """Word addresses where each sized symbol of the image and each gap after one starts, and their names."""
    out = subprocess.run(["avr-nm", "-n", "-S", str(elf)], capture_output=True, text=True, check=True).stdout
    addrs, names = [], []
    for a, size, t, n in (ln.split() for ln in out.splitlines() if len(ln.split()) == 4):
        if t in "tTW":
            addrs += [int(a, 16) // 2, (int(a, 16) + int(size, 16)) // 2]
            names += [VECTORS.get(n, n), "(code without a sized symbol)"]
    return addrs, names


def measure(elf: Path, seconds: float) -> dict:
    """Command every tick for ``seconds`` after a HELLO; ticks/s, busy cycles/tick and the profile."""
    bridge = AvrBridge(elf)
    chip, seq = bridge.chip, 0
    bridge.run_for(0.05)
    chip.push(encode_frame(Hello(nonce=1), seq=0, timestamp_us=0))
    bridge.run_for(0.05)
    decoder = StreamDecoder()
    decoder.feed(chip.pull())
    c0, busy0, n0, prof0 = chip.cycle, chip.busy_cycles, len(bridge.transactions), chip.pc_cycles()
    for seq in range(1, round(seconds * 500) + 1):
        chip.push(encode_frame(Command(millivolts=300, flags=1), seq=seq, timestamp_us=0))
        bridge.run_for(0.002)
    frames = decoder.feed(chip.pull())
    ticks = len(bridge.transactions) - n0
    addrs, names = symbols(elf)
    parts: dict[str, int] = {}
    for word, (after, before) in enumerate(zip(chip.pc_cycles(), prof0)):
        if after != before:
            at = bisect.bisect_right(addrs, word) - 1
            name = names[at] if at >= 0 else "interrupt vector table (jumps)"
            parts[name] = parts.get(name, 0) + after - before
    _, worst = bridge.busy_per_tick(n0)
    return dict(
        ticks_per_s=ticks / ((chip.cycle - c0) / F_CPU),
        busy=(chip.busy_cycles - busy0) / ticks,
        worst=worst,
        parts={k: v / ticks for k, v in parts.items()},
        frames=len(frames),
        rx_lost=chip.rx_lost,
        sizes=firmware_sizes(elf),
        stack=0x8FF - chip.stack_low + 1,
    )


def phase_sweep(elf: Path, n_phases: int = 16, ticks: int = 150) -> tuple[int, int, int]:
    """Busy cycles of single ticks with the COMMAND arriving at ``n_phases`` points of the tick.

    Returns the worst steady-state tick, its phase in cycles after the tick's start, and the worst
    tick of a session's first command (once per session).
    """
    worst, at, first_tick = 0, 0, 0
    for phase in range(0, BUDGET, BUDGET // n_phases):
        bridge = AvrBridge(elf)
        chip = bridge.chip
        bridge.run_for(0.05)
        chip.push(encode_frame(Hello(nonce=1), seq=0, timestamp_us=0))
        bridge.run_for(0.01)
        n0 = len(bridge.transactions)
        start = bridge.transactions[-1][0] + phase
        for seq in range(1, ticks + 1):
            bridge.run_until(max(start + (seq - 1) * BUDGET, chip.cycle))
            chip.push(encode_frame(Command(millivolts=300, flags=1), seq=seq, timestamp_us=0))
        bridge.run_until(start + ticks * BUDGET)
        busy = [t[3] for t in bridge.transactions[n0:]]
        per_tick = [b - a for a, b in zip(busy, busy[1:])]
        first_tick = max(first_tick, max(per_tick[:2]))
        if max(per_tick[2:]) > worst:
            worst, at = max(per_tick[2:]), phase
    return worst, at, first_tick


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--reference", default="89b7e0d")
    parser.add_argument("--seconds", type=float, default=1.0)
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        results = {
            f"reference {args.reference}": measure(reference_elf(args.reference, Path(tmp)), args.seconds),
            "current": measure(cached_firmware(), args.seconds),
        }
    for label, r in results.items():
        s = r["sizes"]
        print(
            f"\n{label}: {r['ticks_per_s']:.1f} ticks/s, busy {r['busy']:.0f} cycles/tick "
            f"({100 * r['busy'] / BUDGET:.1f} % of {BUDGET}), worst 10-tick mean {r['worst']:.0f}; "
            f"flash {s.flash} B, static RAM {s.static_ram} B, "
            f"stack {r['stack']} B; UART bytes lost {r['rx_lost']}"
        )
        for name, cycles in sorted(r["parts"].items(), key=lambda kv: -kv[1])[:12]:
            print(f"  {cycles:8.0f}  {name}")
    worst, at, first_tick = phase_sweep(cached_firmware())
    print(
        f"\ncurrent, command arriving at 16 points of the tick: worst steady-state tick {worst} cycles "
        f"({100 * worst / BUDGET:.1f} %, command {at} cycles after the tick), worst tick of a session's "
        f"first command {first_tick} ({100 * first_tick / BUDGET:.1f} %)"
    )
    after = results["current"]["busy"]
    print(
        f"\nbusy cycles per tick: reference {results[f'reference {args.reference}']['busy']:.0f} "
        f"(whole period at {results[f'reference {args.reference}']['ticks_per_s']:.0f} ticks/s), "
        f"current {after:.0f}; target <= {0.6 * BUDGET:.0f}: {'met' if after <= 0.6 * BUDGET else 'NOT met'}"
    )


if __name__ == "__main__":
    main()
