"""One typed, validated configuration for the node and the offline tool.

Every parameter of CONTRACT.md and every threshold of the method is a field of a frozen
per-section dataclass below, with its default, a one-line description and its constraint
beside it (the scikit-learn ``_parameter_constraints`` lesson: validate once, at the edge,
and let the stages trust their config). ``CalibConfig.from_mapping`` is the only way in:
the CLI feeds it a parameters file, the node its declared ROS parameters, and
``config/calibrator.yaml`` is generated from (and tested against) these defaults.
"""
from __future__ import annotations

import dataclasses
import logging
import math
import re
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from radar_calib_ros.errors import ConfigError

_LOG = logging.getLogger(__name__)


def _p(default: Any, doc: str, *, lo: float | None = None, hi: float | None = None,
       choices: tuple[str | float, ...] | None = None, read_only: bool = False) -> Any:
    """Declare a parameter field: default, description and constraint side by side."""
    meta = {'doc': doc, 'lo': lo, 'hi': hi, 'choices': choices, 'read_only': read_only}
    return field(default=default, metadata=meta)


@dataclass(frozen=True, slots=True, kw_only=True)
class RadarConfig:
    velocity_field: str = _p('', 'name of the radial-velocity field; empty = find by name')
    frame_id: str = _p('radar', 'child frame id of the published calibration')
    velocity_sign: float = _p(
        1.0, 'sign that makes v_r positive for targets moving away (-1 if the radar '
        'reports approach as positive)', choices=(-1.0, 1.0), lo=-1.0, hi=1.0)
    # Clustering's pairs grow with the square of the targets on each road user, and an
    # imaging radar's 800 a frame at 20 Hz took 35-100 CPU-s and 1.3-1.9 GB for ten minutes
    # (a twenty-ninth probe); every second of a car's hundred targets shows the same parts.
    max_targets_per_frame: int = _p(
        0, 'keep at most this many targets of each radar frame, evenly spread over its '
        'list (for dense imaging radars: time and memory); 0 = keep all', lo=0, hi=1000000)
    # A 2-D radar (no elevation) shows nothing of its own tilt, which moves its position
    # too (a held pitch of 8 deg: half a metre along the boresight); an inclinometer on the
    # mount measures it to a tenth of a degree (a forty-ninth probe was told to measure it
    # and had nowhere to enter it). A radar that measures elevation ignores these.
    mount_roll_deg: float = _p(
        0.0, 'roll of a 2-D radar (no elevation) measured at its mount, as the result\'s '
        'roll (+ = its left side, +y, raised); used where mount_tilt_sigma_deg > 0 [deg]',
        lo=-45.0, hi=45.0)
    mount_pitch_deg: float = _p(
        0.0, 'pitch of a 2-D radar measured at its mount, as the result\'s pitch (+ = '
        'boresight tilted down); used where mount_tilt_sigma_deg > 0 [deg]',
        lo=-45.0, hi=45.0)
    mount_tilt_sigma_deg: float = _p(
        0.0, '1-sigma of radar.mount_roll_deg and mount_pitch_deg; 0 = not measured (a 2-D '
        'radar is then held level with 5 deg of uncertainty) [deg]', lo=0.0, hi=10.0)


@dataclass(frozen=True, slots=True, kw_only=True)
class WorldConfig:
    epsg: int = _p(0, 'EPSG code of the UTM world frame; 0 = zone of the first vehicle fix',
                   lo=0, hi=99999)
    frame_id: str = _p('utm', 'frame id of the world (parent) frame')


@dataclass(frozen=True, slots=True, kw_only=True)
class SyncConfig:
    # GPS or TAI time against UTC is 18, 19 or 37 s off; a radar that stamps its uptime
    # (no time sync) is decades off, and the recorder's clock says by how much
    time_offset: float = _p(0.0, 'seconds added to radar stamps before matching to poses',
                            lo=-4.0e9, hi=4.0e9)
    estimate_time_offset: bool = _p(
        True, 'estimate the remaining radar/GNSS clock offset in the final refinement')
    max_time_offset: float = _p(0.25, 'largest clock offset searched for [s]', lo=0.0, hi=2.0)
    max_pose_gap: float = _p(0.5, 'longest pose gap interpolated across [s]', lo=0.02, hi=10.0)


