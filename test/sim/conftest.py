"""Shared short simulations for the simulator tests (each simulated once per session)."""
from __future__ import annotations

from pathlib import Path

import pytest

from radar_calib_ros.sim import SimulationSummary, simulate


@pytest.fixture(scope='session')
def baseline_sim(tmp_path_factory: pytest.TempPathFactory) -> SimulationSummary:
    """90 s of the baseline scenario, default scatter model."""
    return simulate(tmp_path_factory.mktemp('sim') / 'baseline_bag', seed=7, duration_s=90.0)


@pytest.fixture(scope='session')
def model_sims(tmp_path_factory: pytest.TempPathFactory) -> dict[str, SimulationSummary]:
    """The same 90 s drive (seed, scenario) under each scatter model."""
    root: Path = tmp_path_factory.mktemp('models')
    return {model: simulate(root / model, seed=11, duration_s=90.0, scatter_model=model)
            for model in ('skin', 'interior', 'mixed')}
