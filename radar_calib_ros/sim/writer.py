"""Writing a simulation: the rosbag2 bag and, inside its directory, the ground truth.

The bag holds the three input topics of CONTRACT.md with real ROS 2 Jazzy types, written
in receive order (header stamp + a transport latency per sensor): ``/radar/points``
(PointCloud2, frame ``radar``), ``/vehicle/fix`` (NavSatFix) and ``/vehicle/odom``
(Odometry, absent in ``navsat_only``). Beside ``metadata.yaml`` and the storage file go
``ground_truth.json`` (the true calibration in the contract's result layout plus what the
simulator knows), ``params.yaml`` (the parameters a user would write for this drive) and
``ground_truth_targets.npz`` (every target's origin, for the oracle baseline and tests;
the calibration tool never reads any of these).
"""
from __future__ import annotations

import json
import zipfile
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from radar_calib_ros.io import messages as msgs
from radar_calib_ros.io.bag import write_bag
from radar_calib_ros.result import write_atomic
from radar_calib_ros.sim.gnss import GnssStreams
from radar_calib_ros.sim.radar import RadarTargets

RADAR_TOPIC = '/radar/points'
NAVSAT_TOPIC = '/vehicle/fix'
ODOM_TOPIC = '/vehicle/odom'
GROUND_TRUTH_FILE = 'ground_truth.json'
PARAMS_FILE = 'params.yaml'
TARGETS_FILE = 'ground_truth_targets.npz'


def write_recording(path: Path, *, targets: RadarTargets, radar_stamps_ns: np.ndarray,
                    radar_receive_ns: np.ndarray, gnss: GnssStreams,
                    gnss_stamps_ns: np.ndarray, fix_receive_ns: np.ndarray,
                    odom_receive_ns: np.ndarray | None, layout: str, velocity_field: str,
                    storage: str) -> int:
    """Write the bag; returns the number of messages.

    Parameters
    ----------
    targets : RadarTargets
        Sorted by frame; frame f is published with stamp ``radar_stamps_ns[f]``.
    odom_receive_ns : ndarray or None
        None leaves the Odometry topic out.
    """
    store = msgs.get_typestore()
    n_frames = radar_stamps_ns.size
    bounds = np.searchsorted(targets.frame, np.arange(n_frames + 1))
    positions = targets.position_m.astype(np.float32, copy=False)
    velocity = targets.radial_velocity_mps.astype(np.float32, copy=False)
    rcs = targets.rcs_dbsm.astype(np.float32, copy=False)
    # (receive time, topic rank, index), merged into one receive-ordered stream
    keys = [np.column_stack([radar_receive_ns, np.zeros(n_frames, np.int64),
                             np.arange(n_frames)]),
            np.column_stack([fix_receive_ns, np.ones(fix_receive_ns.size, np.int64),
                             np.arange(fix_receive_ns.size)])]
    if odom_receive_ns is not None:
        keys.append(np.column_stack([odom_receive_ns,
                                     np.full(odom_receive_ns.size, 2, np.int64),
                                     np.arange(odom_receive_ns.size)]))
    order = np.concatenate(keys)
    order = order[np.lexsort((order[:, 2], order[:, 1], order[:, 0]))]

    def messages() -> Iterator[tuple[str, str, int, object]]:
        for receive, topic, i in order.tolist():
            if topic == 0:
                a, b = bounds[i], bounds[i + 1]
                msg = msgs.encode_pointcloud(
                    store, int(radar_stamps_ns[i]), 'radar', positions[a:b], velocity[a:b],
                    layout=layout, dtype=np.float32, velocity_field=velocity_field,
                    extra_fields={'rcs': rcs[a:b]})
                yield RADAR_TOPIC, msgs.POINTCLOUD2, receive, msg
            elif topic == 1:
                msg = msgs.encode_navsatfix(
                    store, int(gnss_stamps_ns[i]), 'gnss', float(gnss.lat_deg[i]),
                    float(gnss.lon_deg[i]), float(gnss.alt_m[i]), int(gnss.status[i]),
                    0.02 if gnss.status[i] >= 0 else 5.0)
                yield NAVSAT_TOPIC, msgs.NAVSATFIX, receive, msg
            else:
                msg = msgs.encode_odometry(
                    store, int(gnss_stamps_ns[i]), 'utm', 'base_link', gnss.odom_position_m[i],
                    gnss.quaternion_xyzw[i], gnss.velocity_body_mps[i],
                    float(gnss.yaw_rate_rps[i]))
                yield ODOM_TOPIC, msgs.ODOMETRY, receive, msg

    return write_bag(path, messages(), storage=storage, typestore=store)


def write_ground_truth(path: Path, truth: Mapping[str, Any]) -> None:
    """``ground_truth.json`` (atomic)."""
    write_atomic(path, json.dumps(dict(truth), indent=2) + '\n')


def write_params(path: Path, *, odometry: bool, vehicle: Mapping[str, float],
                 header: str) -> None:
    """``params.yaml``: topics and the calibration vehicle (a ROS 2 parameters file)."""
    params: dict[str, Any] = {
        'radar_topic': RADAR_TOPIC,
        'navsat_topic': NAVSAT_TOPIC,
        # an explicitly empty topic turns the role off: navsat_only has no Odometry
        'odom_topic': ODOM_TOPIC if odometry else '',
        'radar': {'frame_id': 'radar'},
        'vehicle': {**{k: float(v) for k, v in vehicle.items()}, 'odom_is_utm': True},
    }
    text = yaml.safe_dump({'/**': {'ros__parameters': params}}, sort_keys=False)
    write_atomic(path, ''.join(f'# {line}\n' for line in header.splitlines()) + text)


def write_targets(path: Path, arrays: Mapping[str, np.ndarray]) -> None:
    """``ground_truth_targets.npz``: an ordinary ``np.load``-able archive, deflated at the
    fastest level (``np.savez_compressed``'s default level takes longer than simulating)."""
    with zipfile.ZipFile(path, 'w', compression=zipfile.ZIP_DEFLATED, compresslevel=1,
                         allowZip64=True) as archive:
        for name, array in arrays.items():
            with archive.open(f'{name}.npy', 'w', force_zip64=True) as fh:
                np.lib.format.write_array(fh, np.asanyarray(array), allow_pickle=False)