@dataclass(frozen=True, slots=True, kw_only=True)
class VehicleConfig:
    length: float = _p(4.9, 'calibration vehicle length [m]', lo=1.0, hi=25.0)
    width: float = _p(1.9, 'calibration vehicle width [m]', lo=0.5, hi=4.0)
    height: float = _p(1.5, 'calibration vehicle height [m]', lo=0.5, hi=5.0)
    rear_overhang: float = _p(1.0, 'reference point to rear bumper, along -x [m]',
                              lo=-5.0, hi=25.0)
    ref_height: float = _p(0.35, 'reference point above the ground [m]', lo=-1.0, hi=5.0)
    ref_left: float = _p(0.0, 'reference point to the left of the vehicle\'s centre line (an '
                         'off-centre GNSS antenna; negative: to the right) [m]',
                         lo=-3.0, hi=3.0)
    odom_is_utm: bool = _p(False, 'Odometry position is UTM (used only without NavSatFix)')
    min_heading_speed: float = _p(
        1.0, 'NavSatFix only: slowest speed whose course over ground gives heading [m/s]',
        lo=0.1, hi=20.0)


@dataclass(frozen=True, slots=True, kw_only=True)
class BufferConfig:
    max_duration: float = _p(1800.0, 'longest span of data the node buffers [s]',
                             lo=1.0, hi=86400.0)
    max_memory_mb: float = _p(1024.0, 'largest memory the node buffer may use [MiB]',
                              lo=16.0, hi=65536.0)


@dataclass(frozen=True, slots=True, kw_only=True)
class OutputConfig:
    path: str = _p('radar_calibration.yaml', 'result file the node writes (and loads at start)',
                   read_only=True)
    recording_dir: str = _p('radar_calib_recordings', 'directory for ~/save_recording bags')


@dataclass(frozen=True, slots=True, kw_only=True)
class QosConfig:
    reliable: bool = _p(False, 'subscribe reliable instead of sensor-data best effort',
                        read_only=True)
    depth: int = _p(50, 'subscription queue depth', lo=1, hi=10000, read_only=True)


@dataclass(frozen=True, slots=True, kw_only=True)
class MovingConfig:
    min_speed_kmh: float = _p(0.1, 'targets with |v_r| below this are stationary [km/h]',
                              lo=0.0, hi=100.0)
    noise_factor: float = _p(3.0, 'also drop |v_r| below this many sigma of the stationary '
                             'targets\' v_r noise, estimated from the data (0 = off)',
                             lo=0.0, hi=20.0)


@dataclass(frozen=True, slots=True, kw_only=True)
class ClusterConfig:
    eps_m: float = _p(2.0, 'DBSCAN neighbourhood radius [m]', lo=0.05, hi=20.0)
    velocity_weight: float = _p(1.0, 'metres of distance per m/s of radial-velocity '
                                'difference [s]', lo=0.0, hi=100.0)
    min_samples: int = _p(3, 'DBSCAN minimum cluster size', lo=1, hi=1000)
    accumulate_frames: int = _p(3, 'consecutive frames accumulated for clustering',
                                lo=1, hi=50)


@dataclass(frozen=True, slots=True, kw_only=True)
class AssociateConfig:
    gate_m: float = _p(3.0, 'largest cluster-centre jump between frames of one track [m]',
                       lo=0.1, hi=50.0)
    max_gap_frames: int = _p(5, 'frames a track may go unseen before it ends', lo=0, hi=1000)
    min_track_frames: int = _p(8, 'shortest track kept [frames]', lo=2, hi=100000)


@dataclass(frozen=True, slots=True, kw_only=True)
class GroundConfig:
    radius_m: float = _p(1.0, 'neighbour radius of the density estimate [m]', lo=0.05, hi=20.0)
    density_fraction: float = _p(0.2, 'targets under this fraction of the maximum density '
                                 'are dropped', lo=0.0, hi=1.0)
    targets: str = _p('moving', 'which targets define the ground plane',
                      choices=('moving', 'all'))


