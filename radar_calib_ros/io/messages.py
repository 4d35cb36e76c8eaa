"""ROS 2 messages <-> decoded samples: the typestore, decoders and encoders.

Decoders read only the attributes a message has in both worlds (rosbags message objects,
whose ``uint8[]`` data is a numpy array, and rclpy messages, whose data is an
``array.array('B')`` or ``bytes``), so the offline tool and the node share them.
PointCloud2 decoding is one ``np.frombuffer`` with a structured dtype per message: no
per-target Python.

Encoders build rosbags message objects of a given typestore (the simulator, the tests and
the node's ``~/save_recording`` write bags with them).
"""
from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from rosbags.typesys import Stores, get_types_from_msg, get_typestore as _rosbags_typestore

from radar_calib_ros.errors import DecodeError
from radar_calib_ros.types import FixSample, OdomSample, RadarFrame

if TYPE_CHECKING:
    from radar_calib_ros.config import CalibConfig
    from numpy.typing import ArrayLike, DTypeLike
    from rosbags.typesys.store import Typestore

__all__ = [
    'POINTCLOUD2', 'NAVSATFIX', 'ODOMETRY', 'RADARSCAN', 'VELOCITY_FIELD_NAMES',
    'get_typestore', 'stamp_ns', 'frame_id_mismatch', 'decode_pointcloud', 'decode_radarscan',
    'decode_navsatfix', 'lacks_velocity_field',
    'decode_odometry', 'encode_pointcloud', 'encode_navsatfix', 'encode_odometry',
    'msg_schemas_dir',
]

POINTCLOUD2 = 'sensor_msgs/msg/PointCloud2'
NAVSATFIX = 'sensor_msgs/msg/NavSatFix'
ODOMETRY = 'nav_msgs/msg/Odometry'
RADARSCAN = 'radar_msgs/msg/RadarScan'

#: Radial-velocity field names tried in this order when ``radar.velocity_field`` is empty.
#: The contract's names, then radar_msgs' ``doppler_velocity`` (a RadarScan turned into a
#: cloud). Each is also found in another case (CARLA's ROS bridge writes ``Velocity``).
#: A bare ``v`` comes last: drivers that write x, y, z, v mean the radial velocity, but a
#: camera's cloud with texture coordinates u, v does not (``_choose_velocity_field``).
VELOCITY_FIELD_NAMES = ('velocity', 'radial_velocity', 'radial_speed', 'doppler', 'v_r', 'vr',
                        'range_rate', 'doppler_velocity', 'v')
#: Spherical position fields (m, rad), each with the names drivers use for it: the
#: contract's first, then the ``*_angle`` spelling (Continental's ARS548 driver, radar_msgs
#: conversions). CARLA's ``AzimuthAngle`` is not among them: it turns clockwise, and its
#: clouds carry x, y, z anyway.
SPHERICAL_FIELD_NAMES = (('range',), ('azimuth', 'azimuth_angle'),
                         ('elevation', 'elevation_angle'))
#: Velocity components in the sensor frame, used where a cloud has no radial velocity:
#: an object list's (a tracker's output gives each object's velocity, not a Doppler), its
#: radial velocity their projection on the line of sight. The z component is optional
#: (road users move level).
VELOCITY_COMPONENT_NAMES = (('vx', 'vy', 'vz'), ('velocity_x', 'velocity_y', 'velocity_z'),
                            ('vel_x', 'vel_y', 'vel_z'), ('v_x', 'v_y', 'v_z'))

# sensor_msgs/msg/PointField datatype constants -> numpy type codes (byte order added later)
_POINTFIELD_TYPES: dict[int, str] = {1: 'i1', 2: 'u1', 3: 'i2', 4: 'u2', 5: 'i4', 6: 'u4',
                                     7: 'f4', 8: 'f8'}
_POINTFIELD_NAMES = {1: 'INT8', 2: 'UINT8', 3: 'INT16', 4: 'UINT16', 5: 'INT32', 6: 'UINT32',
                     7: 'FLOAT32', 8: 'FLOAT64'}
_NUMPY_TO_POINTFIELD = {np.dtype(code).str[1:]: datatype
                        for datatype, code in _POINTFIELD_TYPES.items()}
_FLOAT_TYPES = (7, 8)

