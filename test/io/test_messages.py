"""io.messages: PointCloud2 layouts against hand-built messages, NavSatFix/Odometry, the
typestore and the encoders."""
from __future__ import annotations

import array
import math
import struct
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest
from rosbags.typesys import get_types_from_msg

from radar_calib_ros.errors import DecodeError
from radar_calib_ros.io import messages as m

FLOAT32, FLOAT64, INT16, UINT16 = 7, 8, 3, 4
_STRUCT = {FLOAT32: 'f', FLOAT64: 'd', INT16: 'h', UINT16: 'H'}
STAMP_NS = 1_700_000_123_456_789_012


@pytest.fixture(scope='module')
def ts() -> Any:
    return m.get_typestore()


def hand_cloud(ts: Any, fields: list[tuple[str, int, int]], points: list[dict[str, float]], *,
               point_step: int, big_endian: bool = False, height: int = 1,
               row_pad: int = 0, truncate: int = 0) -> Any:
    """A PointCloud2 built field by field with struct (independent of the decoder's numpy
    dtype machinery). fields: (name, offset, datatype); unset bytes are 0xAB filler."""
    order = '>' if big_endian else '<'
    width = len(points) // height
    rows = []
    for r in range(height):
        row = bytearray()
        for p in points[r * width:(r + 1) * width]:
            buf = bytearray(b'\xab' * point_step)
            for name, offset, datatype in fields:
                struct.pack_into(order + _STRUCT[datatype], buf, offset, p.get(name, 0))
            row += buf
        rows.append(bytes(row) + b'\xcd' * row_pad)
    data = b''.join(rows)
    if truncate:
        data = data[:-truncate]
    types = ts.types
    header = types['std_msgs/msg/Header'](
        stamp=types['builtin_interfaces/msg/Time'](sec=STAMP_NS // 10**9,
                                                   nanosec=STAMP_NS % 10**9),
        frame_id='radar')
    point_fields = [types['sensor_msgs/msg/PointField'](name=n, offset=o, datatype=d, count=1)
                    for n, o, d in fields]
    return types[m.POINTCLOUD2](
        header=header, height=height, width=width, fields=point_fields,
        is_bigendian=big_endian, point_step=point_step, row_step=width * point_step + row_pad,
        data=np.frombuffer(data, np.uint8).copy(), is_dense=False)


POINTS = [{'x': 1.5, 'y': -2.25, 'z': 0.5, 'velocity': 3.0},
          {'x': 100.125, 'y': 20.0, 'z': -4.0, 'velocity': -12.5},
          {'x': 0.0, 'y': 0.25, 'z': 8.0, 'velocity': 0.0625}]
XYZ = np.array([[p['x'], p['y'], p['z']] for p in POINTS])
VEL = np.array([p['velocity'] for p in POINTS])


def test_stamp_from_header(ts: Any) -> None:
    msg = hand_cloud(ts, [('x', 0, FLOAT32), ('y', 4, FLOAT32), ('z', 8, FLOAT32),
                          ('velocity', 12, FLOAT32)], POINTS, point_step=16)
    assert m.stamp_ns(msg.header) == STAMP_NS
    assert m.decode_pointcloud(msg).stamp_ns == STAMP_NS


@pytest.mark.parametrize('big_endian', [False, True])
@pytest.mark.parametrize('datatype', [FLOAT32, FLOAT64])
def test_xyz_dense(ts: Any, big_endian: bool, datatype: int) -> None:
    size = 4 if datatype == FLOAT32 else 8
    fields = [(n, i * size, datatype) for i, n in enumerate(('x', 'y', 'z', 'velocity'))]
    msg = hand_cloud(ts, fields, POINTS, point_step=4 * size, big_endian=big_endian)
    frame = m.decode_pointcloud(msg)
    # every value is exactly representable in float32
    np.testing.assert_array_equal(frame.positions_m, XYZ)
    np.testing.assert_array_equal(frame.radial_velocity_mps, VEL)
    assert frame.positions_m.dtype == np.float64 and frame.dropped_nonfinite == 0


