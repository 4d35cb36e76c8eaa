"""The calibration result: conversion to UTM and the result files of CONTRACT.md.

``calibration_dict`` is the one place a local-frame ``Extrinsics`` becomes the contract's
keys; the simulator writes its ground truth through it too, so truth and estimate are
converted identically. Files are written atomically (temporary file in the same
directory, fsync, rename): a crash mid-write never leaves a broken result file.
"""
from __future__ import annotations

import datetime as _dt
import errno
import json
import math
import os
import tempfile
from collections.abc import Mapping
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np
import pyproj
import yaml
from scipy.spatial.transform import Rotation

from radar_calib_ros.errors import ResultFileError
from radar_calib_ros.io.geo import LocalFrame
from radar_calib_ros.types import Extrinsics, QualityReport

RESULT_KEYS = ('world_frame', 'radar_frame', 'epsg', 'translation', 'quaternion_xyzw',
               'rpy_deg', 'latitude', 'longitude', 'altitude', 'boresight_azimuth_deg',
               'stamp', 'quality')


#: ISO 8601 basic format, UTC: '20261127T082548Z'. Not the extended '2026-11-27T08:25:48+00:00':
#: YAML 1.1 reads that as a timestamp, and Jazzy's ``ros2 param load`` (rclpy re-parses each
#: value as YAML) then sent a datetime as a string parameter and crashed on the result file
#: (a probe on a real Jazzy build).
STAMP_FORMAT = '%Y%m%dT%H%M%SZ'


def parse_stamp(stamp: Any) -> _dt.datetime | None:
    """A result's ``stamp`` (basic or extended ISO 8601, or the datetime YAML made of the
    extended one) as an aware datetime; None where it is none of them."""
    if isinstance(stamp, str):
        try:
            stamp = _dt.datetime.strptime(stamp, STAMP_FORMAT).replace(tzinfo=_dt.timezone.utc)
        except ValueError:
            try:
                stamp = _dt.datetime.fromisoformat(stamp)
            except ValueError:
                return None
    if not isinstance(stamp, _dt.datetime):
        return None
    return stamp if stamp.tzinfo else stamp.replace(tzinfo=_dt.timezone.utc)


def extrinsics_to_utm(extrinsics: Extrinsics,
                      frame: LocalFrame) -> tuple[np.ndarray, np.ndarray]:
    """(R_utm (3, 3), t_utm (3,)) of a local-frame calibration."""
    t_local = np.asarray(extrinsics.translation_m, float)
    r_grid = frame.rotation_local_to_utm(t_local)
    return r_grid @ extrinsics.rotation, frame.local_to_utm(t_local[None, :])[0]


def utm_to_extrinsics(rotation_utm: np.ndarray, translation_utm: np.ndarray,
                      frame: LocalFrame, time_offset_s: float = 0.0) -> Extrinsics:
    """Inverse of :func:`extrinsics_to_utm`."""
    t_local = frame.utm_to_local(np.asarray(translation_utm, float)[None, :])[0]
    r_grid = frame.rotation_local_to_utm(t_local)
    return Extrinsics(r_grid.T @ np.asarray(rotation_utm, float), t_local, time_offset_s)


def calibration_dict(extrinsics: Extrinsics, frame: LocalFrame, *, world_frame: str = 'utm',
                     radar_frame: str = 'radar', quality: Mapping[str, Any] | None = None,
                     stamp: str | None = None) -> dict[str, Any]:
    """The contract's ``calibration`` mapping (plain Python types, YAML/JSON ready)."""
    rot_utm, t_utm = extrinsics_to_utm(extrinsics, frame)
    rot = Rotation.from_matrix(rot_utm)
    lat, lon, alt = frame.local_to_geodetic(np.asarray(extrinsics.translation_m)[None, :])
    boresight = rot_utm[:, 0]
    grid_azimuth = math.atan2(boresight[0], boresight[1])
    true_azimuth = grid_azimuth - float(frame.utm_convergence_rad(lat, lon)[0])
    return {
        'world_frame': world_frame,
        'radar_frame': radar_frame,
        'epsg': int(frame.epsg),
        'translation': [float(v) for v in t_utm],
        'quaternion_xyzw': [float(v) for v in rot.as_quat()],
        'rpy_deg': [float(v) for v in rot.as_euler('xyz', degrees=True)],
        'latitude': float(lat[0]),
        'longitude': float(lon[0]),
        'altitude': float(alt[0]),
        'boresight_azimuth_deg': float(math.degrees(true_azimuth) % 360.0),
        'stamp': stamp or _dt.datetime.now(_dt.timezone.utc).strftime(STAMP_FORMAT),
        'quality': _plain(dict(quality or {})),
    }