_PACKAGE_NAME = 'radar_calib_ros'


# --- typestore ---------------------------------------------------------------------------

def msg_schemas_dir(start: Path | None = None) -> Path:
    """Directory holding our extra ``.msg`` definitions (``msg_schemas/``).

    A source checkout or editable install has it next to the package; a colcon or pip
    install puts it under ``<prefix>/share/radar_calib_ros/msg_schemas`` (setup.py
    ``data_files``), where ``<prefix>`` is an ancestor of the installed package. Walking up
    from this file (or ``start``) finds either without relying on ``sys.prefix``.

    Raises
    ------
    FileNotFoundError
        Neither location exists (a broken install).
    """
    here = (start or Path(__file__)).resolve().parent
    tried = []
    for ancestor in here.parents:
        for candidate in (ancestor / 'msg_schemas',
                          ancestor / 'share' / _PACKAGE_NAME / 'msg_schemas'):
            if any(candidate.glob('*.msg')):
                return candidate
            tried.append(str(candidate))
    raise FileNotFoundError(f'msg_schemas with the radar_msgs definitions not found (looked '
                            f'in {len(tried)} places up from {here}); reinstall the package')


def _schema_types(directory: Path) -> dict[str, Any]:
    """Parse every ``<pkg>__msg__<Name>.msg`` in a directory into rosbags field defs."""
    types: dict[str, Any] = {}
    for path in sorted(directory.glob('*.msg')):
        msgtype = path.stem.replace('__', '/')
        types.update(get_types_from_msg(path.read_text(encoding='utf-8'), msgtype))
    return types


def get_typestore() -> Typestore:
    """A fresh ROS 2 Jazzy typestore with our ``msg_schemas`` (radar_msgs) registered.

    A new store per call (as rosbags' own ``get_typestore``), so registering types never
    leaks between readers, writers or tests.
    """
    store = _rosbags_typestore(Stores.ROS2_JAZZY)
    store.register(_schema_types(msg_schemas_dir()))
    return store


# --- decoding ----------------------------------------------------------------------------

def stamp_ns(header: Any) -> int:
    """Header stamp (``builtin_interfaces/Time``) as integer nanoseconds."""
    return int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)


def frame_id_mismatch(header_frame_id: str, configured: str) -> str | None:
    """A warning when the radar's messages name another frame than ``radar.frame_id``:
    the calibration is published for the configured name, and a consumer of the cloud that
    looks up its own frame in TF would not find it. None when they agree (or the header
    names none)."""
    cloud = str(header_frame_id or '').lstrip('/')
    if not cloud or cloud == configured.lstrip('/'):
        return None
    return (f"the radar's messages are in frame '{cloud}' but radar.frame_id is "
            f"'{configured}': the calibration is published for '{configured}'; set "
            f"radar.frame_id: {cloud} so that TF consumers of the cloud find it")


def radar_frame_to_keep(header_frame_id: str, kept: str | None,
                        config: CalibConfig) -> str | None:
    """The frame of the radar clouds a topic's reader keeps, after one more cloud in
    ``header_frame_id``: the first frame seen (``kept``), or ``radar.frame_id`` once a
    cloud in it arrives where the parameters set it (so a topic of two radars gives the
    one the parameters name)."""
    cloud = str(header_frame_id or '').lstrip('/')
    configured = config.radar.frame_id.lstrip('/')
    if 'radar.frame_id' in config.explicit and cloud == configured:
        return configured
    return kept or cloud or None


def other_radar(header_frame_id: str, first_frame_id: str | None) -> str | None:
    """Where the radar topic's clouds are in another frame than the one kept
    (``radar_frame_to_keep``; two radars published on one topic): a warning naming both,
    else None. The node and the bag reader skip the other radar's clouds (a twenty-sixth
    probe's two radars on one topic failed as 'another vehicle kept pace with it')."""
    cloud = str(header_frame_id or '').lstrip('/')
    first = str(first_frame_id or '').lstrip('/')
    if not cloud or not first or cloud == first:
        return None
    return (f"the radar topic carries clouds in frame '{cloud}' as well as in '{first}' (two "
            f"radars on one topic?): only those in '{first}' are used (radar.frame_id, or "
            'the first seen); publish each radar on a topic of its own')


