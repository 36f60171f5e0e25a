"""Finalizing a recording: final clock models, exit status, and the commit rules.

Used by the writer on a clean close and by ``labrig recover`` on a crashed file.
"""

from __future__ import annotations

import time
from pathlib import Path

import h5py
import numpy as np

from labrig.clock import ClockModel, unwrap_counter
from labrig.clock_fit import UNKNOWN_LATEST_US, align_trigger_edges, fit_lower_envelope, fit_triggers, match_trigger_edges
from labrig.recording import schema
from labrig.recording.layout import stream_group

#: A camera trigger edge pairs with a known host edge within this distance (and within half the
#: spacing of the host's edges of its polarity): a line that reached a starved controller late
#: makes an edge tens of ms after its host stamp; the clock fit then leaves it below its line.
TRIGGER_MATCH_TOLERANCE_US = 100_000.0


def committed_rows(f: h5py.File) -> dict[str, int] | None:
    """Per-stream rows guaranteed on disk by the last commit (``None``: no commit yet)."""
    commits = f.get(schema.COMMITS_PATH)
    if commits is None or commits["rows"].shape[0] == 0:
        return None
    last = commits["rows"][-1]
    return {name: int(n) for name, n in zip(commits.attrs["streams"], last)}


def fit_clock_models(f: h5py.File, rows: dict[str, int] | None = None) -> dict[str, ClockModel]:
    """Refit every device's clock model over the whole recording."""

    def column(stream: str, name: str, missing: int | None = None) -> np.ndarray:
        """A column's committed rows; a column the file predates reads as ``missing`` (if given)."""
        group = stream_group(f, stream)
        if name not in group and missing is not None:
            return np.full(column(stream, "t_host_us").shape[0], missing, np.int64)
        ds = group[name]
        n = ds.shape[0] if rows is None else min(ds.shape[0], rows.get(stream, ds.shape[0]))
        return ds[:n]

    models: dict[str, ClockModel] = {}
    ft_device = unwrap_counter(column("ft", "t_device_us"), 32)
    if ft_device.size:
        models["ft"] = fit_lower_envelope(ft_device, column("ft", "t_host_us"))

    cam_device, cam_host = column("event_packets", "t_device_us"), column("event_packets", "t_host_us")
    envelope = fit_lower_envelope(cam_device, cam_host) if cam_device.size else None
    camera = _fit_camera_triggers(column, envelope)
    if camera is not None:
        models["camera"] = camera.with_residuals(cam_device, cam_host)
    return models


def _fit_camera_triggers(column, envelope: ClockModel | None) -> ClockModel | None:  # type: ignore[no-untyped-def]
    edges_dev, edges_pol = column("triggers", "t_device_us"), column("triggers", "polarity")
    known_host, known_pol = column("trigger_out", "t_host_us"), column("trigger_out", "polarity")
    known_latest = column("trigger_out", "t_latest_host_us", missing=UNKNOWN_LATEST_US)
    if edges_dev.size == 0 or known_host.size == 0:
        return envelope
    if envelope is None:
        if edges_dev.size != known_host.size:
            return None
        return fit_triggers(edges_dev, known_host, latest_host_us=known_latest)
    pairs_dev: list[np.ndarray] = []
    pairs_host: list[np.ndarray] = []
    pairs_latest: list[np.ndarray] = []
    for polarity in (0, 1):
        dev, host = edges_dev[edges_pol == polarity], known_host[known_pol == polarity]
        latest = known_latest[known_pol == polarity]
        spacing = np.diff(np.sort(host)).min() / 2 if host.size > 1 else TRIGGER_MATCH_TOLERANCE_US
        tolerance = min(spacing, TRIGGER_MATCH_TOLERANCE_US)
        di, hi = match_trigger_edges(dev, host, envelope, tolerance)
        if di.size < min(dev.size, host.size):
            # The envelope's offset includes the camera's minimum latency, which can exceed the
            # tolerance: align the edges' interval pattern instead, on device times mapped with
            # the envelope's drift (hundreds of ppm stretch the pattern past the tolerance over
            # a minute) or, where the envelope is far off under load, as they are.
            for mapped in (envelope.to_host_us(dev), dev):
                ai, ah = align_trigger_edges(mapped, host, tolerance)
                if ai.size > di.size:
                    di, hi = ai, ah
        pairs_dev.append(dev[di])
        pairs_host.append(host[hi])
        pairs_latest.append(latest[hi])
    dev, host = np.concatenate(pairs_dev), np.concatenate(pairs_host)
    return fit_triggers(dev, host, fallback=envelope, latest_host_us=np.concatenate(pairs_latest)) if dev.size else envelope


def store_clock_model(path: Path, device: str, model: ClockModel) -> None:
    """Replace the stored clock model of ``device`` in a finalized recording (``method`` as the model says).

    For a rig that does not resync a device's clock: the recording then maps that device's
    time with ``model`` (e.g. an offset and drift from a sync long before) instead of the fit
    over its own data. The fit's residual attributes are left out, the model has none.
    """
    with h5py.File(path, "r+") as f:
        if not f.attrs.get("finalized", False):
            raise ValueError(f"{path} is not finalized; store a clock model after the recording is closed")
        if device in f["clock"]:
            del f["clock"][device]
        group = f["clock"].create_group(device)
        for key, value in model.to_attrs().items():
            group.attrs[key] = value


def finalize_file(
    path: Path,
    exit_status: str,
    reason: str,
    online_models: dict[str, ClockModel] | None = None,
    rows: dict[str, int] | None = None,
    attrs: dict[str, str | int | float | bool] | None = None,
) -> dict[str, ClockModel]:
    """Store the final clock models, exit status and ``attrs`` (root attributes) in a closed recording file."""
    with h5py.File(path, "r+") as f:
        for key, value in (attrs or {}).items():
            f.attrs[key] = value
        models = fit_clock_models(f, rows)
        for device, model in models.items():
            group = f["clock"].require_group(device)
            for key, value in model.to_attrs().items():
                group.attrs[key] = value
            online = (online_models or {}).get(device)
            if online is not None:
                group.attrs["online_drift_ppm"] = online.drift_ppm
                group.attrs["online_drift_uncertainty_ppm"] = online.drift_uncertainty_ppm
        f.attrs["exit_status"] = exit_status
        f.attrs["exit_reason"] = reason
        f.attrs["finalized"] = True
        f.attrs["ended"] = time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())
    return models