@pytest.mark.parametrize('big_endian', [False, True])
def test_xyz_padding_odd_step_and_shuffled_fields(ts: Any, big_endian: bool) -> None:
    # velocity first, an ignored uint16 between, x/y/z float64 at unaligned offsets, 3 bytes
    # of padding at the end: point_step 37
    fields = [('velocity', 0, FLOAT32), ('intensity', 4, UINT16), ('z', 6, FLOAT64),
              ('x', 14, FLOAT64), ('y', 22, FLOAT64)]
    points = [dict(p, intensity=7) for p in POINTS]
    msg = hand_cloud(ts, fields, points, point_step=37, big_endian=big_endian)
    frame = m.decode_pointcloud(msg)
    np.testing.assert_array_equal(frame.positions_m, XYZ)
    np.testing.assert_array_equal(frame.radial_velocity_mps, VEL)


@pytest.mark.parametrize('big_endian', [False, True])
@pytest.mark.parametrize('datatype', [FLOAT32, FLOAT64])
def test_spherical(ts: Any, big_endian: bool, datatype: int) -> None:
    size = 4 if datatype == FLOAT32 else 8
    spherical = [{'range': 10.0, 'azimuth': math.pi / 6, 'elevation': -0.1, 'doppler': 2.0},
                 {'range': 55.5, 'azimuth': -1.0, 'elevation': 0.15, 'doppler': -7.0},
                 {'range': 3.0, 'azimuth': 0.0, 'elevation': 0.0, 'doppler': 0.5}]
    fields = [(n, i * size, datatype)
              for i, n in enumerate(('range', 'azimuth', 'elevation', 'doppler'))]
    msg = hand_cloud(ts, fields, spherical, point_step=4 * size + 2, big_endian=big_endian)
    frame = m.decode_pointcloud(msg)
    cast = np.float32 if datatype == FLOAT32 else np.float64
    for row, p in zip(frame.positions_m, spherical):
        r, az, el = (float(cast(p[k])) for k in ('range', 'azimuth', 'elevation'))
        expected = [r * math.cos(el) * math.cos(az), r * math.cos(el) * math.sin(az),
                    r * math.sin(el)]
        np.testing.assert_allclose(row, expected, rtol=0, atol=1e-12)
    np.testing.assert_array_equal(frame.radial_velocity_mps, [2.0, -7.0, 0.5])


@pytest.mark.parametrize('angle', ['azimuth', 'elevation'])
def test_spherical_angles_in_degrees_are_refused_by_name(ts: Any, angle: str) -> None:
    """Angles beyond +-pi (azimuth) or +-pi/2 (elevation) cannot be radians: a driver
    writing degrees gets a DecodeError that says so, not targets scattered round the radar
    (a probe's recording failed as 'vehicle never seen' with advice for a sparse radar)."""
    points = [{'range': 20.0, 'azimuth': 0.3, 'elevation': -0.05, 'doppler': 1.0},
              {'range': 30.0, 'azimuth': -0.2, 'elevation': 0.02, 'doppler': 2.0}]
    points[1][angle] = 45.0 if angle == 'azimuth' else -5.0
    fields = [(n, i * 4, FLOAT32)
              for i, n in enumerate(('range', 'azimuth', 'elevation', 'doppler'))]
    with pytest.raises(DecodeError, match='radians'):
        m.decode_pointcloud(hand_cloud(ts, fields, points, point_step=16))


def test_xyz_preferred_over_spherical(ts: Any) -> None:
    fields = [('x', 0, FLOAT32), ('y', 4, FLOAT32), ('z', 8, FLOAT32), ('range', 12, FLOAT32),
              ('azimuth', 16, FLOAT32), ('elevation', 20, FLOAT32), ('velocity', 24, FLOAT32)]
    points = [dict(p, range=999.0, azimuth=1.0, elevation=1.0) for p in POINTS]
    frame = m.decode_pointcloud(hand_cloud(ts, fields, points, point_step=28))
    np.testing.assert_array_equal(frame.positions_m, XYZ)


