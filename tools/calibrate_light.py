"""Add the light's slope response to the ``ID.events.toml`` of every recording of virtual-rig campaigns.

A varied campaign calibrates each recording's sensor as it records it
(:func:`labrig.protocol.virtual_campaign.calibrate_own_camera`); campaigns recorded before the slope
response was part of that calibration have thresholds only. This records the calibration press on each
recording's own virtual rig (the rig file it carries) and writes the ``[shading]`` section beside its
thresholds, skipping sidecars that hold one already (``--redo``: not).

    .venv/bin/python tools/calibrate_light.py data/train-sensors data/train-shapes --workers 2
"""

from __future__ import annotations

import argparse
import sys
import tomllib
from dataclasses import dataclass
from pathlib import Path

from labrig.config import DEFAULT_CALIBRATION_DIR
from labrig.dataset import Dataset, events_sidecar_path
from labrig.executor import run_tasks
from labrig.pipeline.run_setup import rig_from_recording
from labrig.protocol.virtual_campaign import calibrate_own_light
from labrig.recording import Recording

#: The calibration press's seeds: this plus the recording's index in its campaign.
SEED_BASE = 700_000


@dataclass(frozen=True)
class LightTask:
    recording: str
    seed: int
    calibration_dir: str


def calibrate_task(task: LightTask) -> str:
    path = Path(task.recording)
    with Recording(path) as rec:
        rig = rig_from_recording(rec)
    if rig is None:
        raise ValueError(f"{path} carries no rig file: its virtual sensor is unknown")
    calibrate_own_light(rig, path, task.seed, task.calibration_dir)
    return str(path)


def pending(folders: list[Path], calibration_dir: str, redo: bool = False) -> list[LightTask]:
    tasks = []
    for folder in folders:
        for index, rec in enumerate(Dataset.open(folder).complete()):
            sidecar = events_sidecar_path(rec.path)
            if sidecar.exists() and (redo or "shading" not in tomllib.loads(sidecar.read_text())):
                tasks.append(LightTask(str(rec.path), SEED_BASE + index, calibration_dir))
    return tasks


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("data", nargs="+", type=Path, help="campaign folders")
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--calibration", default=DEFAULT_CALIBRATION_DIR, help="the rig's calibration folder")
    parser.add_argument("--redo", action="store_true", help="measure again where a slope response is already written")
    args = parser.parse_args(argv)
    tasks = pending(args.data, args.calibration, args.redo)
    print(f"{len(tasks)} sidecars to complete", flush=True)
    results = run_tasks(calibrate_task, tasks, workers=args.workers, use_cache=False, raise_on_error=False,
                        on_result=lambda i, path: print(path, flush=True))
    for failure in results.failures:
        print(f"FAILED {tasks[failure.index].recording}: {failure.error}: {failure.message}", file=sys.stderr)
    return 1 if results.failures else 0


if __name__ == "__main__":
    sys.exit(main())
