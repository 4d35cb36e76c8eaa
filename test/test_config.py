"""The typed configuration: defaults file, nested/dotted keys, and every rejection path."""
from __future__ import annotations

import logging
from pathlib import Path

import pytest

from radar_calib_ros.config import (
    CalibConfig, default_params_yaml, flatten, parameter_specs, read_params_file)
from radar_calib_ros.errors import ConfigError

ROOT = Path(__file__).resolve().parents[1]


def test_config_file_matches_defaults() -> None:
    assert (ROOT / 'config' / 'calibrator.yaml').read_text() == default_params_yaml()
    assert CalibConfig.from_file(ROOT / 'config' / 'calibrator.yaml') == CalibConfig()


def test_contract_parameters_exist() -> None:
    names = {spec.name for spec in parameter_specs()}
    for name in ('radar_topic', 'navsat_topic', 'odom_topic', 'radar.velocity_field',
                 'radar.frame_id', 'world.epsg', 'sync.time_offset', 'vehicle.length',
                 'vehicle.width', 'vehicle.height', 'vehicle.rear_overhang',
                 'vehicle.ref_height', 'vehicle.odom_is_utm', 'buffer.max_duration',
                 'output.path'):
        assert name in names


def test_nested_and_dotted_keys_are_equivalent() -> None:
    a = CalibConfig.from_mapping({'vehicle': {'length': 4.2}, 'sync.time_offset': 0.04})
    b = CalibConfig.from_mapping({'vehicle.length': 4.2, 'sync': {'time_offset': 0.04}})
    assert a == b
    assert a.vehicle.length == 4.2 and a.sync.time_offset == 0.04
    assert a.explicit == {'vehicle.length', 'sync.time_offset'}


def test_int_is_accepted_for_float_but_not_the_reverse() -> None:
    assert CalibConfig.from_mapping({'vehicle.length': 5}).vehicle.length == 5.0
    with pytest.raises(ConfigError, match="'world.epsg' must be int"):
        CalibConfig.from_mapping({'world.epsg': 32632.0})


@pytest.mark.parametrize('params, match', [
    ({'vehicle.lenght': 4.0}, "unknown parameter 'vehicle.lenght'"),
    ({'vehicle.length': 'long'}, "'vehicle.length' must be float"),
    ({'vehicle.odom_is_utm': 1}, "'vehicle.odom_is_utm' must be bool"),
    ({'vehicle.length': -1.0}, "'vehicle.length' = -1.0 is outside"),
    ({'ground.targets': 'some'}, "'ground.targets' = 'some' is not one of"),
    ({'sync.time_offset': float('nan')}, "'sync.time_offset' must be finite"),
    ({'radar_topic': 3}, "'radar_topic' must be str"),
    # "quality:" with nothing under it in YAML
    ({'quality': None}, "parameter group 'quality' is empty: give its parameters under it"),
    ({'qualty': None}, "unknown parameter 'qualty'"),
    # a sign, not a scale
    ({'radar.velocity_sign': 0.5}, r"'radar.velocity_sign' = 0.5 is not one of \[-1.0, 1.0\]"),
    # the world frame is UTM: degrees or a polar zone would be written as easting/northing
    ({'world.epsg': 4326}, r"'world.epsg' = 4326 \(WGS 84\) is not a UTM zone"),
    ({'world.epsg': 32661}, r"'world.epsg' = 32661 \(WGS 84 / UPS North \(N,E\)\) is not a UTM"),
    ({'world.epsg': 99999}, "'world.epsg' = 99999 is not a known EPSG code"),
])
def test_bad_values_are_named(params: dict[str, object], match: str) -> None:
    with pytest.raises(ConfigError, match=match):
        CalibConfig.from_mapping(params)


def test_utm_zones_of_any_datum_and_both_signs_are_accepted() -> None:
    for code in (32632, 32756, 25832, 26915):
        assert CalibConfig.from_mapping({'world.epsg': code}).world.epsg == code
    assert CalibConfig.from_mapping({'radar.velocity_sign': -1}).radar.velocity_sign == -1.0


def test_params_file_node_keys(tmp_path: Path) -> None:
    path = tmp_path / 'p.yaml'
    path.write_text('/**:\n  ros__parameters:\n    vehicle: {length: 4.0}\n'
                    'calibrator:\n  ros__parameters:\n    vehicle.width: 2.0\n'
                    'other:\n  ros__parameters:\n    vehicle.width: 3.0\n')
    params = read_params_file(path, node_name='calibrator')
    assert params == {'vehicle.length': 4.0, 'vehicle.width': 2.0}


@pytest.mark.parametrize('text, match', [
    ('[1, 2]', 'must be a mapping'),
    ('/**:\n  params: {}\n', 'has no "ros__parameters"'),
    ('/**: {ros__parameters: {a: [}', 'not valid YAML'),
])
def test_bad_params_files(tmp_path: Path, text: str, match: str) -> None:
    path = tmp_path / 'p.yaml'
    path.write_text(text)
    with pytest.raises(ConfigError, match=match):
        CalibConfig.from_file(path)


def test_missing_params_file(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match='cannot read parameters file'):
        CalibConfig.from_file(tmp_path / 'nope.yaml')


def test_flatten_rejects_duplicates() -> None:
    with pytest.raises(ConfigError, match='given twice'):
        flatten({'a.b': 1, 'a': {'b': 2}})


def test_to_flat_round_trip() -> None:
    cfg = CalibConfig.from_mapping({'cluster.eps_m': 1.25, 'world.epsg': 32633})
    assert CalibConfig.from_mapping(cfg.to_flat()) == cfg


def test_offline_sections_of_several_nodes(tmp_path: Path,
                                           caplog: pytest.LogCaptureFixture) -> None:
    """The offline tool takes '/**' and the calibrator's entry, leaves other nodes' alone,
    and refuses to guess between two calibrators (a probe's site file: merged, the last
    winning)."""
    path = tmp_path / 'p.yaml'
    path.write_text('/**:\n  ros__parameters:\n    vehicle: {length: 4.2}\n'
                    'velodyne_driver_node:\n  ros__parameters: {rpm: 600, device_ip: x}\n'
                    '/site/calibrator:\n  ros__parameters:\n    radar.frame_id: south\n')
    config = CalibConfig.from_file(path)
    assert config.radar.frame_id == 'south' and config.vehicle.length == 4.2
    path.write_text('/**:\n  ros__parameters: {vehicle.length: 4.2}\n'
                    '/radar_south/calibrator:\n  ros__parameters: {radar.frame_id: south}\n'
                    '/radar_north/calibrator:\n  ros__parameters: {radar.frame_id: north}\n')
    with pytest.raises(ConfigError, match='several nodes .*radar_south.*radar_north'):
        CalibConfig.from_file(path)
    path.write_text('')
    with caplog.at_level(logging.WARNING):
        assert CalibConfig.from_file(path) == CalibConfig()
    assert 'is empty: the defaults are used' in caplog.text


def test_floats_read_as_ros2_reads_them_and_integers_for_doubles_warned(
        tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    path = tmp_path / 'p.yaml'
    path.write_text('/**:\n  ros__parameters:\n    sync.time_offset: 4e-2\n'
                    '    buffer.max_duration: 600\n    vehicle.length: 5\n')
    with caplog.at_level(logging.WARNING):
        config = CalibConfig.from_file(path)
    assert config.sync.time_offset == pytest.approx(0.04)
    assert config.buffer.max_duration == 600.0
    assert 'buffer.max_duration: 600, vehicle.length: 5 given as integers' in caplog.text
    assert 'would not start' in caplog.text