def quality_dict(report: QualityReport) -> dict[str, Any]:
    """The contract's quality figures from a QualityReport."""
    d = asdict(report)
    extra = d.pop('extra', {})
    d['advice'] = list(d['advice'])
    d['sigma'] = {
        'translation_m': d.pop('sigma_translation_m'),
        'along_boresight_m': d.pop('sigma_along_boresight_m'),
        'across_boresight_m': d.pop('sigma_across_boresight_m'),
        'vertical_m': d.pop('sigma_vertical_m'),
        'rotation_deg': d.pop('sigma_rotation_deg'),
    }
    # each rotation axis apart: a yaw known to 0.02 deg is not hidden under a tilt known to
    # 0.4 (``evaluate`` compares a second recording's fit with each)
    for name, value in zip(('roll_deg', 'pitch_deg', 'yaw_deg'),
                           d.pop('sigma_rotation_axes_deg')):
        if math.isfinite(value):
            d['sigma'][name] = value
    time_sigma = d.pop('sigma_time_offset_s')
    if math.isfinite(time_sigma):
        d['sigma']['time_offset_s'] = time_sigma
    d.update(extra)
    return _plain(d)


def _plain(value: Any) -> Any:
    """numpy scalars/arrays -> Python types, recursively (YAML/JSON safe)."""
    if isinstance(value, Mapping):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    if isinstance(value, np.ndarray):
        return _plain(value.tolist())
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def result_yaml_text(calibration: Mapping[str, Any]) -> str:
    """Text of ``result.yaml``: a ROS 2 parameters file (``/**: ros__parameters:``).

    Empty lists (``quality.advice`` when there is none) are left out: a ROS 2 parameter
    needs a type, an empty YAML sequence has none, and a node that declares its
    parameters from the file (``automatically_declare_parameters_from_overrides``) refuses
    it and does not start. ``load_result`` puts an absent ``advice`` back as empty; the
    JSON form keeps them.
    """
    doc = {'/**': {'ros__parameters': {'calibration': _without_empty_lists(calibration)}}}
    return yaml.safe_dump(doc, sort_keys=False, default_flow_style=None)


def _without_empty_lists(mapping: Mapping[str, Any]) -> dict[str, Any]:
    return {k: _without_empty_lists(v) if isinstance(v, Mapping) else v
            for k, v in mapping.items() if not (isinstance(v, (list, tuple)) and not v)}


def _umask() -> int:
    """The process umask, read without changing it where Linux shows it (setting and
    restoring it would race with the node's other threads creating files)."""
    try:
        with open('/proc/self/status', encoding='ascii') as fh:
            for line in fh:
                if line.startswith('Umask:'):
                    return int(line.split()[1], 8)
    except OSError:
        pass
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def is_stream(path: str | Path) -> bool:
    """Whether a path names a device or a pipe (``/dev/stdout``), not a file to replace."""
    path = Path(path)
    return path.exists() and not path.is_file() and not path.is_dir()


