"""The per-sample message of the episode log: ros2msg schema text and CDR layout.

One message per sample, every field a scalar, so Foxglove plots each one on
its timeline. The layout is fixed (all float64 first, then one int8), so a
run of messages decodes in bulk with ``np.frombuffer`` and a structured dtype
instead of per-message Python work. See FORMAT.md.
"""

from __future__ import annotations

import numpy as np

from qube_koopman.daq.episode import SIGNALS, UNITS

__all__ = [
    "FORMAT_VERSION",
    "SAMPLE_TOPIC",
    "SAMPLE_SCHEMA_NAME",
    "CDR_LE_HEADER",
    "sample_fields",
    "schema_text",
    "parse_schema",
    "payload_dtype",
]

#: Version of the episode log format; readers accept the same major version.
FORMAT_VERSION = "1.5"

SAMPLE_TOPIC = "/qube/sample"
SAMPLE_SCHEMA_NAME = "qube_msgs/msg/EpisodeSample"

#: CDR encapsulation header: plain CDR, little endian, no options.
CDR_LE_HEADER = b"\x00\x01\x00\x00"

# ros2msg primitive types the reader understands, with their numpy types.
_ROS_TYPES = {
    "float64": "<f8",
    "float32": "<f4",
    "int8": "i1",
    "uint8": "u1",
    "int16": "<i2",
    "uint16": "<u2",
    "int32": "<i4",
    "uint32": "<u4",
    "int64": "<i8",
    "uint64": "<u8",
    "bool": "?",
    "byte": "u1",
    "char": "u1",
}


def state_field(i: int) -> str:
    """Name of the message field holding controller state ``i``."""
    return f"controller_state_{i}"


def sample_fields(n_controller_states: int, tick_fields: tuple[str, ...] = ()) -> list[tuple[str, str]]:
    """Fields of one sample message as (name, ros2msg type), in wire order.

    ``tick_fields``: the per-tick record of a controller beyond LTI (e.g. the MPC's solver status),
    float64 fields after the controller's state (added in 1.5).
    """
    return (
        [(name, "float64") for name in SIGNALS]
        + [(state_field(i), "float64") for i in range(n_controller_states)]
        + [(name, "float64") for name in tick_fields]
        + [("saturation", "int8")]
    )


def schema_text(n_controller_states: int, tick_fields: tuple[str, ...] = ()) -> str:
    """The ros2msg definition of one sample message."""
    lines = [
        f"# One tick of a QUBE-Servo episode (episode log format {FORMAT_VERSION}).",
        "# Units: s, rad, V; controller_state_i in the controller's realization.",
    ]
    for name, ros_type in sample_fields(n_controller_states, tick_fields):
        if name.startswith("controller_state_"):
            unit = UNITS["controller_state"]
        else:
            unit = UNITS.get(name, "the controller's per-tick record")
        lines.append(f"{ros_type} {name}  # {unit}")
    return "\n".join(lines) + "\n"


def parse_schema(text: str) -> list[tuple[str, str]]:
    """Fields of a ros2msg definition made only of primitive scalars.

    Raises
    ------
    ValueError
        On a field that is not a primitive scalar (arrays, strings, nested
        messages, constants): the episode log never writes those.
    """
    result = []
    for line in text.splitlines():
        line = line.split("#", 1)[0].strip()
        if not line:
            continue
        parts = line.split()
        if len(parts) != 2 or parts[0] not in _ROS_TYPES or "=" in line:
            raise ValueError(f"unsupported schema line {line!r} (only primitive scalar fields)")
        result.append((parts[1], parts[0]))
    return result


def payload_dtype(fields: list[tuple[str, str]]) -> np.dtype:
    """Structured dtype of one CDR payload, the 4-byte encapsulation header included.

    Classic CDR aligns each primitive to its own size (at most 8) relative
    to the end of the encapsulation header.
    """
    names, offsets = ["cdr_header"], [0]
    formats: list[str | np.dtype] = ["<u4"]
    pos = 0
    for name, ros_type in fields:
        dtype = np.dtype(_ROS_TYPES[ros_type])
        align = min(dtype.itemsize, 8)
        pos += -pos % align
        names.append(name)
        formats.append(dtype)
        offsets.append(4 + pos)
        pos += dtype.itemsize
    return np.dtype({"names": names, "formats": formats, "offsets": offsets, "itemsize": 4 + pos})