@dataclass(frozen=True, slots=True, kw_only=True)
class TrackConfig:
    sigma_accel: float = _p(2.0, 'CTRA process noise: jerk density [m/s^3]', lo=1e-3, hi=100.0)
    sigma_yaw_accel: float = _p(0.5, 'CTRA process noise: yaw acceleration [rad/s^2]',
                                lo=1e-4, hi=100.0)
    measurement_sigma_m: float = _p(0.7, 'noise of a cluster centre [m]', lo=1e-3, hi=20.0)


@dataclass(frozen=True, slots=True, kw_only=True)
class HypothesesConfig:
    min_track_frames: int = _p(10, 'shortest track that makes a hypothesis [frames]',
                               lo=3, hi=100000)
    min_track_length_m: float = _p(8.0, 'shortest travelled distance of a hypothesis track [m]',
                                   lo=0.0, hi=1000.0)
    max_time_gap_s: float = _p(0.1, 'largest gap between a radar stamp and a vehicle pose '
                               'for a correspondence [s]', lo=0.001, hi=5.0)
    max_rms_m: float = _p(2.5, 'hypotheses with a larger registration RMS are dropped [m]',
                          lo=0.01, hi=100.0)
    eps_m: float = _p(3.0, 'DBSCAN radius over hypothesis translations [m]', lo=0.01, hi=100.0)
    min_samples: int = _p(2, 'DBSCAN minimum hypotheses per cluster', lo=1, hi=1000)
    min_passes: int = _p(3, 'fewest agreeing vehicle passes for a calibration', lo=1, hi=1000)
    pass_gap_s: float = _p(2.0, 'tracks closer in time than this belong to one pass [s]',
                           lo=0.0, hi=600.0)
    pass_margin_m: float = _p(
        10.0, 'tracks belong to one pass unless the vehicle went farther than this beyond '
        'the range it was tracked at between them (a stop at a light splits a track, not '
        'a pass) [m]', lo=0.0, hi=1000.0)
    max_mean_angle_deg: float = _p(
        5.0, "hypotheses farther than this from their cluster's rotation medoid, and clusters "
        'with a larger mean pairwise rotation angle, are rejected [deg]', lo=0.01, hi=180.0)
    angle_tie_deg: float = _p(
        1.0, 'clusters this close to the lowest mean angle tie; more passes, then lower RMS '
        'win [deg]', lo=0.0, hi=180.0)
    reflection_height_m: float = _p(
        0.5, 'prior mean height of the vehicle reflections above the road [m]',
        lo=-1.0, hi=5.0)
    max_cluster_rms_m: float = _p(
        1.2, 'a track joins the accepted cluster only if the merged transform fits it within '
        "this RMS (the vehicle's own tracks fit to decimetres, coincidences to metres) [m]",
        lo=0.01, hi=100.0)