def test_spherical_angle_fields_spelled_with_angle(ts: Any) -> None:
    """range, azimuth_angle, elevation_angle, range_rate (the ARS548 driver's spelling; an
    eighth probe's cloud was refused as having no position fields) decode as range,
    azimuth, elevation."""
    names = ('range', 'azimuth_angle', 'elevation_angle', 'range_rate')
    fields = [(n, i * 4, FLOAT32) for i, n in enumerate(names)]
    point = {'range': 20.0, 'azimuth_angle': 0.5, 'elevation_angle': -0.1, 'range_rate': -4.0}
    frame = m.decode_pointcloud(hand_cloud(ts, fields, [point], point_step=16))
    r, az, el = (float(np.float32(v)) for v in (20.0, 0.5, -0.1))
    np.testing.assert_allclose(frame.positions_m, [[r * math.cos(el) * math.cos(az),
                                                    r * math.cos(el) * math.sin(az),
                                                    r * math.sin(el)]], atol=1e-6)
    np.testing.assert_array_equal(frame.radial_velocity_mps, [-4.0])


def test_a_bare_v_is_the_velocity_unless_beside_a_u(ts: Any) -> None:
    """x, y, z, v: v is the radial velocity (the last name tried); x, y, z, u, v (a
    camera's texture coordinates) has no radial velocity."""
    xyzv = [('x', 0, FLOAT32), ('y', 4, FLOAT32), ('z', 8, FLOAT32), ('v', 12, FLOAT32)]
    points = [dict(p, v=p['velocity']) for p in POINTS]
    frame = m.decode_pointcloud(hand_cloud(ts, xyzv, points, point_step=16))
    np.testing.assert_array_equal(frame.radial_velocity_mps, VEL)
    with_u = xyzv + [('u', 16, FLOAT32)]
    msg = hand_cloud(ts, with_u, points, point_step=20)
    assert m.lacks_velocity_field(msg)
    with pytest.raises(DecodeError, match='no radial-velocity field'):
        m.decode_pointcloud(msg)
    # named, it is taken whatever its neighbours
    np.testing.assert_array_equal(m.decode_pointcloud(msg, 'v').radial_velocity_mps, VEL)


@pytest.mark.parametrize('row_pad', [0, 5])
def test_height_greater_than_one(ts: Any, row_pad: int) -> None:
    rng = np.random.default_rng(3)
    points = [{'x': float(np.float32(v[0])), 'y': float(np.float32(v[1])),
               'z': float(np.float32(v[2])), 'velocity': float(np.float32(v[3]))}
              for v in rng.normal(size=(6, 4)) * 20]
    fields = [(n, i * 4, FLOAT32) for i, n in enumerate(('x', 'y', 'z', 'velocity'))]
    msg = hand_cloud(ts, fields, points, point_step=16, height=2, row_pad=row_pad)
    frame = m.decode_pointcloud(msg)
    np.testing.assert_array_equal(frame.positions_m,
                                  [[p['x'], p['y'], p['z']] for p in points])
    np.testing.assert_array_equal(frame.radial_velocity_mps, [p['velocity'] for p in points])


@pytest.mark.parametrize('name', m.VELOCITY_FIELD_NAMES)
def test_every_velocity_name(ts: Any, name: str) -> None:
    fields = [('x', 0, FLOAT32), ('y', 4, FLOAT32), ('z', 8, FLOAT32), (name, 12, FLOAT32)]
    points = [dict(p, **{name: p['velocity']}) for p in POINTS]
    frame = m.decode_pointcloud(hand_cloud(ts, fields, points, point_step=16))
    np.testing.assert_array_equal(frame.radial_velocity_mps, VEL)


def test_velocity_field_order_and_parameter(ts: Any) -> None:
    fields = [('x', 0, FLOAT32), ('y', 4, FLOAT32), ('z', 8, FLOAT32), ('doppler', 12, FLOAT32),
              ('radial_velocity', 16, FLOAT32), ('speed_raw', 20, INT16)]
    points = [dict(p, doppler=1.0, radial_velocity=2.0, speed_raw=-3) for p in POINTS]
    msg = hand_cloud(ts, fields, points, point_step=24)
    # the contract's order: radial_velocity comes before doppler
    np.testing.assert_array_equal(m.decode_pointcloud(msg).radial_velocity_mps, [2.0] * 3)
    np.testing.assert_array_equal(m.decode_pointcloud(msg, 'doppler').radial_velocity_mps,
                                  [1.0] * 3)
    # an integer velocity field is accepted when named
    np.testing.assert_array_equal(m.decode_pointcloud(msg, 'speed_raw').radial_velocity_mps,
                                  [-3.0] * 3)


