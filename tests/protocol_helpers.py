"""Message generators shared by the protocol tests (hypothesis and seeded random)."""

from __future__ import annotations

import random

from hypothesis import strategies as st

from qube_koopman.firmware_protocol import MESSAGE_CLASSES, Command, Config, Message, Telemetry

# Tick rates the device accepts: 10..1000 Hz with a whole-microsecond period.
VALID_RATES = [r for r in range(10, 1001) if 1_000_000 % r == 0]


def message_strategy(cls: type[Message]) -> st.SearchStrategy[Message]:
    """Any message of ``cls`` that ``pack`` accepts."""
    args = {name: st.integers(low, high) for name, (low, high) in cls.field_ranges().items()}
    if cls is Config:
        args["rate_hz"] = st.sampled_from(VALID_RATES)
    return st.builds(cls, **args)


messages = st.one_of(*[message_strategy(cls) for cls in MESSAGE_CLASSES.values()])
u32 = st.integers(0, 0xFFFFFFFF)


def random_message(rng: random.Random) -> Message:
    """A random valid message, mostly telemetry and commands as on a real link."""
    cls = rng.choices(
        list(MESSAGE_CLASSES.values()),
        weights=[8 if c in (Telemetry, Command) else 1 for c in MESSAGE_CLASSES.values()],
    )[0]
    values = {}
    for name, (low, high) in cls.field_ranges().items():
        # Half the time small values: real counters are mostly small, and
        # their zero bytes make many short COBS blocks, the hard case.
        small = rng.random() < 0.5 and low <= 0 <= high
        values[name] = rng.randint(max(low, -100), min(high, 100)) if small else rng.randint(low, high)
    if cls is Config:
        values["rate_hz"] = rng.choice(VALID_RATES)
    return cls(**values)