def _field_table(fields: Sequence[Any]) -> dict[str, tuple[int, int]]:
    """``{name: (offset, datatype)}``; the first of duplicate names wins (as PCL does)."""
    table: dict[str, tuple[int, int]] = {}
    for f in fields:
        table.setdefault(str(f.name), (int(f.offset), int(f.datatype)))
    return table


def _fields_extent(fields: Sequence[Any]) -> int:
    """Bytes from the start of a point to the end of its last field of known size."""
    extent = 0
    for f in fields:
        code = _POINTFIELD_TYPES.get(int(f.datatype))
        if code is not None:
            extent = max(extent, int(f.offset) + np.dtype(code).itemsize * max(int(f.count), 1))
    return extent


def _fields_listing(table: Mapping[str, tuple[int, int]]) -> str:
    return ', '.join(table) if table else 'none'


def _field_named(table: Mapping[str, tuple[int, int]], name: str) -> str | None:
    """The field called ``name``, else the one field called so in another case (drivers
    differ: CARLA's ROS bridge writes ``Velocity``), else None."""
    if name in table:
        return name
    folded = [key for key in table if key.lower() == name.lower()]
    return folded[0] if len(folded) == 1 else None


def lacks_velocity_field(msg: Any, velocity_field: str = '') -> bool:
    """True for a PointCloud2 with fields but no radial-velocity field (a lidar's x, y, z,
    intensity): not a radar. A cloud without fields (an empty scan) says nothing: False."""
    table = _field_table(list(msg.fields))
    if not table:
        return False
    if velocity_field:
        return _field_named(table, velocity_field) is None
    return _velocity_field_among(table) is None and _velocity_components_among(table) is None


def _velocity_field_among(table: Mapping[str, tuple[int, int]]) -> str | None:
    """The first of ``VELOCITY_FIELD_NAMES`` the cloud has (a ``v`` beside a ``u`` is a
    texture coordinate, not a velocity), else None."""
    for name in VELOCITY_FIELD_NAMES:
        found = _field_named(table, name)
        if found is not None and not (name == 'v' and _field_named(table, 'u') is not None):
            return found
    return None


def _velocity_components_among(table: Mapping[str, tuple[int, int]]) -> tuple[str, ...] | None:
    """The first complete set of ``VELOCITY_COMPONENT_NAMES`` the cloud has (x and y, and z
    where present), else None."""
    for names in VELOCITY_COMPONENT_NAMES:
        found = [_field_named(table, name) for name in names]
        if found[0] is not None and found[1] is not None:
            return tuple(str(name) for name in found if name is not None)
    return None


def _choose_velocity_field(table: Mapping[str, tuple[int, int]], velocity_field: str) -> str:
    if velocity_field:
        found = _field_named(table, velocity_field)
        if found is None:
            raise DecodeError(f'PointCloud2 has no velocity field {velocity_field!r} '
                              f'(radar.velocity_field); fields found: {_fields_listing(table)}')
        return found
    found = _velocity_field_among(table)
    if found is not None:
        return found
    # Autoware's radar_scan_to_pointcloud2 writes its doppler_pointcloud as x, y, z and
    # 'intensity' holding the Doppler velocity: a guess we do not take (its amplitude
    # cloud looks the same), but the user may know
    hint = ("; a radar cloud from Autoware's radar_scan_to_pointcloud2 (doppler_pointcloud) "
            "carries the radial velocity in 'intensity': if so, set radar.velocity_field: "
            'intensity' if _field_named(table, 'intensity') is not None else '')
    raise DecodeError(f'PointCloud2 has no radial-velocity field (looked for '
                      f'{", ".join(VELOCITY_FIELD_NAMES)}, or velocity components vx, vy; set '
                      f'radar.velocity_field); fields found: {_fields_listing(table)}{hint}')


def _numpy_code(name: str, datatype: int, *, float_only: bool) -> str:
    code = _POINTFIELD_TYPES.get(datatype)
    if code is None or (float_only and datatype not in _FLOAT_TYPES):
        kind = _POINTFIELD_NAMES.get(datatype, f'unknown datatype {datatype}')
        want = 'FLOAT32 or FLOAT64' if float_only else 'a numeric PointField datatype'
        raise DecodeError(f'PointCloud2 field {name!r} has unsupported datatype {kind} '
                          f'(need {want})')
    return code


