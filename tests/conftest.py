"""Shared fixtures. Slow artefacts are built once per test run."""

from __future__ import annotations

import os
import signal
from collections.abc import Iterator

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

from pathlib import Path

import pytest

from labrig.config import RigConfig, load_rig
from labrig.indenters import Indenter, load_indenter
from labrig.physics.mechanics import ContactTable
from labrig.sim.truth_config import true_contact_table
from labrig.testing.synthetic import SyntheticRun, record_synthetic

#: Modules whose tests keep wall-clock time (pseudo-terminals, real-time runs, rates, timeouts): marked
#: ``serial`` so that `make test` runs them alone, after the rest has run on every core (pytest-xdist).
#: A single such test elsewhere carries ``@pytest.mark.serial`` itself.
SERIAL_MODULES = frozenset({
    "test_bota_driver", "test_bota_pty", "test_calibration_rig", "test_campaign_stop", "test_cli_devices",
    "test_cnc_envelope", "test_crash_safety", "test_device_faults", "test_evk4", "test_grbl_driver", "test_grbl_pty",
    "test_machine_limits", "test_parent_watch", "test_pipeline_live", "test_procedure", "test_protocol_runner",
    "test_realtime", "test_registration_robust", "test_rig_ready", "test_serial_pty", "test_session_drain",
    "test_sim_live",
})


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    for item in items:
        if item.path.stem in SERIAL_MODULES:
            item.add_marker(pytest.mark.serial)


#: A short synthetic run used by many tests (about 1.5 M events).
SMALL_RUN = SyntheticRun(duration_s=3.0, peak_event_rate_hz=8e5, seed=11)


@pytest.fixture(scope="session")
def small_recording(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A finalized synthetic recording (read-only: copy it before changing it)."""
    path = tmp_path_factory.mktemp("recordings") / "small.h5"
    record_synthetic(path, SMALL_RUN)
    return path


@pytest.fixture(scope="session")
def rig() -> RigConfig:
    """The default rig (calibration/rig.toml); frozen, shared."""
    return load_rig()


@pytest.fixture(scope="session")
def sphere() -> Indenter:
    return load_indenter("sphere")


@pytest.fixture(scope="session")
def table(rig: RigConfig, sphere: Indenter) -> ContactTable:
    """The sphere's contact table (cached on disk after the first build)."""
    return true_contact_table(sphere, rig)


@pytest.fixture(scope="session")
def sphere_press(tmp_path_factory: pytest.TempPathFactory, rig: RigConfig, sphere: Indenter) -> Path:
    """One short virtual-rig probe (about 1 s): the sphere 0.8 mm deep at (1, -1) mm, 0.3 mm of shear, 4 mm/s
    (read-only: copy it before changing it)."""
    from labrig.sim.live import record_live
    from labrig.sim.motion import probing_path

    path = tmp_path_factory.mktemp("sphere-press") / "press.h5"
    tool = probing_path(rig, sphere, location_mm=(1.0, -1.0), depth_mm=0.8, shear_mm=0.3, normal_speed_mm_s=4.0,
                        shear_speed_mm_s=4.0, wait_s=0.05)
    record_live(path, rig, sphere, tool, realtime=False)
    return path


@pytest.fixture()
def time_limit_20s() -> Iterator[None]:
    """Fail a test that runs over 20 s (a hung socket, numba compiling on a cold cache) instead of hanging."""

    def expire(*_: object) -> None:
        raise TimeoutError("test ran over its 20 s limit")

    old = signal.signal(signal.SIGALRM, expire)
    signal.alarm(20)
    yield
    signal.alarm(0)
    signal.signal(signal.SIGALRM, old)