def test_field_names_in_another_case(ts: Any) -> None:
    """CARLA's ROS bridge writes x, y, z, Range, Velocity, AzimuthAngle, ElevationAngle:
    its velocity is found in another case, named or not; a name two fields share in other
    cases is not guessed."""
    fields = [('x', 0, FLOAT32), ('y', 4, FLOAT32), ('z', 8, FLOAT32), ('Range', 12, FLOAT32),
              ('Velocity', 16, FLOAT32), ('AzimuthAngle', 20, FLOAT32),
              ('ElevationAngle', 24, FLOAT32)]
    points = [dict(p, Velocity=p['velocity'], Range=9.0) for p in POINTS]
    msg = hand_cloud(ts, fields, points, point_step=28)
    frame = m.decode_pointcloud(msg)
    np.testing.assert_array_equal(frame.positions_m, XYZ)
    np.testing.assert_array_equal(frame.radial_velocity_mps, VEL)
    np.testing.assert_array_equal(m.decode_pointcloud(msg, 'velocity').radial_velocity_mps, VEL)
    # spherical fields in capitals
    spherical = [('RANGE', 0, FLOAT32), ('Azimuth', 4, FLOAT32), ('Elevation', 8, FLOAT32),
                 ('Doppler', 12, FLOAT32)]
    frame = m.decode_pointcloud(hand_cloud(
        ts, spherical, [{'RANGE': 10.0, 'Azimuth': 0.0, 'Elevation': 0.0, 'Doppler': -2.0}],
        point_step=16))
    np.testing.assert_allclose(frame.positions_m, [[10.0, 0.0, 0.0]], atol=1e-6)
    np.testing.assert_array_equal(frame.radial_velocity_mps, [-2.0])
    twice = [('x', 0, FLOAT32), ('y', 4, FLOAT32), ('z', 8, FLOAT32), ('VELOCITY', 12, FLOAT32),
             ('Velocity', 16, FLOAT32)]
    with pytest.raises(DecodeError, match="no radial-velocity field"):
        m.decode_pointcloud(hand_cloud(ts, twice, POINTS, point_step=20))


def test_nonfinite_rows_dropped_and_counted(ts: Any) -> None:
    points = [dict(POINTS[0]), dict(POINTS[1], x=math.nan), dict(POINTS[2]),
              dict(POINTS[0], velocity=math.inf), dict(POINTS[1], z=-math.inf)]
    fields = [(n, i * 4, FLOAT32) for i, n in enumerate(('x', 'y', 'z', 'velocity'))]
    frame = m.decode_pointcloud(hand_cloud(ts, fields, points, point_step=16))
    assert frame.dropped_nonfinite == 3
    # the cloud says it may hold invalid points (is_dense false): the node counts, not warns
    assert frame.invalid_declared
    dense = m.encode_pointcloud(ts, STAMP_NS, 'radar', XYZ, VEL)
    assert dense.is_dense and not m.decode_pointcloud(dense).invalid_declared
    np.testing.assert_array_equal(frame.positions_m, XYZ[[0, 2]])
    np.testing.assert_array_equal(frame.radial_velocity_mps, VEL[[0, 2]])