def decode_pointcloud(msg: Any, velocity_field: str = '') -> RadarFrame:
    """Radar targets of one ``sensor_msgs/msg/PointCloud2``.

    Parameters
    ----------
    msg : PointCloud2
        A rosbags or rclpy message. Read: ``header.stamp``, ``fields`` (name, offset,
        datatype, count), ``point_step``, ``row_step`` (if present), ``width``, ``height``,
        ``is_bigendian``, ``data``.
    velocity_field : str, default=''
        Name of the radial-velocity field; empty tries ``VELOCITY_FIELD_NAMES`` in order.

    Returns
    -------
    RadarFrame
        Targets with NaN/inf in any used field dropped (counted in ``dropped_nonfinite``).
        Positions come from x/y/z or, when those are absent, from range/azimuth/elevation
        (m, rad; x = r cos(el) cos(az), y = r cos(el) sin(az), z = r sin(el)).

    Raises
    ------
    DecodeError
        Data shorter than the points it declares, ``point_step`` smaller than the fields,
        no position or velocity field, or an unsupported datatype.
    """
    stamp = stamp_ns(msg.header)
    width, height = int(msg.width), int(msg.height)
    point_step = int(msg.point_step)
    n = width * height
    fields = list(msg.fields)
    if n == 0 and not fields:
        # drivers publish empty clouds without fields when nothing was detected
        return RadarFrame(stamp, np.zeros((0, 3)), np.zeros(0))
    table = _field_table(fields)
    cartesian = [_field_named(table, name) for name in ('x', 'y', 'z')]
    polar = [next((found for found in (_field_named(table, name) for name in names)
                   if found is not None), None) for names in SPHERICAL_FIELD_NAMES]
    # A 2-D radar's cloud may leave out the third coordinate (x, y; or range, azimuth)
    # rather than write z = 0: read as level, as z = 0 is (an independent probe's range,
    # azimuth, doppler cloud was refused while the same targets as x, y, 0 calibrated)
    if None not in cartesian[:2]:
        position_names, spherical = cartesian, False
    elif None not in polar[:2]:
        position_names, spherical = polar, True
    else:
        raise DecodeError('PointCloud2 has neither x/y/z nor range/azimuth/elevation fields; '
                          f'fields found: {_fields_listing(table)}')
    components: tuple[str, ...] = (
        () if velocity_field or _velocity_field_among(table) is not None
        else _velocity_components_among(table) or ())
    # (without either, choosing the velocity field raises, naming the fields found)
    v_names = components or (_choose_velocity_field(table, velocity_field),)
    extent = _fields_extent(fields)
    if point_step < extent:
        raise DecodeError(f'PointCloud2 point_step {point_step} is smaller than its fields '
                          f'({extent} bytes)')
    order = '>' if msg.is_bigendian else '<'
    columns = [(key, str(name)) for key, name in zip(('p0', 'p1', 'p2'), position_names)
               if name is not None]
    columns += [(f'v{i}', name) for i, name in enumerate(v_names)]
    formats = [order + _numpy_code(name, table[name][1], float_only=not key.startswith('v'))
               for key, name in columns]
    try:
        dtype = np.dtype({'names': [key for key, _ in columns], 'formats': formats,
                          'offsets': [table[name][0] for _, name in columns],
                          'itemsize': point_step})
    except (ValueError, OverflowError) as err:
        # numpy keeps itemsize and offsets in a C int; no real cloud comes near 2 GiB a point
        raise DecodeError(f'PointCloud2 point_step {point_step} or a field offset is too '
                          f'large: {err}') from err
    raw = np.frombuffer(msg.data, np.uint8)
    row_bytes = width * point_step
    row_step = int(getattr(msg, 'row_step', row_bytes) or row_bytes)
    if height > 1 and row_step > row_bytes:
        # rows padded at their end: the last row needs no padding after it
        need = (height - 1) * row_step + row_bytes
        if raw.size < need:
            raise DecodeError(f'PointCloud2 data has {raw.size} bytes, fewer than height '
                              f'{height} x row_step {row_step} (last row {row_bytes}) = {need}')
        rows = np.lib.stride_tricks.as_strided(raw, (height, row_bytes), (row_step, 1),
                                               writeable=False)
        points = np.ascontiguousarray(rows).reshape(-1).view(dtype)
    else:
        need = n * point_step
        if raw.size < need:
            raise DecodeError(f'PointCloud2 data has {raw.size} bytes, fewer than width {width}'
                              f' x height {height} x point_step {point_step} = {need}')
        points = np.frombuffer(raw, dtype, count=n)
    with np.errstate(invalid='ignore'):
        # signalling NaNs (corrupt data) warn when cast; they are dropped below as non-finite
        p0 = points['p0'].astype(np.float64)
        p1 = points['p1'].astype(np.float64)
        p2 = (points['p2'].astype(np.float64) if 'p2' in points.dtype.names
              else np.zeros(p0.size))
        v = np.column_stack([points[f'v{i}'].astype(np.float64) for i in range(len(v_names))])
    finite = (np.isfinite(p0) & np.isfinite(p1) & np.isfinite(p2)
              & np.all(np.isfinite(v), axis=1))
    dropped = int(n - np.count_nonzero(finite))
    if dropped:
        p0, p1, p2, v = p0[finite], p1[finite], p2[finite], v[finite]
    if spherical:
        if p1.size and (np.abs(p1).max() > math.pi + 1e-6
                        or np.abs(p2).max() > math.pi / 2 + 1e-6):
            # a driver writing degrees: angles up to 60 cannot be radians, and read as such
            # they scatter the targets round the radar (a probe's recording failed with
            # 'vehicle never seen' and advice for a sparse radar)
            raise DecodeError(f'PointCloud2 azimuth/elevation reach {np.abs(p1).max():.1f} / '
                              f'{np.abs(p2).max():.1f}, beyond +-pi / +-pi/2: the spherical '
                              'layout takes radians (degrees written?)')
        horizontal = p0 * np.cos(p2)
        positions = np.column_stack([horizontal * np.cos(p1), horizontal * np.sin(p1),
                                     p0 * np.sin(p2)])
    else:
        positions = np.column_stack([p0, p1, p2])
    if components:
        # the radar stands still: the velocity it gives is the object's, and what it would
        # have measured is its projection on the line of sight, positive moving away
        rng = np.linalg.norm(positions, axis=1)
        along = np.einsum('ij,ij->i', positions[:, :v.shape[1]], v)
        velocity = np.divide(along, rng, out=np.zeros_like(along), where=rng > 0.0)
    else:
        velocity = v[:, 0]
    return RadarFrame(stamp, positions, velocity, dropped_nonfinite=dropped,
                      invalid_declared=not bool(getattr(msg, 'is_dense', True)),
                      velocity_components=components)


