"""Episodes out to the tools people already use: legacy CSV, Parquet, MATLAB, pandas.

Formats (one file per episode, named after the log: ``<log stem>.<ext>``):

``csv``
    The legacy rig's layout, byte for byte as the rig wrote it (and as
    ``qube-import`` reads it): a header line
    ``t, target_theta, target_alpha, theta, alpha, control_output, feedforward, plant_input, saturation``
    then one row per tick, every value printed ``%.17e`` (which round-trips
    float64 exactly), separated by ``", "``, ``\\n`` line ends. Only these
    nine columns: the controller state is recomputed on import, the
    metadata lives in the file name (start time, seeds) and the
    ``controller.toml`` beside it. Exporting an imported dataset file gives
    back the original bytes. The layout has no status: for an episode that
    did not complete (aborted, or a log cut short and salvaged) the status
    goes beside the CSV, in ``<log stem>.status.json`` (keys ``status``,
    ``reason``, ``salvaged``, ``salvage_note``, ``samples``), written before
    the CSV, and ``qube-import`` gives the episode that status back; a
    complete episode's export removes a status file left there by an
    earlier one. The layout is evenly spaced in time: a log that lost
    samples (a damaged chunk skipped when it was read) is written with the
    jump in ``t``, which ``qube-import`` refuses, and the export warns so
    (:class:`CsvGapWarning`; parquet and mat keep such a log whole).
``parquet``
    One table per episode: every per-sample array as a float64 column
    (``saturation`` int8, ``controller_state`` as ``controller_state_0``...),
    each field's unit in its field metadata (``unit``), and the episode's
    metadata in the schema metadata: keys ``qube.episode``,
    ``qube.controller`` and ``qube.status``, each a JSON object of the
    string map the MCAP log holds (daq/log/FORMAT.md). Needs pyarrow.
``mat``
    MATLAB 5 ``.mat`` (scipy.io): one column vector per signal,
    ``controller_state`` as an n x k matrix, and a struct ``metadata`` whose
    fields ``episode``, ``controller`` and ``status`` hold the same string
    maps (structured values as JSON text: ``jsondecode`` them in MATLAB).

:func:`episode_frame` gives a pandas DataFrame (pandas is optional).
"""

from __future__ import annotations

import io
import json
import warnings
from pathlib import Path

import numpy as np

from qube_koopman.daq.episode import UNITS, Episode, stack_signals
from qube_koopman.daq.legacy_csv import LEGACY_COLUMNS, status_sidecar
from qube_koopman.core.files import atomic_path

__all__ = [
    "FORMATS",
    "CsvGapWarning",
    "ExportError",
    "episode_columns",
    "metadata_records",
    "episode_frame",
    "legacy_csv_bytes",
    "write_csv",
    "write_parquet",
    "write_mat",
    "export_episode",
]

#: Format name -> file extension.
FORMATS = {"csv": ".csv", "parquet": ".parquet", "mat": ".mat"}


class ExportError(ValueError):
    """An episode that cannot be exported; the message names the file and the problem."""


class CsvGapWarning(UserWarning):
    """An episode exported to CSV with a jump in time (lost samples): ``qube-import`` will refuse the file."""


def _time_gap(episode: Episode) -> tuple[int, float] | None:
    """The first jump in the episode's time stamps as ``(samples missing, t before it)``, or ``None``.

    A jump is a step longer than 1.5 sample periods (the median step).
    """
    t = np.asarray(episode.t, float)
    if t.size < 3:
        return None
    steps = np.diff(t)
    period = float(np.median(steps))
    jumps = np.flatnonzero(steps > 1.5 * period)
    if not jumps.size:
        return None
    k = int(jumps[0])
    return int(round(steps[k] / period)) - 1, float(t[k])


def episode_columns(episode: Episode) -> dict[str, np.ndarray]:
    """The per-sample arrays as flat columns, the controller state split into ``controller_state_<i>``."""
    columns: dict[str, np.ndarray] = {}
    for name, value in episode.arrays().items():
        if name == "controller_state":
            columns.update({f"controller_state_{i}": value[:, i] for i in range(value.shape[1])})
        elif name == "controller_record":  # a controller beyond LTI's per-tick record, by its field names
            columns.update(dict(zip(episode.metadata.controller.tick_fields, value.T)))
        else:
            columns[name] = value
    return columns


def metadata_records(episode: Episode) -> dict[str, dict[str, str]]:
    """The episode's metadata as the log's string maps (``qube.episode``, ``qube.controller``, ``qube.status``)."""
    from qube_koopman.daq.log.metadata import STATUS_RECORD, episode_records, status_record

    meta = episode.metadata
    records = episode_records(meta)
    records[STATUS_RECORD] = status_record(
        meta.status, meta.status_reason, len(episode), meta.timing, meta.backend_stats
    )
    return records


def _unit(column: str) -> str:
    if column.startswith("controller_state_"):
        return UNITS["controller_state"]
    return UNITS.get(column, "")  # a controller's per-tick record: its units are the controller's


def episode_frame(episode: Episode):
    """The episode as a pandas DataFrame, one row per tick.

    Columns as :func:`episode_columns`; ``frame.attrs`` holds
    ``"metadata"`` (:func:`metadata_records`) and ``"units"``.

    Raises
    ------
    ImportError
        If pandas is not installed (it is optional: ``pip install "qube-koopman[pandas]"``).
    """
    try:
        import pandas as pd
    except ImportError:
        raise ImportError(
            'episode_frame needs pandas, which is optional: pip install "qube-koopman[pandas]" (or pip install pandas)'
        ) from None
    columns = episode_columns(episode)
    frame = pd.DataFrame(columns)
    frame.attrs["metadata"] = metadata_records(episode)
    frame.attrs["units"] = {name: _unit(name) for name in columns}
    return frame


