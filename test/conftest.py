"""Fixtures shared by several test files."""
from __future__ import annotations

from typing import Any

import pytest

from radar_calib_ros.config import CalibConfig
from radar_calib_ros.io.bag import read_recording
from radar_calib_ros.recording import Recording
from radar_calib_ros.sim import SimulationSummary, simulate


@pytest.fixture(scope='session')
def sim(tmp_path_factory: pytest.TempPathFactory) -> SimulationSummary:
    """30 s of the baseline scenario: two passes of the calibration vehicle."""
    return simulate(tmp_path_factory.mktemp('short_drive') / 'bag', seed=5, duration_s=30.0)


@pytest.fixture(scope='session')
def config(sim: SimulationSummary) -> CalibConfig:
    return CalibConfig.from_file(sim.paths.params)


@pytest.fixture(scope='session')
def recording(sim: SimulationSummary, config: CalibConfig) -> Recording:
    return read_recording(sim.paths.bag, config)


@pytest.fixture(scope='session')
def drive(tmp_path_factory: pytest.TempPathFactory) -> Any:
    """150 s of the baseline scenario (five passes) and its configuration."""
    summary = simulate(tmp_path_factory.mktemp('drive') / 'bag', seed=3, duration_s=150.0)
    return summary, CalibConfig.from_file(summary.paths.params)