def decode_radarscan(msg: Any) -> RadarFrame:
    """Radar targets of one ``radar_msgs/msg/RadarScan`` (spherical returns, doppler_velocity
    as the radial velocity); non-finite returns dropped and counted."""
    returns = msg.returns
    values = np.array([(r.range, r.azimuth, r.elevation, r.doppler_velocity) for r in returns],
                      np.float64).reshape(-1, 4)
    finite = np.isfinite(values).all(axis=1)
    values = values[finite]
    rng, az, el = values[:, 0], values[:, 1], values[:, 2]
    horizontal = rng * np.cos(el)
    positions = np.column_stack([horizontal * np.cos(az), horizontal * np.sin(az),
                                 rng * np.sin(el)])
    return RadarFrame(stamp_ns(msg.header), positions, values[:, 3].copy(),
                      dropped_nonfinite=int(finite.size - np.count_nonzero(finite)))


def decode_navsatfix(msg: Any) -> FixSample:
    """One ``sensor_msgs/msg/NavSatFix``; no filtering (``RecordingBuilder.add_fix`` drops
    and counts no-fix and non-finite samples)."""
    sigma = (math.nan, math.nan)
    if int(getattr(msg, 'position_covariance_type', 0)) > 0:  # 0: COVARIANCE_TYPE_UNKNOWN
        c = [float(v) for v in msg.position_covariance]
        if len(c) == 9 and all(math.isfinite(v) for v in c):
            sigma = (math.sqrt(max(0.5 * (c[0] + c[4]), 0.0)), math.sqrt(max(c[8], 0.0)))
    return FixSample(stamp_ns(msg.header), float(msg.latitude), float(msg.longitude),
                     float(msg.altitude), int(msg.status.status), sigma,
                     str(getattr(msg.header, 'frame_id', '') or ''))