@dataclass(frozen=True, slots=True, kw_only=True)
class RefineConfig:
    polygon: bool = _p(True, 'run the paper refinement (closest target + polygon loss)')
    final: bool = _p(True, 'run the final 6-DoF + clock-offset refinement over all targets')
    gate_m: float = _p(1.5, 'targets farther than this from the vehicle box are ignored [m]',
                       lo=0.1, hi=20.0)
    final_gate_m: float = _p(0.9, 'after the first round, targets farther than this from the '
                             'vehicle box are ignored [m]', lo=0.1, hi=20.0)
    velocity_sigma_mps: float = _p(0.15, 'radial-velocity noise assumed in the fit [m/s]',
                                   lo=1e-3, hi=10.0)
    velocity_gate_mps: float = _p(
        0.6, "after the first round, targets whose radial velocity differs from the vehicle's "
        'rigid motion by more than this are ignored (widened to 4 robust sigma of those '
        'differences where the radar is noisier; 0 = off) [m/s]', lo=0.0, hi=100.0)
    position_sigma_m: float = _p(0.5, 'target position scatter assumed in the fit [m]',
                                 lo=1e-3, hi=10.0)
    # Order 8, not 4: reflections near the faces make a profile with kinks where a corner
    # turns into view, whose Fourier terms fall only as 1/k^2; cut at 4, the remainder
    # leaned on the radar's position along the boresight (an independent generator's
    # near-surface cars: +7 to +42 cm, always the same way, at 1.4 sigma on average). At
    # 8: -12 to +7 cm where the views allow; our simulator's bench unchanged within its
    # scatter (interior median 8.5 -> 7.4 cm). At 12 it overfits narrow views (a +-9 deg
    # long-range radar: 36 -> 78 cm).
    profile_harmonics: int = _p(8, 'Fourier order of the reflection profile over aspect angle',
                                lo=0, hi=12)
    # See ``core/reflection.py`` for why: without them a car reflecting at its nearest
    # corner put the radar 0.2-0.8 m along its boresight at a fifth of that in sigma.
    profile_steps: bool = _p(
        True, 'the reflection profile switches between front and rear, and between the '
        'sides, as a step where the near face changes (false: Fourier terms only)')
    profile_range_terms: str = _p(
        'perspective', 'how the reflection profile may change with range: its depth along '
        "the line of sight linearly, plus its low orders as 1 / range ('perspective'), the "
        "depth only ('depth'), or its low orders linearly ('full')",
        choices=('perspective', 'depth', 'full'))
    max_iterations: int = _p(5, 'gate / re-fit rounds of the final refinement', lo=1, hi=50)
    range_sigma_m: float = _p(0.15, 'radar range noise (1 sigma) [m]', lo=1e-4, hi=10.0)
    azimuth_sigma_deg: float = _p(0.3, 'radar azimuth noise (1 sigma) [deg]', lo=1e-4, hi=20.0)
    elevation_sigma_deg: float = _p(1.5, 'radar elevation noise (1 sigma) [deg]', lo=1e-4,
                                    hi=30.0)
    reflection_height_m: float = _p(
        0.35, 'prior mean height above the road of all the vehicle targets, multipath images '
        'below the road included, for a car 1.5 m tall (scaled with vehicle.height) [m]',
        lo=-2.0, hi=5.0)
    reflection_height_sigma_m: float = _p(
        0.3, 'uncertainty of refine.reflection_height_m (scaled with it) [m]', lo=1e-3,
        hi=5.0)
    model_check: bool = _p(
        True, "refit with refine.profile_range_terms 'depth' (or 'full' where that is the one "
        "chosen) and add the two positions' difference to the reported covariance (at most "
        "the fit's own variance along it)")
    model_sigma_tilt_deg: float = _p(
        0.1, 'systematic 1-sigma of the reflection model in roll and pitch (rotation about the '
        'horizontal world axes), added to the reported uncertainty [deg]', lo=0.0, hi=10.0)
    model_sigma_height_difference_m: float = _p(
        0.1, "systematic 1-sigma of the difference between the vehicle's reflection heights "
        'seen from the front and from the rear; its effect on the fit (mostly roll and pitch) '
        'is added to the reported uncertainty [m]', lo=0.0, hi=5.0)
    model_sigma_height_range_m: float = _p(
        0.3, "systematic 1-sigma of the change of the vehicle's mean reflection height with "
        'range, from the median range to twice it; its effect on the fit (mostly pitch, and '
        'roll where range follows azimuth) is added to the reported uncertainty [m]',
        lo=0.0, hi=5.0)
    azimuth_scale_sigma: float = _p(
        0.0, "prior 1-sigma of a scale error of the radar's own azimuths (1 % = 0.45 deg at "
        '45 deg), fitted with the calibration when above 0 (for a radar whose angle '
        'calibration is in doubt)', lo=0.0, hi=0.2)
    model_sigma_along_m: float = _p(
        0.02, 'systematic 1-sigma of the reflection model along the boresight, added to the '
        'reported uncertainty [m]', lo=0.0, hi=5.0)
    cell_frames: float = _p(
        3.0, 'frames of one (vehicle position, aspect) cell that count at full weight; more '
        'frames share that weight (a queued car must not dominate)', lo=0.1, hi=1e6)
    cell_size_m: float = _p(1.0, 'vehicle position bin of the information weighting [m]',
                            lo=0.01, hi=100.0)
    cell_aspect_deg: float = _p(10.0, 'aspect-angle bin of the information weighting [deg]',
                                lo=0.1, hi=360.0)