def legacy_csv_bytes(episode: Episode) -> bytes:
    """The episode in the legacy rig's CSV layout (see the module docstring)."""
    data = stack_signals(episode, LEGACY_COLUMNS)
    buffer = io.StringIO()
    np.savetxt(buffer, data, fmt="%.17e", delimiter=", ", header=", ".join(LEGACY_COLUMNS), comments="")
    return buffer.getvalue().encode("ascii")


def write_csv(episode: Episode, path: str | Path) -> None:
    """Write the episode as a legacy-layout CSV file, and the status of one that did not complete beside it.

    See the module's docstring (``csv``) for the status file.
    """
    path, sidecar = Path(path), status_sidecar(path)
    if episode.is_complete:
        sidecar.unlink(missing_ok=True)
    else:
        meta = episode.metadata
        with atomic_path(sidecar) as tmp:
            tmp.write_text(
                json.dumps(
                    {
                        "status": meta.status,
                        "reason": meta.status_reason,
                        "salvaged": meta.salvaged,
                        "salvage_note": meta.salvage_note,
                        "samples": len(episode),
                    },
                    indent=2,
                )
                + "\n"
            )
    content = legacy_csv_bytes(episode)
    with atomic_path(path) as tmp:
        tmp.write_bytes(content)
    gap = _time_gap(episode)
    if gap is not None:
        warnings.warn(
            f"{path}: {gap[0]} samples missing after t = {gap[1]:.3f} s (lost when the log was read); "
            "the CSV layout is evenly spaced, so qube-import will refuse this file: "
            "--format parquet or mat keep the episode as it is",
            CsvGapWarning,
            stacklevel=2,
        )


def _pyarrow():
    try:
        import pyarrow
        import pyarrow.parquet
    except ImportError:
        raise ExportError(
            "--format parquet needs pyarrow (pip install pyarrow; it comes with the [viz] extra's rerun-sdk)"
        ) from None
    return pyarrow


def write_parquet(episode: Episode, path: str | Path) -> None:
    """Write the episode as one Parquet table with its metadata attached.

    Raises
    ------
    ExportError
        If pyarrow is not installed.
    """
    pa = _pyarrow()
    columns = episode_columns(episode)
    fields = [
        pa.field(name, pa.from_numpy_dtype(value.dtype), metadata={"unit": _unit(name)})
        for name, value in columns.items()
    ]
    metadata = {key: json.dumps(value, separators=(",", ":")) for key, value in metadata_records(episode).items()}
    table = pa.Table.from_arrays([pa.array(v) for v in columns.values()], schema=pa.schema(fields, metadata=metadata))
    with atomic_path(path) as tmp:
        pa.parquet.write_table(table, str(tmp))


def write_mat(episode: Episode, path: str | Path) -> None:
    """Write the episode as a MATLAB ``.mat`` file (column vectors and a ``metadata`` struct)."""
    from scipy.io import savemat

    arrays = {name: (value.reshape(-1, 1) if value.ndim == 1 else value) for name, value in episode.arrays().items()}
    records = metadata_records(episode)
    metadata = {name.split(".", 1)[1]: dict(record) for name, record in records.items()}
    with atomic_path(path) as tmp:
        savemat(str(tmp), {**arrays, "metadata": metadata}, do_compression=True, oned_as="column")


_WRITERS = {"csv": write_csv, "parquet": write_parquet, "mat": write_mat}


def export_episode(log: str | Path, fmt: str, out_dir: str | Path, *, overwrite: bool = False) -> Path:
    """Read one episode log and write it to ``out_dir/<log stem>.<ext>``.

    Parameters
    ----------
    log : str or Path
        The ``.mcap`` episode log.
    fmt : {"csv", "parquet", "mat"}
        Output format.
    out_dir : str or Path
        Output folder (created if missing).
    overwrite : bool
        Replace an existing output file (otherwise it is an error).

    Returns
    -------
    Path
        The file written.

    Raises
    ------
    ExportError
        Naming the log and the problem: unreadable, not an episode log,
        output exists, unknown format, pyarrow missing.
    """
    log, out_dir = Path(log), Path(out_dir)
    if fmt not in FORMATS:
        raise ExportError(f"unknown format {fmt!r} (choose from {', '.join(FORMATS)})")
    out = out_dir / f"{log.stem}{FORMATS[fmt]}"
    if out.exists() and not overwrite:
        raise ExportError(f"{log}: {out} exists (use --force to overwrite)")
    if fmt == "parquet":
        _pyarrow()  # fail before reading, with the install hint
    from qube_koopman.daq.log import read_episode

    try:
        episode = read_episode(log)
    except OSError as exc:
        raise ExportError(f"{log}: cannot read ({exc.strerror or exc})") from None
    except ValueError as exc:
        message = str(exc)
        raise ExportError(message if message.startswith(str(log)) else f"{log}: {message}") from None
    out_dir.mkdir(parents=True, exist_ok=True)
    try:
        _WRITERS[fmt](episode, out)
    except OSError as exc:
        raise ExportError(f"{log}: cannot write {out}: {exc.strerror or exc}") from None
    return out