def decode_odometry(msg: Any) -> OdomSample:
    """One ``nav_msgs/msg/Odometry``; no filtering (``RecordingBuilder.add_odometry`` does)."""
    p = msg.pose.pose.position
    q = msg.pose.pose.orientation
    v = msg.twist.twist.linear
    return OdomSample(stamp_ns(msg.header), (float(p.x), float(p.y), float(p.z)),
                      (float(q.x), float(q.y), float(q.z), float(q.w)),
                      (float(v.x), float(v.y), float(v.z)), float(msg.twist.twist.angular.z))


# --- encoding ----------------------------------------------------------------------------

def _header(typestore: Typestore, stamp: int, frame_id: str) -> Any:
    types = typestore.types
    sec, nanosec = divmod(int(stamp), 1_000_000_000)
    return types['std_msgs/msg/Header'](
        stamp=types['builtin_interfaces/msg/Time'](sec=sec, nanosec=nanosec), frame_id=frame_id)


def encode_pointcloud(typestore: Typestore, stamp_ns: int, frame_id: str,
                      positions_m: ArrayLike, radial_velocity_mps: ArrayLike, *,
                      layout: str = 'xyz', dtype: DTypeLike = np.float32,
                      big_endian: bool = False, pad_bytes: int = 0,
                      velocity_field: str = 'velocity',
                      extra_fields: Mapping[str, ArrayLike] | None = None) -> Any:
    """A ``sensor_msgs/msg/PointCloud2`` (height 1) of radar targets.

    Parameters
    ----------
    typestore : Typestore
        Store whose message classes are used (``get_typestore()``).
    stamp_ns : int
        Header stamp [ns].
    frame_id : str
    positions_m : array_like of shape (n, 3)
        Targets in the sensor frame, x forward, y left, z up [m].
    radial_velocity_mps : array_like of shape (n,)
        Positive = moving away [m/s].
    layout : {'xyz', 'spherical'}, default='xyz'
        Fields x, y, z or range, azimuth, elevation (m, rad).
    dtype : float32 or float64, default=float32
        Type of the position and velocity fields.
    big_endian : bool, default=False
    pad_bytes : int, default=0
        Unused bytes appended to each point (odd ``point_step``).
    velocity_field : str, default='velocity'
    extra_fields : dict of str to array_like of shape (n,), optional
        More fields (e.g. ``rcs``), each in its array's numeric dtype.
    """
    types = typestore.types
    positions = np.asarray(positions_m, np.float64).reshape(-1, 3)
    n = positions.shape[0]
    velocity = np.asarray(radial_velocity_mps, np.float64).reshape(n)
    value_type = np.dtype(dtype)
    if value_type.str[1:] not in ('f4', 'f8'):
        raise ValueError(f'dtype must be float32 or float64, got {value_type}')
    if layout == 'xyz':
        columns = {'x': positions[:, 0], 'y': positions[:, 1], 'z': positions[:, 2]}
    elif layout == 'spherical':
        rng = np.linalg.norm(positions, axis=1)
        with np.errstate(invalid='ignore', divide='ignore'):
            elevation = np.where(rng > 0, np.arcsin(np.clip(positions[:, 2] / rng, -1, 1)), 0.0)
        columns = {'range': rng, 'azimuth': np.arctan2(positions[:, 1], positions[:, 0]),
                   'elevation': elevation}
    else:
        raise ValueError(f"layout must be 'xyz' or 'spherical', got {layout!r}")
    order = '>' if big_endian else '<'
    columns[velocity_field] = velocity
    column_types = {name: np.dtype(order + value_type.str[1:]) for name in columns}
    for name, values in (extra_fields or {}).items():
        array = np.asarray(values).reshape(n)
        if array.dtype.str[1:] not in _NUMPY_TO_POINTFIELD:
            raise ValueError(f'extra field {name!r} has dtype {array.dtype}, which PointField '
                             'cannot carry')
        columns[name] = array
        column_types[name] = np.dtype(order + array.dtype.str[1:])
    offsets, offset = [], 0
    for name in columns:
        offsets.append(offset)
        offset += column_types[name].itemsize
    point_step = offset + int(pad_bytes)
    record = np.dtype({'names': list(columns), 'formats': list(column_types.values()),
                       'offsets': offsets, 'itemsize': point_step})
    points = np.zeros(n, record)
    for name, values in columns.items():
        points[name] = values
    point_field = types['sensor_msgs/msg/PointField']
    fields = [point_field(name=name, offset=off,
                          datatype=_NUMPY_TO_POINTFIELD[column_types[name].str[1:]], count=1)
              for name, off in zip(columns, offsets)]
    return types[POINTCLOUD2](
        header=_header(typestore, stamp_ns, frame_id), height=1, width=n, fields=fields,
        is_bigendian=bool(big_endian), point_step=point_step, row_step=point_step * n,
        data=points.view(np.uint8).reshape(-1), is_dense=bool(np.isfinite(positions).all()))