@dataclass(frozen=True, slots=True, kw_only=True)
class QualityConfig:
    bootstrap: int = _p(100, 'bootstrap resamples over passes for the uncertainty', lo=0,
                        hi=10000)
    seed: int = _p(0, 'seed of the bootstrap', lo=0, hi=2**31 - 1)
    max_boresight_sigma_m: float = _p(
        0.05, 'warn and advise when the 1-sigma along the boresight exceeds this [m]',
        lo=0.0, hi=10.0)
    min_vehicle_detection: float = _p(
        0.2, 'fewest frames, of those where the calibration puts the moving vehicle in view, '
        'that must show targets with its radial velocity near its box', lo=0.0, hi=1.0)


_TOP_LEVEL: dict[str, tuple[str, str]] = {
    'radar_topic': ('radar/points', 'PointCloud2 topic of the radar targets'),
    'navsat_topic': ('vehicle/fix', 'NavSatFix topic of the calibration vehicle'),
    'odom_topic': ('vehicle/odom', 'Odometry topic of the calibration vehicle'),
}


@dataclass(frozen=True, slots=True, kw_only=True)
class CalibConfig:
    """All parameters, grouped by section; see ``config/calibrator.yaml``.

    ``explicit`` names the parameters that were given (not defaulted): the bag reader uses
    it to tell "pick the topic by type" from "this topic must exist".
    """

    # read_only: the node subscribes once, at start (as tf2_ros's static_transform_publisher
    # declares its fixed parameters read-only)
    radar_topic: str = _p(*_TOP_LEVEL['radar_topic'], read_only=True)
    navsat_topic: str = _p(*_TOP_LEVEL['navsat_topic'], read_only=True)
    odom_topic: str = _p(*_TOP_LEVEL['odom_topic'], read_only=True)
    radar: RadarConfig = field(default_factory=RadarConfig)
    world: WorldConfig = field(default_factory=WorldConfig)
    sync: SyncConfig = field(default_factory=SyncConfig)
    vehicle: VehicleConfig = field(default_factory=VehicleConfig)
    buffer: BufferConfig = field(default_factory=BufferConfig)
    output: OutputConfig = field(default_factory=OutputConfig)
    qos: QosConfig = field(default_factory=QosConfig)
    moving: MovingConfig = field(default_factory=MovingConfig)
    cluster: ClusterConfig = field(default_factory=ClusterConfig)
    associate: AssociateConfig = field(default_factory=AssociateConfig)
    ground: GroundConfig = field(default_factory=GroundConfig)
    track: TrackConfig = field(default_factory=TrackConfig)
    hypotheses: HypothesesConfig = field(default_factory=HypothesesConfig)
    refine: RefineConfig = field(default_factory=RefineConfig)
    quality: QualityConfig = field(default_factory=QualityConfig)
    explicit: frozenset[str] = field(default=frozenset(), compare=False)

    @classmethod
    def from_mapping(cls, params: Mapping[str, Any]) -> CalibConfig:
        """Build and validate from nested and/or dotted keys (``vehicle.length``).

        Raises
        ------
        ConfigError
            Naming the first unknown, ill-typed or out-of-range parameter.
        """
        flat = flatten(params)
        specs = {spec.name: spec for spec in parameter_specs()}
        unknown = sorted(set(flat) - set(specs))
        if unknown:
            groups = {name.split('.', 1)[0] for name in specs if '.' in name}
            if flat[unknown[0]] is None and unknown[0] in groups:
                # YAML's "quality:" with nothing under it reads as a null, not as a group
                raise ConfigError(f'parameter group {unknown[0]!r} is empty: give its '
                                  f'parameters under it (e.g. {unknown[0]}.'
                                  f'{_first_in(unknown[0], specs)}) or remove the line')
            raise ConfigError(f'unknown parameter {unknown[0]!r}'
                              + (f' (and {len(unknown) - 1} more)' if len(unknown) > 1 else ''))
        sections: dict[str, dict[str, Any]] = {}
        top: dict[str, Any] = {}
        for name, value in flat.items():
            checked = specs[name].check(value)
            if '.' in name:
                section, key = name.split('.', 1)
                sections.setdefault(section, {})[key] = checked
            else:
                top[name] = checked
        kwargs: dict[str, Any] = dict(top)
        for f in dataclasses.fields(cls):
            if f.name in sections:
                section_cls = type(getattr(cls(), f.name))
                kwargs[f.name] = section_cls(**sections[f.name])
        config = cls(**kwargs, explicit=frozenset(flat))
        _check_utm_epsg(config.world.epsg)
        return config

    @classmethod
    def from_file(cls, path: str | Path, node_name: str | None = None) -> CalibConfig:
        """Read a ROS 2 parameters file (``/**: ros__parameters: ...``)."""
        return cls.from_mapping(read_params_file(path, node_name))

    def replaced(self, settings: Mapping[str, Any]) -> CalibConfig:
        """This configuration with ``settings`` (dotted names) over its values, validated
        as a parameters file is."""
        return CalibConfig.from_mapping({**self.to_flat(), **settings})

    def to_flat(self) -> dict[str, Any]:
        """Every parameter as ``{dotted_name: value}`` (what the node declares)."""
        out: dict[str, Any] = {}
        for spec in parameter_specs():
            out[spec.name] = self.get(spec.name)
        return out

    def get(self, name: str) -> Any:
        """Value of a dotted parameter name."""
        obj: Any = self
        for part in name.split('.'):
            obj = getattr(obj, part)
        return obj


