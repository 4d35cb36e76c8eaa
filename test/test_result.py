"""Result conversion local -> UTM, the result files, and their validation."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pyproj
import pytest
import yaml
from scipy.spatial.transform import Rotation

from radar_calib_ros.errors import ResultFileError
from radar_calib_ros.io.geo import LocalFrame
from radar_calib_ros.result import (
    calibration_dict, extrinsics_to_utm, load_result, utm_to_extrinsics, write_atomic,
    write_result_json, write_result_yaml)
from radar_calib_ros.types import Extrinsics

SITES = [(48.40, 9.99), (48.0, 12.5), (-33.9, 18.4), (60.2, 24.9)]


def _rz(deg: float) -> np.ndarray:
    return Rotation.from_euler('z', deg, degrees=True).as_matrix()


@pytest.mark.parametrize('lat, lon', SITES)
def test_boresight_pointing_true_north_reads_zero(lat: float, lon: float) -> None:
    frame = LocalFrame.at(lat, lon)
    # local grid north is true north at the frame's origin, so yaw 90 deg points north
    cal = calibration_dict(Extrinsics(_rz(90.0), np.zeros(3)), frame)
    assert abs((cal['boresight_azimuth_deg'] + 180.0) % 360.0 - 180.0) < 1e-6
    # the UTM grid yaw differs from 90 deg by the meridian convergence (pyproj's sign:
    # positive east of the central meridian in the north)
    conv = pyproj.Proj(f'EPSG:{frame.epsg}').get_factors(lon, lat).meridian_convergence
    assert cal['rpy_deg'][2] == pytest.approx(90.0 + conv, abs=1e-4)


@pytest.mark.parametrize('lat, lon', SITES)
def test_utm_round_trip(lat: float, lon: float) -> None:
    frame = LocalFrame.at(lat, lon)
    ext = Extrinsics(Rotation.from_euler('xyz', [1.5, 8.0, -130.0], degrees=True).as_matrix(),
                     np.array([35.0, -80.0, 490.0]))
    r_utm, t_utm = extrinsics_to_utm(ext, frame)
    back = utm_to_extrinsics(r_utm, t_utm, frame)
    assert np.allclose(back.rotation, ext.rotation, atol=1e-12)
    assert np.allclose(back.translation_m, ext.translation_m, atol=1e-6)
    e, n = pyproj.Transformer.from_crs('EPSG:4326', f'EPSG:{frame.epsg}', always_xy=True
                                       ).transform(*frame.local_to_geodetic(
                                           ext.translation_m[None])[1::-1])
    assert np.allclose(t_utm[:2], [e[0], n[0]], atol=1e-6)


def test_result_yaml_is_a_ros_parameters_file(tmp_path: Path) -> None:
    frame = LocalFrame.at(48.4, 9.99)
    cal = calibration_dict(Extrinsics(_rz(10.0), np.array([1.0, 2.0, 480.0])), frame,
                           quality={'inlier_ratio': np.float64(0.7), 'advice': []})
    write_result_yaml(tmp_path / 'r.yaml', cal)
    doc = yaml.safe_load((tmp_path / 'r.yaml').read_text())
    body = doc['/**']['ros__parameters']['calibration']
    assert list(body) == ['world_frame', 'radar_frame', 'epsg', 'translation',
                          'quaternion_xyzw', 'rpy_deg', 'latitude', 'longitude', 'altitude',
                          'boresight_azimuth_deg', 'stamp', 'quality']
    assert body['quality']['inlier_ratio'] == pytest.approx(0.7)
    # an empty list has no ROS 2 parameter type (a node declaring its parameters from the
    # file would not start): left out of the YAML, put back empty on loading
    assert 'advice' not in body['quality']
    loaded = load_result(tmp_path / 'r.yaml')
    assert loaded['epsg'] == frame.epsg and loaded['quality']['advice'] == []
    write_result_json(tmp_path / 'r.json', cal)
    assert json.loads((tmp_path / 'r.json').read_text())['quality']['advice'] == []
    assert json.loads((tmp_path / 'r.json').read_text())['translation'] == cal['translation']
    assert load_result(tmp_path / 'r.json')['translation'] == cal['translation']


@pytest.mark.parametrize('text, match', [
    ('', 'no calibration mapping'),
    ('/**: {ros__parameters: {calibration: {epsg: 32632}}}', 'lacks translation'),
    ('{"epsg": 32632, "translation": [1, 2], "quaternion_xyzw": [0, 0, 0, 1]}',
     'translation must be 3 finite numbers'),
    ('{"epsg": 32632, "translation": [1, 2, 3], "quaternion_xyzw": [0, 0, 0, 2]}',
     'unit quaternion'),
    ('{"epsg": "x", "translation": [1, 2, 3], "quaternion_xyzw": [0, 0, 0, 1]}',
     'epsg must be an integer'),
    ('{"epsg": 3', 'not valid YAML'),
])
def test_corrupt_result_files(tmp_path: Path, text: str, match: str) -> None:
    path = tmp_path / 'r.yaml'
    path.write_text(text)
    with pytest.raises(ResultFileError, match=match):
        load_result(path)


def _result_file(tmp_path: Path, **edits: object) -> Path:
    frame = LocalFrame.at(48.4, 9.99)
    cal = calibration_dict(Extrinsics(_rz(10.0), np.array([1.0, 2.0, 480.0])), frame)
    cal.update(edits)
    write_result_yaml(tmp_path / 'r.yaml', cal)
    return tmp_path / 'r.yaml'


def test_a_hand_edited_rpy_or_position_contradicting_the_file_is_refused(
        tmp_path: Path) -> None:
    cal = load_result(_result_file(tmp_path))
    roll, pitch, yaw = cal['rpy_deg']
    with pytest.raises(ResultFileError, match=r'rpy_deg .* disagree by 2\.000 deg; the tool '
                       'uses quaternion_xyzw'):
        load_result(_result_file(tmp_path, rpy_deg=[roll, pitch, yaw + 2.0]))
    with pytest.raises(ResultFileError, match=r'lie 1\.1.. m from translation') as err:
        load_result(_result_file(tmp_path, latitude=cal['latitude'] + 1e-5))
    # numbers as numbers, not numpy's repr
    assert 'np.' not in str(err.value) and 'translation [' in str(err.value)
    with pytest.raises(ResultFileError, match='rpy_deg must be 3 numbers'):
        load_result(_result_file(tmp_path, rpy_deg=[0.0, 'x', 1.0]))
    # a file of the three keys the tool uses alone is fine
    minimal = {k: cal[k] for k in ('epsg', 'translation', 'quaternion_xyzw')}
    (tmp_path / 'min.json').write_text(json.dumps(minimal))
    assert load_result(tmp_path / 'min.json')['translation'] == cal['translation']


@pytest.mark.parametrize('lat, lon, epsg', [(48.4, 11.99, 32632), (48.4, 11.99, 32633),
                                            (-33.9, 18.4, 0), (60.2, 24.9, 3067)])
def test_written_results_load_in_any_zone(tmp_path: Path, lat: float, lon: float,
                                          epsg: int) -> None:
    """The redundant keys agree with the ones used wherever the frame's grid lies (a zone
    forced by world.epsg, a national grid)."""
    frame = LocalFrame.at(lat, lon, epsg)
    ext = Extrinsics(Rotation.from_euler('xyz', [1.5, 8.0, -130.0], degrees=True).as_matrix(),
                     np.array([350.0, -800.0, 490.0]))
    write_result_yaml(tmp_path / 'r.yaml', calibration_dict(ext, frame))
    assert load_result(tmp_path / 'r.yaml')['epsg'] == frame.epsg


def test_every_value_of_result_yaml_survives_ros2_param_load(tmp_path: Path) -> None:
    """Jazzy's ``ros2 param load`` re-parses each value's text as YAML: the extended ISO
    stamp came back a datetime and crashed it (a probe on a real Jazzy build). Every value
    must come back as what it was, and the stamp still read as the time it says."""
    import datetime as dt

    from radar_calib_ros.live import _stamp_ns
    path = _result_file(tmp_path, quality={
        'inlier_ratio': 0.8, 'passes': 4, 'sigma': {'rotation_deg': 0.2},
        'sigma_rotation_covers': 'roll, pitch, yaw',
        'advice': ["The vehicle's front was seen from bearings 7 deg apart: drive again.",
                   'Drive "northbound" again: it shows new sides.']})
    body = yaml.safe_load(path.read_text())['/**']['ros__parameters']

    def leaves(node: object, name: str = '') -> list[tuple[str, object]]:
        if isinstance(node, dict):
            return [x for k, v in node.items() for x in leaves(v, f'{name}.{k}')]
        return [(name, node)]
    for name, value in leaves(body):
        again = yaml.safe_load(str(value))   # what rclpy's get_parameter_value does
        assert type(again) is type(value) and again == value, name
    stamp = body['calibration']['stamp']
    assert stamp.endswith('Z') and len(stamp) == 16
    now = dt.datetime.now(dt.timezone.utc).timestamp()
    assert abs(_stamp_ns(stamp) * 1e-9 - now) < 60
    # files written before (extended form, or the datetime YAML made of it) still load
    assert _stamp_ns('2026-11-27T08:25:48+00:00') == _stamp_ns('20261127T082548Z')


def test_writing_under_a_file_or_onto_a_directory_names_it(tmp_path: Path) -> None:
    (tmp_path / 'plain').write_text('x')
    with pytest.raises(NotADirectoryError, match="'.*plain' is a file, not a directory"):
        write_atomic(tmp_path / 'plain' / 'sub' / 'r.yaml', 'x: 1\n')
    (tmp_path / 'dir').mkdir()
    with pytest.raises(IsADirectoryError, match="'.*dir' is a directory: give a file name"):
        write_atomic(tmp_path / 'dir', 'x: 1\n')
    assert (tmp_path / 'plain').read_text() == 'x' and not list((tmp_path / 'dir').iterdir())


def test_write_atomic_keeps_old_file_on_failure(tmp_path: Path) -> None:
    path = tmp_path / 'r.yaml'
    write_atomic(path, 'old\n')

    with pytest.raises(TypeError):
        write_atomic(path, 123)  # type: ignore[arg-type]
    assert path.read_text() == 'old\n'
    assert [p.name for p in tmp_path.iterdir()] == ['r.yaml']


def test_written_files_get_the_umask_permissions(tmp_path: Path) -> None:
    """Not mkstemp's 0600: a node running as another user must be able to read a result."""
    import os
    import stat

    old = os.umask(0o022)
    try:
        write_atomic(tmp_path / 'r.yaml', 'x: 1\n')
        os.umask(0o077)
        write_atomic(tmp_path / 'private.yaml', 'x: 1\n')
    finally:
        os.umask(old)
    assert stat.S_IMODE((tmp_path / 'r.yaml').stat().st_mode) == 0o644
    assert stat.S_IMODE((tmp_path / 'private.yaml').stat().st_mode) == 0o600