def encode_navsatfix(typestore: Typestore, stamp_ns: int, frame_id: str, lat_deg: float,
                     lon_deg: float, alt_m: float, status: int = 2,
                     position_sigma_m: float | tuple[float, float] = 0.02) -> Any:
    """A ``sensor_msgs/msg/NavSatFix`` (WGS 84, ellipsoidal altitude).

    ``status`` 2 is STATUS_GBAS_FIX (RTK), -1 STATUS_NO_FIX; the covariance is diagonal
    with ``position_sigma_m`` on every axis, or (horizontal, vertical)
    (COVARIANCE_TYPE_DIAGONAL_KNOWN); NaN writes COVARIANCE_TYPE_UNKNOWN.
    """
    types = typestore.types
    sigma_h, sigma_v = (position_sigma_m if isinstance(position_sigma_m, tuple)
                        else (position_sigma_m, position_sigma_m))
    known = math.isfinite(sigma_h) and math.isfinite(sigma_v)
    covariance = np.zeros(9)
    if known:
        covariance[:] = np.diag([sigma_h ** 2, sigma_h ** 2, sigma_v ** 2]).ravel()
    return types[NAVSATFIX](
        header=_header(typestore, stamp_ns, frame_id),
        status=types['sensor_msgs/msg/NavSatStatus'](status=int(status), service=1),
        latitude=float(lat_deg), longitude=float(lon_deg), altitude=float(alt_m),
        position_covariance=covariance, position_covariance_type=2 if known else 0)


def encode_odometry(typestore: Typestore, stamp_ns: int, frame_id: str, child_frame_id: str,
                    position_m: ArrayLike, quaternion_xyzw: ArrayLike,
                    velocity_body_mps: ArrayLike, yaw_rate_rps: float) -> Any:
    """A ``nav_msgs/msg/Odometry``: pose in ``frame_id`` (orientation ENU against true
    north), twist in ``child_frame_id`` (the vehicle frame); zero covariances."""
    types = typestore.types
    px, py, pz = (float(v) for v in np.asarray(position_m, float).reshape(3))
    qx, qy, qz, qw = (float(v) for v in np.asarray(quaternion_xyzw, float).reshape(4))
    vx, vy, vz = (float(v) for v in np.asarray(velocity_body_mps, float).reshape(3))
    vector3 = types['geometry_msgs/msg/Vector3']
    pose = types['geometry_msgs/msg/Pose'](
        position=types['geometry_msgs/msg/Point'](x=px, y=py, z=pz),
        orientation=types['geometry_msgs/msg/Quaternion'](x=qx, y=qy, z=qz, w=qw))
    twist = types['geometry_msgs/msg/Twist'](
        linear=vector3(x=vx, y=vy, z=vz),
        angular=vector3(x=0.0, y=0.0, z=float(yaw_rate_rps)))
    return types[ODOMETRY](
        header=_header(typestore, stamp_ns, frame_id), child_frame_id=child_frame_id,
        pose=types['geometry_msgs/msg/PoseWithCovariance'](pose=pose, covariance=np.zeros(36)),
        twist=types['geometry_msgs/msg/TwistWithCovariance'](twist=twist,
                                                             covariance=np.zeros(36)))