def _check_utm_epsg(code: int) -> None:
    """ConfigError unless ``code`` is 0 or an EPSG code of a UTM zone (any datum).

    Why: the world frame is UTM by contract; another projection (degrees of EPSG:4326, a
    polar stereographic zone) would be written as if it were easting and northing."""
    if not code:
        return
    import pyproj  # here, not at the top: the parameters are read where pyproj is not needed
    try:
        crs = pyproj.CRS.from_epsg(code)
    except pyproj.exceptions.CRSError as err:
        raise ConfigError(f'parameter \'world.epsg\' = {code} is not a known EPSG code') from err
    if crs.utm_zone is None:
        raise ConfigError(f'parameter \'world.epsg\' = {code} ({crs.name}) is not a UTM zone; '
                          'the world frame is UTM (e.g. 32632, WGS 84 / UTM zone 32N), or 0 '
                          'for the zone of the first vehicle fix')


@dataclass(frozen=True, slots=True)
class ParameterSpec:
    """One parameter: name, type, default, description and constraint."""

    name: str
    type: type
    default: Any
    doc: str
    lo: float | None
    hi: float | None
    choices: tuple[str | float, ...] | None
    read_only: bool

    def check(self, value: Any) -> Any:
        """Return the value in this parameter's type, or raise ConfigError naming it."""
        want = self.type
        if want is bool:
            ok = isinstance(value, bool)
        elif want is int:
            ok = isinstance(value, int) and not isinstance(value, bool)
        elif want is float:
            ok = isinstance(value, (int, float)) and not isinstance(value, bool)
        else:
            ok = isinstance(value, str)
        if not ok:
            raise ConfigError(f'parameter {self.name!r} must be {want.__name__}, got '
                              f'{type(value).__name__} {value!r}')
        if want is float:
            value = float(value)
            if not math.isfinite(value):
                raise ConfigError(f'parameter {self.name!r} must be finite, got {value!r}')
        if self.lo is not None and value < self.lo or self.hi is not None and value > self.hi:
            raise ConfigError(f'parameter {self.name!r} = {value!r} is outside '
                              f'[{self.lo}, {self.hi}]')
        if self.choices is not None and value not in self.choices:
            raise ConfigError(f'parameter {self.name!r} = {value!r} is not one of '
                              f'{list(self.choices)}')
        return value