def test_a_file_of_several_radars_gives_the_one_asked_for(tmp_path: Path) -> None:
    """What --all-radars writes (the combined parameters file, its JSON keyed by frame)
    can be evaluated: the calibration of radar.frame_id, or the only one; otherwise the
    error lists the frames (it used to say 'no calibration mapping')."""
    from radar_calib_ros.multi_radar import combined_parameters

    frame = LocalFrame.at(48.4, 9.99)
    cals = {name: calibration_dict(Extrinsics(_rz(deg), np.array([deg, 2.0, 480.0])), frame,
                                   radar_frame=name)
            for name, deg in (('radar_ne', 10.0), ('radar_sw', 190.0))}
    (tmp_path / 'all.yaml').write_text(yaml.safe_dump(combined_parameters(cals)))
    write_atomic(tmp_path / 'all.json', json.dumps(cals))
    for name in ('all.yaml', 'all.json'):
        picked = load_result(tmp_path / name, 'radar_sw')
        assert picked['radar_frame'] == 'radar_sw'
        assert picked['translation'] == cals['radar_sw']['translation']
        with pytest.raises(ResultFileError, match=r'several radars \(radar_ne, radar_sw\) and '
                           r"none of frame 'radar': set radar.frame_id"):
            load_result(tmp_path / name, 'radar')
    one = {'radar_ne': cals['radar_ne']}
    (tmp_path / 'one.yaml').write_text(yaml.safe_dump(combined_parameters(one)))
    assert load_result(tmp_path / 'one.yaml', 'radar')['radar_frame'] == 'radar_ne'
