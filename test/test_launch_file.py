"""launch/calibrator.launch.py: loads and declares its two arguments (needs ROS launch)."""
from __future__ import annotations

import importlib.util
from pathlib import Path

import pytest

launch = pytest.importorskip('launch')
launch_ros_actions = pytest.importorskip('launch_ros.actions')

LAUNCH_FILE = Path(__file__).resolve().parents[1] / 'launch' / 'calibrator.launch.py'


def test_launch_file_declares_params_file_and_namespace() -> None:
    spec = importlib.util.spec_from_file_location('calibrator_launch', LAUNCH_FILE)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    description = module.generate_launch_description()
    assert isinstance(description, launch.LaunchDescription)
    names = [argument.name for argument in description.get_launch_arguments()]
    assert names == ['params_file', 'namespace']
    nodes = [e for e in description.entities if isinstance(e, launch_ros_actions.Node)]
    assert len(nodes) == 1