def write_atomic(path: str | Path, text: str) -> None:
    """Write a file via a temporary file in the same directory, fsync, rename; with the
    permissions a plainly created file gets (mkstemp's 0600 would keep a node running as
    another user from reading the result)."""
    path = Path(path)
    if is_stream(path):
        # written through, as a shell would; a rename would have replaced the device node
        # itself (a probe's /dev/full, as root)
        with open(path, 'w', encoding='utf-8') as fh:
            fh.write(text)
        return
    # through a symbolic link to its file: the rename replaced the link by a plain file
    # and left the file it named as it was
    path = Path(os.path.realpath(path))
    _check_writable_place(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f'.{path.name}.', suffix='.tmp', dir=path.parent)
    try:
        os.fchmod(fd, 0o666 & ~_umask())
        with os.fdopen(fd, 'w', encoding='utf-8') as fh:
            fh.write(text)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
        dir_fd = os.open(path.parent, os.O_RDONLY)
        try:
            os.fsync(dir_fd)
        finally:
            os.close(dir_fd)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def _check_writable_place(path: Path) -> None:
    """Name what is in the way: mkdir and rename say only 'File exists' or 'Is a directory'
    (a twenty-sixth probe's output.path under a file)."""
    if path.is_dir():
        raise IsADirectoryError(errno.EISDIR, f'{str(path)!r} is a directory: give a file '
                                'name', str(path))
    for parent in path.parents:
        if parent.exists():
            if not parent.is_dir():
                raise NotADirectoryError(errno.ENOTDIR, f'{str(parent)!r} is a file, not a '
                                         'directory', str(path))
            return


def _one_radar(calibrations: Mapping[str, Any], radar_frame: str | None,
               path: Path) -> Any:
    """The calibration of ``radar_frame`` in a file of several radars (or its only one):
    by key, or by the ``radar_frame`` an entry names (the combined parameters file keys a
    frame with '/' by its parameter-safe name)."""
    if radar_frame in calibrations:
        return calibrations[radar_frame]
    named = [c for c in calibrations.values() if isinstance(c, Mapping) and radar_frame
             and str(c.get('radar_frame', '')).lstrip('/') == radar_frame.lstrip('/')]
    if len(named) == 1:
        return named[0]
    if len(calibrations) == 1:
        return next(iter(calibrations.values()))
    raise ResultFileError(f'result file {str(path)!r} holds the calibrations of several radars '
                          f'({", ".join(map(str, calibrations))}) and none of frame '
                          f'{radar_frame!r}: set radar.frame_id to the one to use')


def write_result_yaml(path: str | Path, calibration: Mapping[str, Any]) -> None:
    write_atomic(path, result_yaml_text(calibration))


def write_result_json(path: str | Path, calibration: Mapping[str, Any]) -> None:
    write_atomic(path, json.dumps(dict(calibration), indent=2) + '\n')


def load_result(path: str | Path, radar_frame: str | None = None) -> dict[str, Any]:
    """Read and validate a result file (``result.yaml`` or ``result.json`` layout).

    A file of several radars (``--all-radars``: the combined parameters file, or its JSON
    keyed by frame) gives the calibration of ``radar_frame``, or its only one.

    Raises
    ------
    ResultFileError
        Naming what is missing or malformed, or the frames to choose from.
    """
    path = Path(path)
    try:
        text = path.read_text(encoding='utf-8')
    except OSError as err:
        raise ResultFileError(f'cannot read result file {str(path)!r}: {err.strerror}') from err
    try:
        doc = yaml.safe_load(text)  # JSON is YAML
    except yaml.YAMLError as err:
        raise ResultFileError(f'result file {str(path)!r} is not valid YAML/JSON') from err
    if isinstance(doc, dict) and 'world_frame' not in doc:
        several: Any = None
        for body in doc.values():
            if isinstance(body, dict) and isinstance(body.get('ros__parameters'), dict):
                params = body['ros__parameters']
                several = params.get('calibrations')
                doc = params.get('calibration')
                break
        else:
            # the --all-radars JSON: {frame: calibration}
            if doc and all(isinstance(v, dict) and 'world_frame' in v for v in doc.values()):
                several = doc
        if isinstance(several, dict) and several:
            doc = _one_radar(several, radar_frame, path)
    if not isinstance(doc, dict):
        raise ResultFileError(f'result file {str(path)!r} has no calibration mapping')
    missing = [k for k in ('translation', 'quaternion_xyzw', 'epsg') if k not in doc]
    if missing:
        raise ResultFileError(f'result file {str(path)!r} lacks {", ".join(missing)}')
    t = np.asarray(doc['translation'], dtype=float) if _is_numbers(doc['translation'], 3) \
        else None
    q = np.asarray(doc['quaternion_xyzw'], dtype=float) if _is_numbers(
        doc['quaternion_xyzw'], 4) else None
    if t is None or not np.all(np.isfinite(t)):
        raise ResultFileError(f'result file {str(path)!r}: translation must be 3 finite numbers')
    if q is None or not np.all(np.isfinite(q)) or abs(np.linalg.norm(q) - 1.0) > 1e-3:
        raise ResultFileError(f'result file {str(path)!r}: quaternion_xyzw must be a unit '
                              'quaternion of 4 numbers')
    if not isinstance(doc['epsg'], int):
        raise ResultFileError(f'result file {str(path)!r}: epsg must be an integer')
    _check_redundant_keys(doc, t, q, path)
    if isinstance(doc.get('quality'), dict):
        doc['quality'].setdefault('advice', [])  # left out of result.yaml when empty
    return doc