def parameter_specs() -> Iterator[ParameterSpec]:
    """All parameters in declaration order, derived from the dataclasses."""
    root = CalibConfig()
    for f in dataclasses.fields(CalibConfig):
        if f.name == 'explicit':
            continue
        value = getattr(root, f.name)
        if dataclasses.is_dataclass(value):
            for sub in dataclasses.fields(value):
                yield _spec(f'{f.name}.{sub.name}', sub, getattr(value, sub.name))
        else:
            yield _spec(f.name, f, value)


def _spec(name: str, f: dataclasses.Field[Any], default: Any) -> ParameterSpec:
    meta = f.metadata
    return ParameterSpec(name=name, type=type(default), default=default, doc=meta['doc'],
                         lo=meta['lo'], hi=meta['hi'], choices=meta['choices'],
                         read_only=meta['read_only'])


def _first_in(group: str, specs: Mapping[str, Any]) -> str:
    return next(name.split('.', 1)[1] for name in specs if name.startswith(group + '.'))


def flatten(params: Mapping[str, Any], prefix: str = '') -> dict[str, Any]:
    """Nested mapping -> ``{dotted.name: value}`` (nested and dotted keys are equivalent)."""
    flat: dict[str, Any] = {}
    for key, value in params.items():
        if not isinstance(key, str):
            raise ConfigError(f'parameter name {key!r} is not a string')
        name = f'{prefix}{key}'
        items = flatten(value, name + '.') if isinstance(value, Mapping) else {name: value}
        for sub, sub_value in items.items():
            if sub in flat:
                raise ConfigError(f'parameter {sub!r} is given twice')
            flat[sub] = sub_value
    return flat


#: The node's name unless remapped (``ros2 run radar_calib_ros calibrator``); the offline
#: tool reads the section of this name where a file holds several nodes' parameters.
DEFAULT_NODE_NAME = 'calibrator'

#: A float as YAML 1.2 and ROS 2's parameter parser read it: PyYAML (YAML 1.1) reads
#: ``1e3`` and ``1.5e-3`` as strings, which then failed as 'must be float, got str'.
_FLOAT_12 = re.compile(r'^[-+]?(\.[0-9]+|[0-9]+\.[0-9]*|[0-9]+)([eE][-+]?[0-9]+)$'
                       r'|^[-+]?(\.[0-9]+|[0-9]+\.[0-9]*)$')


class _ParamsLoader(yaml.SafeLoader):
    """PyYAML's safe loader reading floats as ROS 2 does."""


_ParamsLoader.add_implicit_resolver('tag:yaml.org,2002:float', _FLOAT_12,
                                    list('-+0123456789.'))


def read_params_file(path: str | Path, node_name: str | None = None) -> dict[str, Any]:
    """The ``ros__parameters`` of a ROS 2 parameters file, merged over node keys.

    Entries under ``/**`` apply to every node; an entry under the node's own name
    overrides them, as ROS 2 does, and other nodes' entries are left alone. The offline
    tool (``node_name`` None) has no node name: it takes the file's one node entry, or of
    several the one named ``calibrator`` (any namespace), and refuses to guess among more.
    """
    path = Path(path)
    try:
        text = path.read_text(encoding='utf-8')
    except OSError as err:
        raise ConfigError(f'cannot read parameters file {str(path)!r}: {err.strerror}') from err
    try:
        doc = yaml.load(text, Loader=_ParamsLoader)  # noqa: S506 - a SafeLoader
    except yaml.YAMLError as err:
        raise ConfigError(f'parameters file {str(path)!r} is not valid YAML: {err}') from err
    if doc is None:
        _LOG.warning('parameters file %r is empty: the defaults are used', str(path))
        return {}
    if not isinstance(doc, dict):
        raise ConfigError(f'parameters file {str(path)!r} must be a mapping of node names')
    if 'world_frame' in doc or any(isinstance(b, dict) and isinstance(
            b.get('ros__parameters'), dict) and ({'calibration', 'calibrations'}
                                                 & set(b['ros__parameters']))
            for b in doc.values()):
        raise ConfigError(f'{str(path)!r} is a result file of radar-calib calibrate, not a '
                          'parameters file: give it as --calibration (evaluate, report) and '
                          'the parameters with --params')
    for key, body in doc.items():
        if not isinstance(body, dict) or 'ros__parameters' not in body:
            raise ConfigError(f'parameters file {str(path)!r}: entry {key!r} has no '
                              '"ros__parameters"')
    chosen = ['/**'] if '/**' in doc else []
    chosen += _node_entries(doc, node_name, path)
    merged: dict[str, Any] = {}
    for key in chosen:
        params = doc[key]['ros__parameters'] or {}
        if not isinstance(params, dict):
            raise ConfigError(f'parameters file {str(path)!r}: ros__parameters of {key!r} '
                              'is not a mapping')
        merged.update(flatten(params))
    if not merged:
        _LOG.warning('parameters file %r sets no parameter: the defaults are used', str(path))
    if node_name is None:
        _warn_integers_for_doubles(merged, path)
    return merged