@pytest.mark.parametrize('container', ['array', 'bytes', 'memoryview'])
def test_rclpy_like_message(ts: Any, container: str) -> None:
    """rclpy messages: data as array.array('B') or bytes, fields as plain objects."""
    fields = [(n, i * 4, FLOAT32) for i, n in enumerate(('x', 'y', 'z', 'velocity'))]
    msg = hand_cloud(ts, fields, POINTS, point_step=16, big_endian=True)
    raw = msg.data.tobytes()
    data = {'array': array.array('B', raw), 'bytes': raw, 'memoryview': memoryview(raw)}
    duck = SimpleNamespace(
        header=SimpleNamespace(stamp=SimpleNamespace(sec=msg.header.stamp.sec,
                                                     nanosec=msg.header.stamp.nanosec)),
        fields=[SimpleNamespace(name=f.name, offset=f.offset, datatype=f.datatype, count=1)
                for f in msg.fields],
        point_step=16, width=3, height=1, is_bigendian=True, data=data[container])
    frame = m.decode_pointcloud(duck)
    assert frame.stamp_ns == STAMP_NS
    np.testing.assert_array_equal(frame.positions_m, XYZ)
    np.testing.assert_array_equal(frame.radial_velocity_mps, VEL)


def test_empty_cloud_without_fields(ts: Any) -> None:
    frame = m.decode_pointcloud(hand_cloud(ts, [], [], point_step=0))
    assert frame.positions_m.shape == (0, 3) and frame.radial_velocity_mps.shape == (0,)


# --- decode errors -----------------------------------------------------------------------

XYZV32 = [(n, i * 4, FLOAT32) for i, n in enumerate(('x', 'y', 'z', 'velocity'))]


def test_error_truncated_data(ts: Any) -> None:
    msg = hand_cloud(ts, XYZV32, POINTS, point_step=16, truncate=1)
    with pytest.raises(DecodeError, match=r'47 bytes.*width 3 x height 1 x point_step 16 = 48'):
        m.decode_pointcloud(msg)


def test_error_truncated_rows(ts: Any) -> None:
    msg = hand_cloud(ts, XYZV32, POINTS * 2, point_step=16, height=2, row_pad=4, truncate=10)
    with pytest.raises(DecodeError, match='row_step 52'):
        m.decode_pointcloud(msg)


def test_error_point_step_smaller_than_fields(ts: Any) -> None:
    msg = hand_cloud(ts, XYZV32, POINTS, point_step=16)
    small = SimpleNamespace(**{k: getattr(msg, k) for k in (
        'header', 'fields', 'width', 'height', 'is_bigendian', 'data')}, point_step=12)
    with pytest.raises(DecodeError, match='point_step 12 is smaller than its fields'):
        m.decode_pointcloud(small)


def test_error_no_positions(ts: Any) -> None:
    # (x, y without z is a 2-D radar's, read level: see the test above)
    fields = [('x', 0, FLOAT32), ('z', 4, FLOAT32), ('range', 8, FLOAT32),
              ('velocity', 12, FLOAT32)]
    with pytest.raises(DecodeError, match='neither x/y/z nor range/azimuth/elevation.*'
                       'x, z, range, velocity'):
        m.decode_pointcloud(hand_cloud(ts, fields, POINTS, point_step=16))


def test_error_no_velocity_lists_fields(ts: Any) -> None:
    fields = [('x', 0, FLOAT32), ('y', 4, FLOAT32), ('z', 8, FLOAT32), ('rcs', 12, FLOAT32)]
    msg = hand_cloud(ts, fields, POINTS, point_step=16)
    with pytest.raises(DecodeError, match=r'no radial-velocity field.*fields found: x, y, z, '
                       'rcs$'):
        m.decode_pointcloud(msg)
    # x, y, z, intensity: Autoware's doppler_pointcloud keeps the velocity in intensity
    autoware = hand_cloud(ts, fields[:3] + [('intensity', 12, FLOAT32)], POINTS, point_step=16)
    with pytest.raises(DecodeError, match=r"fields found: x, y, z, intensity; a radar cloud "
                       r"from Autoware's .* set radar.velocity_field: intensity$"):
        m.decode_pointcloud(autoware)
    with pytest.raises(DecodeError, match=r"no velocity field 'v'.*fields found: x, y, z, rcs"):
        m.decode_pointcloud(msg, 'v')