#: How far the redundant keys may sit from translation / quaternion_xyzw: they are written
#: from the same numbers at full precision, so only a hand edit moves them this far.
_RPY_TOLERANCE_DEG = 0.01
_GEODETIC_TOLERANCE_M = 0.01


def _check_redundant_keys(doc: Mapping[str, Any], translation: np.ndarray,
                          quaternion: np.ndarray, path: Path) -> None:
    """rpy_deg, latitude/longitude/altitude say again what quaternion_xyzw and translation
    say; the tool reads only the latter. A file where they disagree has been edited by hand
    (a yaw corrected in rpy_deg, a position in latitude/longitude) and served as it was, it
    would publish something else than its reader believes (a twenty-sixth probe's case):
    refused, naming both."""
    name = str(path)
    rpy = doc.get('rpy_deg')
    if rpy is not None:
        if not _is_numbers(rpy, 3):
            raise ResultFileError(f'result file {name!r}: rpy_deg must be 3 numbers')
        from_rpy = Rotation.from_euler('xyz', rpy, degrees=True)
        apart = math.degrees((from_rpy.inv() * Rotation.from_quat(quaternion)).magnitude())
        if apart > _RPY_TOLERANCE_DEG:
            stated = ', '.join(f'{v:.3f}' for v in Rotation.from_quat(quaternion).as_euler(
                'xyz', degrees=True))
            raise ResultFileError(
                f'result file {name!r}: rpy_deg {_listed(rpy)} and quaternion_xyzw (roll, pitch, '
                f'yaw {stated} deg) disagree by {apart:.3f} deg; the tool uses '
                'quaternion_xyzw: edit both, or remove rpy_deg')
    geodetic = [doc.get(k) for k in ('latitude', 'longitude', 'altitude')]
    if all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in geodetic):
        try:
            to_utm = pyproj.Transformer.from_crs(4326, int(doc['epsg']), always_xy=True)
        except pyproj.exceptions.CRSError as err:
            raise ResultFileError(f'result file {name!r}: epsg {doc["epsg"]} is not a known '
                                  'coordinate system') from err
        lat, lon, alt = (float(v) for v in geodetic)
        easting, northing = to_utm.transform(lon, lat)
        apart = math.dist((easting, northing, alt), translation)
        if not apart <= _GEODETIC_TOLERANCE_M:
            raise ResultFileError(
                f'result file {name!r}: latitude/longitude/altitude {lat:.7f}, {lon:.7f}, '
                f'{alt:.3f} lie {apart:.3f} m from translation {_listed(translation)} (EPSG '
                f'{doc["epsg"]}); the tool uses translation: edit both, or remove latitude, '
                'longitude and altitude')


def _listed(values: Any) -> str:
    """'[1.000, 2.000]': numbers as a message shows them (a thirty-seventh probe's read
    '[np.float64(500277.99178861646), ...]')."""
    return '[' + ', '.join(f'{float(v):.3f}' for v in values) + ']'


def _is_numbers(value: Any, n: int) -> bool:
    return (isinstance(value, (list, tuple)) and len(value) == n
            and all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in value))


def rotation_error_deg(rot_a: np.ndarray, rot_b: np.ndarray) -> float:
    """Angle of R_a^T R_b [deg]."""
    return float(np.degrees(Rotation.from_matrix(rot_a.T @ rot_b).magnitude()))