def _node_entries(doc: Mapping[Any, Any], node_name: str | None, path: Path) -> list[Any]:
    """The node entries (not ``/**``) of a parameters file that apply (see
    :func:`read_params_file`): a site's one file for a radar node and a lidar driver was
    refused for the driver's parameters, one for two radar nodes had its entries merged,
    the alphabetically last winning (a probe's)."""
    nodes = [key for key in doc if key != '/**']

    def base(key: Any) -> str:
        return str(key).strip('/').split('/')[-1]

    if node_name is not None:
        return sorted((k for k in nodes if base(k) == node_name), key=str)
    if len(nodes) <= 1:
        return nodes
    ours = [k for k in nodes if base(k) == DEFAULT_NODE_NAME]
    if len(ours) == 1:
        return ours
    names = ', '.join(str(k) for k in (ours or nodes))
    raise ConfigError(f'parameters file {str(path)!r} holds the parameters of several nodes '
                      f'({names}) and the offline tool cannot tell which one is this '
                      "radar's: give a file with '/**' and that node's entry only")


def _warn_integers_for_doubles(params: Mapping[str, Any], path: Path) -> None:
    """The node (ROS 2) refuses an integer for a parameter of type double and does not
    start; the offline tool reads one as a float. Said, so that the file a site tests
    offline also starts its node."""
    specs = {spec.name: spec for spec in parameter_specs()}
    integers = [f'{name}: {value}' for name, value in params.items()
                if name in specs and specs[name].type is float
                and isinstance(value, int) and not isinstance(value, bool)]
    if integers:
        _LOG.warning('parameters file %r: %s given as integer%s; the ROS 2 node refuses an '
                     'integer for a floating-point parameter and would not start: write '
                     'them with a decimal point (e.g. %s.0)', str(path), ', '.join(integers),
                     's' if len(integers) > 1 else '', integers[0].split(': ')[1])


def default_params_yaml() -> str:
    """Text of ``config/calibrator.yaml``: every parameter, its default and a comment."""
    lines = ['# radar_calib_ros parameters: one file serves the node and `radar-calib`.',
             '# Generated from radar_calib_ros/config.py (test/test_config.py keeps them equal).',
             '/**:', '  ros__parameters:']
    section = None
    for spec in parameter_specs():
        if '.' in spec.name:
            sec, key = spec.name.split('.', 1)
            if sec != section:
                lines.append(f'    {sec}:')
                section = sec
            indent = '      '
        else:
            key, indent = spec.name, '    '
        value = yaml.safe_dump(spec.default, default_flow_style=True).strip()
        if value.endswith('...'):
            value = value[:-3].strip()
        bound = ''
        if spec.lo is not None or spec.hi is not None:
            bound = f' [{spec.lo}, {spec.hi}]'
        if spec.choices:
            bound = f' {{{", ".join(map(str, spec.choices))}}}'
        lines.append(f'{indent}{key}: {value}  # {spec.doc}{bound}')
    return '\n'.join(lines) + '\n'