@pytest.mark.parametrize('datatype, label', [(INT16, 'INT16'), (42, 'unknown datatype 42')])
def test_error_unsupported_datatype(ts: Any, datatype: int, label: str) -> None:
    msg = hand_cloud(ts, XYZV32, POINTS, point_step=16)
    msg.fields[0].datatype = datatype
    with pytest.raises(DecodeError, match=f"field 'x' has unsupported datatype {label}"):
        m.decode_pointcloud(msg)
    msg.fields[0].datatype = FLOAT32
    msg.fields[3].datatype = 42
    with pytest.raises(DecodeError, match="field 'velocity' has unsupported datatype"):
        m.decode_pointcloud(msg)


def test_errors_are_one_line(ts: Any) -> None:
    msg = hand_cloud(ts, XYZV32[:3], POINTS, point_step=16)
    with pytest.raises(DecodeError) as info:
        m.decode_pointcloud(msg)
    assert '\n' not in str(info.value)


# --- encoders ----------------------------------------------------------------------------

@pytest.mark.parametrize('layout', ['xyz', 'spherical'])
@pytest.mark.parametrize('dtype', [np.float32, np.float64])
@pytest.mark.parametrize('big_endian', [False, True])
def test_encode_pointcloud_round_trip(ts: Any, layout: str, dtype: Any,
                                      big_endian: bool) -> None:
    rng = np.random.default_rng(7)
    positions = rng.uniform(-60, 60, size=(50, 3)) + [70.0, 0.0, 0.0]
    velocity = rng.normal(0, 8, 50)
    msg = m.encode_pointcloud(ts, STAMP_NS, 'radar', positions, velocity, layout=layout,
                              dtype=dtype, big_endian=big_endian, pad_bytes=3,
                              velocity_field='range_rate',
                              extra_fields={'rcs': rng.normal(size=50).astype(np.float32),
                                            'id': np.arange(50, dtype=np.uint16)})
    back = ts.deserialize_cdr(ts.serialize_cdr(msg, m.POINTCLOUD2), m.POINTCLOUD2)
    assert [f.name for f in back.fields][-3:] == ['range_rate', 'rcs', 'id']
    assert back.point_step == (3 + 1) * np.dtype(dtype).itemsize + 4 + 2 + 3
    frame = m.decode_pointcloud(back)
    assert frame.stamp_ns == STAMP_NS and back.header.frame_id == 'radar'
    tol = 1e-9 if dtype is np.float64 else 1e-4  # float32 of ~100 m: 4e-6 relative
    np.testing.assert_allclose(frame.positions_m, positions, rtol=0, atol=tol * 100)
    np.testing.assert_allclose(frame.radial_velocity_mps, velocity, rtol=0, atol=tol * 10)


def test_encode_navsatfix_and_odometry_round_trip(ts: Any) -> None:
    fix = m.encode_navsatfix(ts, STAMP_NS, 'gnss', 48.123456789, 11.987654321, 523.25,
                             status=-1, position_sigma_m=0.03)
    fix = ts.deserialize_cdr(ts.serialize_cdr(fix, m.NAVSATFIX), m.NAVSATFIX)
    sample = m.decode_navsatfix(fix)
    assert (sample.stamp_ns, sample.lat_deg, sample.lon_deg, sample.alt_m, sample.status) == (
        STAMP_NS, 48.123456789, 11.987654321, 523.25, -1)
    np.testing.assert_allclose(np.diag(fix.position_covariance.reshape(3, 3)), [9e-4] * 3)
    assert sample.position_sigma_m == pytest.approx((0.03, 0.03))
    # (horizontal, vertical) sigmas, and an unknown covariance read as NaN
    fix = m.encode_navsatfix(ts, STAMP_NS, 'gnss', 48.1, 11.9, 500.0, status=0,
                             position_sigma_m=(1.5, 2.5))
    assert m.decode_navsatfix(fix).position_sigma_m == pytest.approx((1.5, 2.5))
    fix = m.encode_navsatfix(ts, STAMP_NS, 'gnss', 48.1, 11.9, 500.0,
                             position_sigma_m=(math.nan, math.nan))
    assert fix.position_covariance_type == 0
    assert all(math.isnan(v) for v in m.decode_navsatfix(fix).position_sigma_m)
    q = (0.0, 0.0, math.sin(0.4), math.cos(0.4))
    odom = m.encode_odometry(ts, STAMP_NS + 5, 'map', 'base_link', (1.0, -2.0, 3.5), q,
                             (12.0, 0.5, -0.25), 0.3)
    odom = ts.deserialize_cdr(ts.serialize_cdr(odom, m.ODOMETRY), m.ODOMETRY)
    sample = m.decode_odometry(odom)
    assert sample.stamp_ns == STAMP_NS + 5 and odom.child_frame_id == 'base_link'
    assert sample.position_m == (1.0, -2.0, 3.5) and sample.quaternion_xyzw == q
    assert sample.velocity_body_mps == (12.0, 0.5, -0.25) and sample.yaw_rate_rps == 0.3


