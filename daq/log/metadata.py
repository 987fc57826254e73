"""Episode metadata as MCAP metadata records (string maps), and back.

MCAP metadata values are strings: plain text stays plain (so Foxglove's
metadata panel shows it readably), structured values are JSON. Floats go
through JSON's repr, which round-trips float64 exactly.
"""

from __future__ import annotations

import json
from typing import Mapping

from qube_koopman.daq.episode import EpisodeMetadata
from qube_koopman.core.controller_file import STATE_SPACE_KIND, ControllerInfo, registered_controller_kinds
from qube_koopman.core.files import loads_json
from qube_koopman.daq.log.schema import FORMAT_VERSION

__all__ = [
    "EPISODE_RECORD",
    "CONTROLLER_RECORD",
    "STATUS_RECORD",
    "episode_records",
    "status_record",
    "metadata_from_records",
]

EPISODE_RECORD = "qube.episode"
CONTROLLER_RECORD = "qube.controller"
STATUS_RECORD = "qube.status"

# Written at the start, so a log cut short still says what it is.
_EPISODE_KEYS = (
    "format_version",
    "sample_rate_hz",
    "backend",
    "source",
    "start_time",
    "software_version",
    "excitation",
    "extra",
)
_CONTROLLER_KEYS = ("kind", "method", "gains", "dt", "A", "B", "C", "D")
# Added in 1.4 (a state-space controller's provenance); absent from older logs: empty. Added in 1.5
# (a registered kind's settings and the names of its per-tick record).
_OPTIONAL_CONTROLLER_KEYS = ("provenance", "settings", "tick_fields")


#: The kinds of controller the loop runs, and so the kinds a log may record (core/controller_file.py).
_CONTROLLER_KINDS = ("pd", STATE_SPACE_KIND)


def _parse(text: str):
    """A metadata value's JSON, nesting bounded (a ValueError, not a RecursionError, for a crafted one)."""
    return loads_json(text, "a metadata value")


def _json(value) -> str:
    return json.dumps(value, allow_nan=False, separators=(",", ":"))


def episode_records(meta: EpisodeMetadata) -> dict[str, dict[str, str]]:
    """The records written when an episode starts: name -> string map."""
    controller = meta.controller.as_dict()
    return {
        EPISODE_RECORD: {
            "format_version": FORMAT_VERSION,
            "sample_rate_hz": repr(meta.sample_rate_hz),
            "backend": meta.backend,
            "source": meta.source,
            "start_time": meta.start_time,
            "software_version": meta.software_version,
            "excitation": _json(dict(meta.excitation)),
            "extra": _json(dict(meta.extra)),
        },
        CONTROLLER_RECORD: {
            "kind": controller["kind"],
            "method": controller["method"],
            "gains": _json(controller["gains"]),
            "dt": repr(controller["dt"]),
            **{m: _json(controller[m]) for m in "ABCD"},
            "provenance": _json(controller["provenance"]),
            **{k: _json(controller[k]) for k in ("settings", "tick_fields") if k in controller},
        },
    }


def status_record(
    status: str, reason: str, n_samples: int, timing: Mapping | None = None, backend_stats: Mapping | None = None
) -> dict[str, str]:
    """The record written when an episode ends (``timing``, ``backend_stats``: JSON, only when given)."""
    record = {"status": status, "reason": reason, "n_samples": str(n_samples)}
    if timing:
        record["timing"] = _json(_finite(dict(timing)))
    if backend_stats:
        record["backend_stats"] = _json(dict(backend_stats))
    return record


def _finite(timing: dict) -> dict:
    # JSON has no NaN: a statistic that was not measured is written as null.
    return {k: None if isinstance(v, float) and v != v else v for k, v in timing.items()}


def _major(version: str) -> str:
    return version.split(".", 1)[0]


