"""Writing a simulation: the rosbag2 bag and, inside its directory, the ground truth.

The bag holds the three input topics of CONTRACT.md with real ROS 2 Jazzy types, written
in receive order (header stamp + a transport latency per sensor): ``/radar/points``
(PointCloud2, frame ``radar``), ``/vehicle/fix`` (NavSatFix) and ``/vehicle/odom``
(Odometry, absent in ``navsat_only``). Beside ``metadata.yaml`` and the storage file go
``ground_truth.json`` (the true calibration in the contract's result layout plus what the
simulator knows), ``params.yaml`` (the parameters a user would write for this drive) and
``ground_truth_targets.npz`` (every target's origin, for the oracle baseline and tests;
the calibration tool never reads any of these).

A recording of several radars (scenario ``more_radars``) has one topic per radar,
``/radar_1/points`` ... with frames ``radar_1`` ..., and per radar ``ground_truth_<frame>.json``
and ``ground_truth_targets_<frame>.npz``; ``ground_truth.json`` and
``ground_truth_targets.npz`` stay those of ``radar_1`` (so single-radar readers still work),
the former listing every radar under ``radars``.
"""
from __future__ import annotations

import json
import zipfile
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass
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


def ground_truth_file(frame_id: str) -> str:
    """Name of one radar's ground truth in a multi-radar recording."""
    return f'ground_truth_{frame_id}.json'


def targets_file(frame_id: str) -> str:
    """Name of one radar's target origins in a multi-radar recording."""
    return f'ground_truth_targets_{frame_id}.npz'


@dataclass(frozen=True)
class RadarStream:
    """One more radar of a multi-radar recording: its topic, frame id, targets (sorted by
    frame), header stamps and receive times per frame."""

    topic: str
    frame_id: str
    targets: RadarTargets
    stamps_ns: np.ndarray
    receive_ns: np.ndarray


def write_recording(path: Path, *, targets: RadarTargets, radar_stamps_ns: np.ndarray,
                    radar_receive_ns: np.ndarray, gnss: GnssStreams,
                    gnss_stamps_ns: np.ndarray, fix_receive_ns: np.ndarray,
                    odom_receive_ns: np.ndarray | None, layout: str, velocity_field: str,
                    storage: str, radar_topic: str = RADAR_TOPIC, radar_frame: str = 'radar',
                    extra_radars: Sequence[RadarStream] = (),
                    fix_index: np.ndarray | None = None,
                    fix_stamps_ns: np.ndarray | None = None) -> int:
    """Write the bag; returns the number of messages.

    Parameters
    ----------
    targets : RadarTargets
        Sorted by frame; frame f is published with stamp ``radar_stamps_ns[f]``.
    fix_index : ndarray or None
        The GNSS epochs published as NavSatFix (``fix_receive_ns`` has one receipt per
        entry); None: every epoch.
    fix_stamps_ns : ndarray or None
        Header stamps of the NavSatFix of each GNSS epoch; None: ``gnss_stamps_ns``.
    odom_receive_ns : ndarray or None
        None leaves the Odometry topic out.
    radar_topic, radar_frame : str
        Topic and header frame id of the (first) radar.
    extra_radars : sequence of RadarStream
        Further radars recorded in parallel, each on its own topic.
    """
    store = msgs.get_typestore()
    radars = [RadarStream(radar_topic, radar_frame, targets, radar_stamps_ns,
                          radar_receive_ns), *extra_radars]
    # topic ranks: 0 fix, 1 odometry, 2 + k radar k
    packed = []
    for radar in radars:
        n = radar.stamps_ns.size
        packed.append((np.searchsorted(radar.targets.frame, np.arange(n + 1)),
                       radar.targets.position_m.astype(np.float32, copy=False),
                       radar.targets.radial_velocity_mps.astype(np.float32, copy=False),
                       radar.targets.rcs_dbsm.astype(np.float32, copy=False)))
    # (receive time, topic rank, index), merged into one receive-ordered stream; a radar
    # frame sorts before a fix received at the same nanosecond, as it always has
    keys = [np.column_stack([r.receive_ns, np.full(r.stamps_ns.size, -len(radars) + k,
                                                   np.int64), np.arange(r.stamps_ns.size)])
            for k, r in enumerate(radars)]
    fixes = np.arange(fix_receive_ns.size) if fix_index is None else np.asarray(fix_index)
    fix_stamps = gnss_stamps_ns if fix_stamps_ns is None else fix_stamps_ns
    keys.append(np.column_stack([fix_receive_ns, np.ones(fix_receive_ns.size, np.int64),
                                 fixes]))
    if odom_receive_ns is not None:
        keys.append(np.column_stack([odom_receive_ns,
                                     np.full(odom_receive_ns.size, 2, np.int64),
                                     np.arange(odom_receive_ns.size)]))
    order = np.concatenate(keys)
    order = order[np.lexsort((order[:, 2], order[:, 1], order[:, 0]))]

    def messages() -> Iterator[tuple[str, str, int, object]]:
        for receive, topic, i in order.tolist():
            if topic < 0:
                radar = radars[topic + len(radars)]
                bounds, positions, velocity, rcs = packed[topic + len(radars)]
                a, b = bounds[i], bounds[i + 1]
                msg = msgs.encode_pointcloud(
                    store, int(radar.stamps_ns[i]), radar.frame_id, positions[a:b],
                    velocity[a:b], layout=layout, dtype=np.float32,
                    velocity_field=velocity_field, extra_fields={'rcs': rcs[a:b]})
                yield radar.topic, msgs.POINTCLOUD2, receive, msg
            elif topic == 1:
                msg = msgs.encode_navsatfix(
                    store, int(fix_stamps[i]), 'base_link', float(gnss.lat_deg[i]),
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
                 header: str, radar_topic: str | None = RADAR_TOPIC) -> None:
    """``params.yaml``: topics and the calibration vehicle (a ROS 2 parameters file).

    ``radar_topic`` None (a recording of several radars) names no radar topic or frame:
    the user picks one (``radar_topic``) or calibrates them all (``--all-radars``).
    """
    params: dict[str, Any] = {
        'radar_topic': radar_topic,
        'navsat_topic': NAVSAT_TOPIC,
        # an explicitly empty topic turns the role off: navsat_only has no Odometry
        'odom_topic': ODOM_TOPIC if odometry else '',
        'radar': {'frame_id': 'radar'},
        'vehicle': {**{k: float(v) for k, v in vehicle.items()}, 'odom_is_utm': True},
    }
    if radar_topic is None:
        del params['radar_topic'], params['radar']
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
