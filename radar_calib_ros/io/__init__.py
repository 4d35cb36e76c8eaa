"""The package's edge to files and messages: rosbags (``bag``, ``messages``) and pyproj
(``geo``).

The names below are imported lazily: ``recording.py`` (core) imports ``io.geo``, and that
must not pull rosbags in through this ``__init__``.
"""
from __future__ import annotations

import importlib
from typing import Any

__all__ = ['BagReadError', 'DecodeError', 'LocalFrame', 'decode_navsatfix', 'decode_odometry',
           'decode_pointcloud', 'get_typestore', 'radar_topics', 'read_recording',
           'select_topics', 'write_bag']

_HOMES = {
    'BagReadError': 'radar_calib_ros.errors', 'DecodeError': 'radar_calib_ros.errors',
    'LocalFrame': 'radar_calib_ros.io.geo',
    'decode_navsatfix': 'radar_calib_ros.io.messages',
    'decode_odometry': 'radar_calib_ros.io.messages',
    'decode_pointcloud': 'radar_calib_ros.io.messages',
    'get_typestore': 'radar_calib_ros.io.messages',
    'radar_topics': 'radar_calib_ros.io.bag', 'read_recording': 'radar_calib_ros.io.bag',
    'select_topics': 'radar_calib_ros.io.bag', 'write_bag': 'radar_calib_ros.io.bag',
}


def __getattr__(name: str) -> Any:
    home = _HOMES.get(name)
    if home is None:
        raise AttributeError(f'module {__name__!r} has no attribute {name!r}')
    return getattr(importlib.import_module(home), name)