def test_encode_rejects_bad_arguments(ts: Any) -> None:
    with pytest.raises(ValueError, match='layout'):
        m.encode_pointcloud(ts, 0, 'r', np.zeros((1, 3)), np.zeros(1), layout='polar')
    with pytest.raises(ValueError, match='float32 or float64'):
        m.encode_pointcloud(ts, 0, 'r', np.zeros((1, 3)), np.zeros(1), dtype=np.int32)


# --- typestore and radar_msgs ------------------------------------------------------------

def test_typestore_fresh_and_has_radar_msgs() -> None:
    a, b = m.get_typestore(), m.get_typestore()
    assert a is not b
    for msgtype in (m.POINTCLOUD2, m.NAVSATFIX, m.ODOMETRY, m.RADARSCAN,
                    'radar_msgs/msg/RadarReturn', 'geometry_msgs/msg/TransformStamped',
                    'tf2_msgs/msg/TFMessage', 'diagnostic_msgs/msg/DiagnosticArray'):
        assert msgtype in a.types
    a.register(get_types_from_msg('float64 a', 'extra_msgs/msg/Only'))
    assert 'extra_msgs/msg/Only' not in b.types


def test_radarscan_round_trip(ts: Any) -> None:
    types = ts.types
    ret = types['radar_msgs/msg/RadarReturn']
    returns = [ret(range=10.0, azimuth=0.5, elevation=-0.05, doppler_velocity=-3.0,
                   amplitude=20.0),
               ret(range=math.nan, azimuth=0.0, elevation=0.0, doppler_velocity=0.0,
                   amplitude=0.0),
               ret(range=40.0, azimuth=-0.25, elevation=0.0, doppler_velocity=1.5,
                   amplitude=10.0)]
    scan = types[m.RADARSCAN](header=m.encode_navsatfix(ts, STAMP_NS, 'radar', 0, 0, 0).header,
                              returns=returns)
    scan = ts.deserialize_cdr(ts.serialize_cdr(scan, m.RADARSCAN), m.RADARSCAN)
    frame = m.decode_radarscan(scan)
    assert frame.stamp_ns == STAMP_NS and frame.dropped_nonfinite == 1
    r, az, el = np.float32(10.0), np.float32(0.5), np.float32(-0.05)
    np.testing.assert_allclose(frame.positions_m[0], [r * np.cos(el) * np.cos(az),
                                                      r * np.cos(el) * np.sin(az),
                                                      r * np.sin(el)], atol=1e-6)
    np.testing.assert_array_equal(frame.radial_velocity_mps, [-3.0, 1.5])


def test_msg_schemas_found_in_installed_layout(tmp_path: Path) -> None:
    """colcon/pip put data_files under <prefix>/share/radar_calib_ros/msg_schemas."""
    package = tmp_path / 'lib' / 'python3.12' / 'site-packages' / 'radar_calib_ros' / 'io'
    package.mkdir(parents=True)
    share = tmp_path / 'share' / 'radar_calib_ros' / 'msg_schemas'
    share.mkdir(parents=True)
    (share / 'radar_msgs__msg__RadarReturn.msg').write_text('float32 range\n')
    assert m.msg_schemas_dir(package / 'messages.py') == share


