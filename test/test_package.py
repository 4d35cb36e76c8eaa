"""Packaging: package.xml parses as ROS would parse it, and setup.py installs what ros2 run
and colcon need."""
from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def test_package_xml_parses_with_catkin_pkg() -> None:
    catkin_pkg = pytest.importorskip('catkin_pkg.package')  # in extras_require['test']
    pkg = catkin_pkg.parse_package(str(ROOT / 'package.xml'))
    assert pkg.name == 'radar_calib_ros'
    assert pkg.package_format == 3
    assert pkg.get_build_type() == 'ament_python'
    exec_deps = {d.name for d in pkg.exec_depends}
    for dep in ('rclpy', 'sensor_msgs', 'nav_msgs', 'geometry_msgs', 'std_srvs', 'tf2_msgs',
                'diagnostic_msgs', 'python3-numpy', 'python3-scipy', 'python3-pyproj',
                'python3-yaml'):
        assert dep in exec_deps
    assert 'python3-pytest' in {d.name for d in pkg.test_depends}


def test_setup_declares_entry_points_and_data() -> None:
    text = (ROOT / 'setup.py').read_text()
    assert "'calibrator = radar_calib_ros.node:main'" in text
    assert "'radar-calib = radar_calib_ros.cli:main'" in text
    assert "extras_require" in text and 'tests_require' not in text
    cfg = (ROOT / 'setup.cfg').read_text()
    assert re.search(r'script_dir=\$base/lib/radar_calib_ros', cfg)
    assert re.search(r'install_scripts=\$base/lib/radar_calib_ros', cfg)
    assert (ROOT / 'resource' / 'radar_calib_ros').is_file()


def test_core_never_imports_rclpy_or_rosbags() -> None:
    for path in (ROOT / 'radar_calib_ros' / 'core').glob('*.py'):
        text = path.read_text()
        assert not re.search(r'^\s*(import|from)\s+(rclpy|rosbags)', text, re.M), path
    for name in ('recording.py', 'vehicle_track.py', 'clocks.py', 'pipeline.py', 'config.py',
                 'types.py', 'result.py'):
        text = (ROOT / 'radar_calib_ros' / name).read_text()
        assert not re.search(r'^\s*(import|from)\s+rclpy', text, re.M), name
