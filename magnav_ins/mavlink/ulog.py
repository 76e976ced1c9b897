"""PX4 ULog reading: the only module that imports ``pyulog``.

ULog timestamps are microseconds on the autopilot's boot clock; :func:`read_ulog_topic` returns them as float
seconds ``t`` on the same clock. Field names are ULog's own (``magnetometer_ga[0]``); units are whatever the
topic defines (gauss for ``magnetometer_ga``, rad/s for ``gyro_rad``, m/s^2 for ``accelerometer_m_s2``); convert
at the caller with :mod:`magnav_ins.core.units`.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
from numpy.typing import NDArray
from pyulog import ULog

from ..core.errors import InputError

US_TO_S = 1e-6


def read_ulog_topic(
    path: str | Path, topic: str, fields: Sequence[str] | None = None, *, multi_id: int = 0
) -> dict[str, NDArray[np.float64]]:
    """Read one topic of a ULog file: ``{"t": seconds (N,), field: values (N,), ...}``.

    ``fields`` selects fields by their ULog names (all fields when ``None``); ``"timestamp"`` is always read and
    returned as ``t`` [s]. A missing file, topic or field raises :class:`InputError` naming it and listing what
    exists.
    """
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: no such ULog file")
    try:
        ulog = ULog(str(path), [topic])
    except Exception as exc:  # pyulog raises bare exceptions on corrupt input
        raise InputError(f"{path}: cannot read as ULog ({exc})") from exc
    datasets = [d for d in ulog.data_list if d.name == topic and d.multi_id == multi_id]
    if not datasets:
        try:
            names = sorted({d.name for d in ULog(str(path)).data_list})
        except Exception:  # pragma: no cover - the first read succeeded
            names = []
        raise InputError(f"{path}: no topic {topic!r} (multi_id {multi_id}); topics: {', '.join(names)}")
    data = datasets[0].data
    wanted = list(data) if fields is None else list(fields)
    missing = [f for f in wanted if f not in data]
    if missing:
        raise InputError(
            f"{path}: topic {topic!r} has no field {missing[0]!r}; fields: {', '.join(k for k in data if k != 'timestamp')}"
        )
    out: dict[str, NDArray[np.float64]] = {"t": np.asarray(data["timestamp"], dtype=np.float64) * US_TO_S}
    for name in wanted:
        if name != "timestamp":
            out[name] = np.asarray(data[name], dtype=np.float64)
    return out