def test_msg_schemas_readme_names_every_definition() -> None:
    directory = m.msg_schemas_dir()
    readme = (directory / 'README.md').read_text(encoding='utf-8')
    files = sorted(p.name for p in directory.glob('*.msg'))
    assert files and all(f'`{name}`' in readme for name in files)


@pytest.mark.parametrize('names', [('vx', 'vy'), ('vx', 'vy', 'vz'),
                                   ('velocity_x', 'velocity_y', 'velocity_z')])
def test_velocity_components_give_the_radial_velocity(ts: Any, names: tuple[str, ...]) -> None:
    """An object list gives each object's velocity in the sensor frame, no Doppler (an
    independent probe's vx, vy cloud was refused, and naming vx as the velocity field
    calibrated nothing): the radial velocity is its projection on the line of sight."""
    fields = [(n, i * 4, FLOAT32) for i, n in enumerate(('x', 'y', 'z', *names))]
    velocity = [(10.0, 0.0, 0.0), (0.0, -5.0, 0.0), (3.0, 4.0, 1.0)]
    points = [dict(p, **dict(zip(names, v))) for p, v in zip(POINTS, velocity)]
    frame = m.decode_pointcloud(hand_cloud(ts, fields, points, point_step=4 * len(fields)))
    xyz = frame.positions_m
    v = np.array(velocity)[:, :len(names)]
    expected = np.sum(xyz[:, :len(names)] * v, axis=1) / np.linalg.norm(xyz, axis=1)
    np.testing.assert_allclose(frame.radial_velocity_mps, expected, rtol=1e-6)
    assert frame.velocity_components == names
    # a radial velocity beside the components is the radar's own: taken as it is
    with_radial = [*fields, ('velocity', 4 * len(fields), FLOAT32)]
    frame = m.decode_pointcloud(hand_cloud(ts, with_radial, points,
                                           point_step=4 * len(with_radial)))
    np.testing.assert_array_equal(frame.radial_velocity_mps, VEL)
    assert frame.velocity_components == ()


def test_a_lone_velocity_component_is_no_radial_velocity(ts: Any) -> None:
    """vx without vy is not a velocity the line of sight can be projected on: refused,
    naming what was looked for."""
    fields = [('x', 0, FLOAT32), ('y', 4, FLOAT32), ('z', 8, FLOAT32), ('vx', 12, FLOAT32)]
    with pytest.raises(DecodeError, match='velocity components vx, vy'):
        m.decode_pointcloud(hand_cloud(ts, fields, POINTS, point_step=16))
    assert m.lacks_velocity_field(hand_cloud(ts, fields, POINTS, point_step=16))


@pytest.mark.parametrize('layout', [('x', 'y'), ('range', 'azimuth')])
def test_a_2d_radar_without_its_third_coordinate_is_read_level(
        ts: Any, layout: tuple[str, str]) -> None:
    """A 2-D radar's cloud of x, y (or range, azimuth) and a Doppler, without z or
    elevation (an independent probe's range, azimuth, doppler was refused while the same
    targets as x, y, 0 calibrated): read with z = 0."""
    fields = [(layout[0], 0, FLOAT32), (layout[1], 4, FLOAT32), ('doppler', 8, FLOAT32)]
    if layout == ('x', 'y'):
        points = [{'x': 10.0, 'y': -2.0, 'doppler': 1.5}]
    else:
        points = [{'range': 10.0, 'azimuth': -0.2, 'doppler': 1.5}]
    frame = m.decode_pointcloud(hand_cloud(ts, fields, points, point_step=12))
    expected = ([10.0, -2.0, 0.0] if layout == ('x', 'y')
                else [10.0 * math.cos(-0.2), 10.0 * math.sin(-0.2), 0.0])
    np.testing.assert_allclose(frame.positions_m, [expected], atol=1e-5)
    np.testing.assert_array_equal(frame.radial_velocity_mps, [1.5])
    with pytest.raises(DecodeError, match='neither x/y/z'):
        m.decode_pointcloud(hand_cloud(ts, [('x', 0, FLOAT32), ('doppler', 4, FLOAT32)],
                                       [{'x': 1.0, 'doppler': 0.0}], point_step=8))