def _final_status(status: Mapping[str, str] | None, salvage_note: str) -> tuple[str, str]:
    """The episode's status and reason from the status record (None when lost) and what the reader salvaged."""
    skipped = "; skipped: " in salvage_note  # a damaged chunk skipped, samples lost in the middle
    if status is not None and not skipped:
        return status.get("status", ""), status.get("reason", "")
    if " is unusable: " in salvage_note:
        # A damaged record (flipped bits, a bad CRC) ends the readable part, not the writer;
        # a damaged chunk framed soundly is skipped, and the note says what it lost.
        reason = f"corrupted: {salvage_note}" + ("" if skipped else "; the samples after it are lost")
    else:
        reason = "no final status record: the writer stopped before finishing the episode"
    if status is not None:
        reason += f"; the log's final status: {status.get('status', '')}" + (
            f" ({status['reason']})" if status.get("reason") else ""
        )
    return "incomplete", reason


def metadata_from_records(
    records: Mapping[str, Mapping[str, str]], where: str, *, salvage_note: str = ""
) -> EpisodeMetadata:
    """Rebuild :class:`EpisodeMetadata` from the records of one file.

    Parameters
    ----------
    records : mapping
        Metadata record name -> string map, as found in the file.
    where : str
        The file, for messages.
    salvage_note : str
        Non-empty when the file was cut short or damaged: marks the
        metadata salvaged; without a status record the status is
        ``"incomplete"``.

    Raises
    ------
    ValueError
        Naming the file, when it is not an episode log, has an unsupported
        format version or malformed metadata.
    """
    if EPISODE_RECORD not in records:
        raise ValueError(f"{where}: not a QUBE episode log (no {EPISODE_RECORD!r} metadata record)")
    episode = records[EPISODE_RECORD]
    version = episode.get("format_version", "")
    if _major(version) != _major(FORMAT_VERSION):
        raise ValueError(
            f"{where}: episode log format version {version!r} is not supported "
            f"(this reader reads {_major(FORMAT_VERSION)}.x)"
        )
    if CONTROLLER_RECORD not in records:
        raise ValueError(f"{where}: no {CONTROLLER_RECORD!r} metadata record")
    controller = records[CONTROLLER_RECORD]
    try:
        missing = [k for k in _EPISODE_KEYS if k not in episode] + [k for k in _CONTROLLER_KEYS if k not in controller]
        if missing:
            raise ValueError(f"missing metadata keys {', '.join(missing)}")
        kinds: tuple[str, ...] = _CONTROLLER_KINDS
        if controller["kind"] not in kinds:  # the entry points are scanned only for a kind beyond the built-in ones
            kinds += registered_controller_kinds()
        if controller["kind"] not in kinds:
            raise ValueError(
                f"unknown controller kind {controller['kind']!r} (a log records one of {', '.join(map(repr, kinds))})"
            )
        controller_info = ControllerInfo.from_dict(
            {
                "kind": controller["kind"],
                "method": controller["method"],
                "gains": _parse(controller["gains"]),
                "dt": float(controller["dt"]),
                **{m: _parse(controller[m]) for m in "ABCD"},
                **{k: _parse(controller[k]) for k in _OPTIONAL_CONTROLLER_KEYS if k in controller},
            }
        )
        status = records.get(STATUS_RECORD)
        timing = backend_stats = {}
        status_value, reason = _final_status(status, salvage_note)
        if status is not None:
            if "timing" in status:
                timing = _parse(status["timing"])
            if "backend_stats" in status:
                backend_stats = _parse(status["backend_stats"])
        return EpisodeMetadata(
            controller=controller_info,
            sample_rate_hz=float(episode["sample_rate_hz"]),
            backend=episode["backend"],
            source=episode["source"],
            start_time=episode["start_time"],
            excitation=_parse(episode["excitation"]),
            software_version=episode["software_version"],
            status=status_value,
            status_reason=reason,
            salvaged=bool(salvage_note),
            salvage_note=salvage_note,
            log_format_version=version,
            extra=_parse(episode["extra"]),
            timing=timing,
            backend_stats=backend_stats,
        )
    except (ValueError, TypeError, KeyError) as exc:
        raise ValueError(f"{where}: malformed episode metadata: {exc}") from None
