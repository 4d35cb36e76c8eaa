"""Named scenarios: site, junction, radar mount, traffic and the calibration drive.

Each scenario is a fixed description of a site: its junction, static scene and radar
mount(s). The seed varies the drive past it (signal offsets, traffic, the calibration
vehicle's route, every noise draw), never the site, so two seeds are two recordings of the
same radar; a separate mount seed moves the mount a little (within the ranges of real
installations) for another installation of the same scenario. Sites differ on purpose: the
grid convergence between true north, the local grid and UTM ranges from ~0.3 to ~2.5 deg
across them, one site is in the southern hemisphere with left-hand traffic.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np

from radar_calib_ros.errors import ConfigError
from radar_calib_ros.sim.roads import JunctionSpec


@dataclass(frozen=True)
class Site:
    """Where the junction is: WGS 84 position of its centre, ellipsoidal ground altitude
    there, and the road gradient (dz/dx east, dz/dy north)."""

    name: str
    lat_deg: float
    lon_deg: float
    ground_alt_m: float
    slope: tuple[float, float] = (0.0, 0.0)


@dataclass(frozen=True)
class RadarMount:
    """The radar on its pole, relative to the junction centre.

    pitch_deg is positive looking down; the boresight's yaw points at ``look_at_xy`` plus
    ``yaw_offset_deg``. The mount is R = Rz(yaw) Ry(pitch) Rx(roll) (extrinsic x-y-z, as the
    result's rpy_deg), so x_world = R x_sensor + t.
    """

    position_xy_m: tuple[float, float]
    height_m: float
    pitch_deg: float
    roll_deg: float
    look_at_xy_m: tuple[float, float] = (0.0, 0.0)
    yaw_offset_deg: float = 0.0


@dataclass(frozen=True)
class TrafficSpec:
    """Traffic demand and signal timing."""

    vehicles_per_lane_h: float = 300.0
    truck_share: float = 0.08
    cyclists_per_arm_h: float = 30.0
    pedestrians_per_arm_h: float = 50.0
    green_s: float = 22.0
    parked_cars: int = 10


@dataclass(frozen=True)
class DriveSpec:
    """How the calibration vehicle drives.

    mode 'junction': passes through the junction on varied movements, joined by U-turns;
    'arm': every pass enters or leaves by ``focus_arm`` (a radar far down that arm);
    'away': back and forth on ``focus_arm`` beyond the radar's range.
    """

    mode: str = 'junction'
    focus_arm: int = 0
    speed_mps: tuple[float, float] = (8.5, 13.5)


@dataclass(frozen=True)
class VehicleSpec:
    """The calibration vehicle's box (CONTRACT.md vehicle.*) and wheelbase [m]."""

    length: float = 4.77
    width: float = 1.83
    height: float = 1.48
    rear_overhang: float = 1.02
    ref_height: float = 0.33
    wheelbase: float = 2.79


@dataclass(frozen=True)
class Scenario:
    """One named simulation setting (see :data:`SCENARIOS`)."""

    name: str
    description: str
    site: Site
    junction: JunctionSpec
    radar: RadarMount
    traffic: TrafficSpec = field(default_factory=TrafficSpec)
    drive: DriveSpec = field(default_factory=DriveSpec)
    vehicle: VehicleSpec = field(default_factory=VehicleSpec)
    #: radar clock offset [s] (added to radar stamps gives GNSS time); None: a synchronised
    #: clock, |offset| < 2 ms drawn from the seed
    clock_offset_s: float | None = None
    #: rate of a free-running radar clock against GNSS time [ppm]: the offset then changes
    #: by that many microseconds a second (``clock_offset_s`` is the one at mid-recording)
    clock_drift_ppm: float = 0.0
    point_layout: str = 'xyz'
    velocity_field: str = 'velocity'
    odometry: bool = True
    #: NavSatFix rate [Hz], at most the GNSS/INS rate (50 Hz); the Odometry stays at 50 Hz
    fix_rate_hz: float = 50.0
    #: how much later than its epoch a NavSatFix is stamped [s] (a driver that stamps on
    #: output, as nmea_navsat_driver does); the Odometry is stamped at its epoch
    fix_stamp_lag_s: float = 0.0
    clutter_density: float = 1.0
    #: further radars on other poles, recorded in parallel with ``radar`` (a site with
    #: several radars). Then the topics are /radar_1/points ... with frames radar_1 ...
    #: (``radar`` is radar_1), and each radar has its own ground truth file.
    more_radars: tuple[RadarMount, ...] = ()


_FOUR_WAY = JunctionSpec(arm_deg=(12.0, 101.0, 192.0, 283.0), phases=((0, 2), (1, 3)))

_SCENARIO_LIST: tuple[Scenario, ...] = (
    Scenario(
        'baseline',
        'Ulm (48.4N 9.9E): four-arm junction, radar 6.5 m up on a corner pole, pitched 8 deg '
        'down, looking across the junction; moderate traffic.',
        Site('Ulm', 48.42650, 9.95850, 480.0, (0.004, -0.006)), _FOUR_WAY,
        RadarMount((15.0, 16.5), 6.5, 8.0, 0.7, (-22.0, -14.0))),
    Scenario(
        'dense_traffic_steep_pitch',
        'Munich (48.1N 11.6E, UTM convergence ~1.9 deg): heavy traffic with long queues and '
        'trucks, radar 8.5 m up pitched 14 deg down (it sees the road from ~20 m on).',
        Site('Munich', 48.13720, 11.57560, 520.0, (-0.003, 0.002)),
        JunctionSpec(arm_deg=(-5.0, 88.0, 176.0, 266.0), phases=((0, 2), (1, 3)), lanes_in=2,
                     lanes_out=2),
        RadarMount((-16.0, 17.0), 8.5, 14.0, -1.2, (25.0, -20.0)),
        TrafficSpec(vehicles_per_lane_h=620.0, truck_share=0.14, cyclists_per_arm_h=60.0,
                    pedestrians_per_arm_h=120.0, green_s=26.0, parked_cars=14)),
    Scenario(
        'low_mount',
        'Stuttgart (48.8N 9.2E): radar only 4.2 m up, pitched 3.5 deg down and rolled 1.8 '
        'deg, so nearer road users hide farther ones; spherical point layout '
        '(range/azimuth/elevation).',
        Site('Stuttgart', 48.77580, 9.18290, 300.0, (0.008, 0.003)),
        JunctionSpec(arm_deg=(30.0, 122.0, 208.0, 300.0), phases=((0, 2), (1, 3))),
        RadarMount((13.5, -15.0), 4.2, 3.5, 1.8, (-30.0, 10.0), yaw_offset_deg=6.0),
        TrafficSpec(vehicles_per_lane_h=380.0), point_layout='spherical'),
    Scenario(
        'navsat_only',
        'Berlin (52.5N 13.4E, zone 33, UTM convergence ~1.3 deg): no Odometry, the vehicle '
        'heading must come from the course over ground.',
        Site('Berlin', 52.52000, 13.40500, 80.0, (0.0, 0.002)),
        JunctionSpec(arm_deg=(0.0, 90.0, 180.0, 270.0), phases=((0, 2), (1, 3)),
                     lanes_in=2, lanes_out=2, lane_width_m=3.5),
        RadarMount((-15.0, -16.5), 7.0, 6.0, -0.5, (20.0, 18.0)),
        odometry=False),
    Scenario(
        'slow_gnss',
        'Vienna (48.2N 16.4E, zone 33): the GNSS receiver at its default 1 Hz beside the '
        '50 Hz INS Odometry, its fixes stamped on output 0.12 s after their epoch; the path '
        'between fixes is the Odometry\'s.',
        Site('Vienna', 48.20820, 16.37380, 190.0, (0.003, 0.001)),
        JunctionSpec(arm_deg=(8.0, 95.0, 188.0, 280.0), phases=((0, 2), (1, 3))),
        RadarMount((14.0, -16.0), 6.0, 7.5, 0.6, (-25.0, 15.0)),
        fix_rate_hz=1.0, fix_stamp_lag_s=0.12),
    Scenario(
        'clock_offset',
        'Hamburg (53.6N 10.0E): the radar clock is 40 ms behind GNSS time (stamps + 0.040 s '
        '= GNSS time).',
        Site('Hamburg', 53.55110, 9.99370, 45.0, (-0.002, -0.002)),
        JunctionSpec(arm_deg=(20.0, 110.0, 200.0, 290.0), phases=((0, 2), (1, 3))),
        RadarMount((16.0, 14.0), 6.0, 7.0, 1.0, (-20.0, -20.0)),
        clock_offset_s=0.040),
    Scenario(
        'drifting_clock',
        'Graz (47.1N 15.4E): the radar stamps its scans with a free-running clock of its own, '
        '120 ppm fast against GNSS time (72 ms over ten minutes), 25 ms behind it at '
        'mid-recording.',
        Site('Graz', 47.07070, 15.43950, 355.0, (0.003, -0.002)),
        JunctionSpec(arm_deg=(5.0, 93.0, 178.0, 272.0), phases=((0, 2), (1, 3))),
        RadarMount((-15.0, -15.5), 6.5, 8.0, -0.5, (20.0, 16.0)),
        clock_offset_s=0.025, clock_drift_ppm=120.0),
    Scenario(
        'vehicle_never_in_view',
        'Ulm geometry, but the calibration vehicle only drives far down one arm, out of the '
        "radar's range: nothing to calibrate with.",
        Site('Ulm', 48.42650, 9.95850, 480.0, (0.004, -0.006)), _FOUR_WAY,
        RadarMount((15.0, 16.5), 6.5, 8.0, 0.7, (-22.0, -14.0)),
        drive=DriveSpec(mode='away', focus_arm=2)),
    Scenario(
        'mid_block',
        'Dresden (51.1N 13.7E): radar 7 m up at the roadside 95 m down one arm, looking along '
        'the road at the junction: the vehicle is seen almost only head-on and tail-on.',
        Site('Dresden', 51.05040, 13.73730, 160.0, (0.005, 0.0)),
        JunctionSpec(arm_deg=(0.0, 95.0, 180.0, 268.0), phases=((0, 2), (1, 3))),
        RadarMount((95.0, 10.5), 7.0, 6.5, -0.8, (0.0, 0.0), yaw_offset_deg=-3.0),
        TrafficSpec(vehicles_per_lane_h=330.0, parked_cars=18),
        drive=DriveSpec(mode='arm', focus_arm=0)),
    Scenario(
        'skewed_junction',
        'Vienna (48.2N 16.4E): busy skewed junction (arms 62 and 118 deg apart), radar 7.5 m '
        "up; the radial-velocity field is named 'doppler'.",
        Site('Vienna', 48.20820, 16.37380, 220.0, (0.002, 0.004)),
        JunctionSpec(arm_deg=(0.0, 62.0, 180.0, 242.0), phases=((0, 2), (1, 3))),
        RadarMount((-14.0, 19.0), 7.5, 9.0, 0.3, (18.0, -12.0)),
        TrafficSpec(vehicles_per_lane_h=480.0, truck_share=0.1, pedestrians_per_arm_h=90.0),
        velocity_field='doppler'),
    Scenario(
        'southern_t_junction',
        'Sydney (33.9S 151.2E, zone 56S): T-junction with left-hand traffic, radar 6 m up '
        'on the far side of the top road.',
        Site('Sydney', -33.86880, 151.20930, 60.0, (-0.005, 0.003)),
        JunctionSpec(arm_deg=(25.0, 205.0, 295.0), phases=((0, 1), (2,)), left_hand=True),
        RadarMount((3.0, 17.5), 6.0, 8.5, -1.6, (-4.0, -30.0), yaw_offset_deg=8.0),
        TrafficSpec(vehicles_per_lane_h=340.0, green_s=20.0)),
    Scenario(
        'far_from_meridian',
        'Stockholm (59.3N 18.1E, 2.9 deg west of the zone-34 meridian: UTM convergence ~2.5 '
        'deg): diagonal junction with three inbound lanes, radar 9 m up.',
        Site('Stockholm', 59.32930, 18.06860, 30.0, (0.0, -0.004)),
        JunctionSpec(arm_deg=(45.0, 135.0, 225.0, 315.0), phases=((0, 2), (1, 3)), lanes_in=3,
                     lanes_out=2),
        RadarMount((0.0, -24.0), 9.0, 10.0, 0.5, (0.0, 10.0), yaw_offset_deg=-5.0),
        TrafficSpec(vehicles_per_lane_h=260.0, green_s=25.0),
        vehicle=VehicleSpec(length=4.98, width=1.92, height=1.66, rear_overhang=1.10,
                            ref_height=0.36, wheelbase=2.98)),
    Scenario(
        'three_radars',
        'Ulm junction with three radars on three corner poles recorded in parallel (topics '
        '/radar_1/points ... /radar_3/points, frames radar_1 ... radar_3, own clocks), each '
        'looking across the junction; the vehicle drives past them all.',
        Site('Ulm', 48.42650, 9.95850, 480.0, (0.004, -0.006)), _FOUR_WAY,
        RadarMount((15.0, 16.5), 6.5, 8.0, 0.7, (-22.0, -14.0)),
        more_radars=(RadarMount((-16.5, -15.0), 7.0, 9.0, -0.6, (20.0, 15.0)),
                     RadarMount((17.0, -16.0), 5.8, 7.0, 1.0, (-20.0, 16.0),
                                yaw_offset_deg=4.0))),
)

_BY_NAME = {s.name: s for s in _SCENARIO_LIST}

#: Scenario names and their one-line descriptions.
SCENARIOS: dict[str, str] = {s.name: s.description for s in _SCENARIO_LIST}


def get_scenario(name: str) -> Scenario:
    """The named scenario.

    Raises
    ------
    ConfigError
        Unknown name (the message lists the known ones).
    """
    try:
        return _BY_NAME[name]
    except KeyError:
        raise ConfigError(f'unknown scenario {name!r}; known: {", ".join(SCENARIOS)}') from None


def perturbed_mount(mount: RadarMount, rng: np.random.Generator) -> RadarMount:
    """The mount moved a little by a mount seed's generator, staying inside real
    installation ranges (height 4-9 m, pitch 3-15 deg down, roll within +-2 deg)."""
    dx, dy = rng.normal(0.0, 0.6, 2)
    return replace(
        mount,
        position_xy_m=(mount.position_xy_m[0] + dx, mount.position_xy_m[1] + dy),
        height_m=float(np.clip(mount.height_m + rng.normal(0.0, 0.2), 4.0, 9.0)),
        pitch_deg=float(np.clip(mount.pitch_deg + rng.normal(0.0, 0.6), 3.0, 15.0)),
        roll_deg=float(np.clip(mount.roll_deg + rng.normal(0.0, 0.3), -2.0, 2.0)),
        yaw_offset_deg=mount.yaw_offset_deg + float(rng.uniform(-4.0, 4.0)))


def mount_rotation(mount: RadarMount) -> tuple[np.ndarray, float]:
    """(R sensor -> local world (3, 3), yaw [rad]) of a mount: R = Rz(yaw) Ry(pitch) Rx(roll)."""
    px, py = mount.position_xy_m
    yaw = math.atan2(mount.look_at_xy_m[1] - py, mount.look_at_xy_m[0] - px) + math.radians(
        mount.yaw_offset_deg)
    pitch, roll = math.radians(mount.pitch_deg), math.radians(mount.roll_deg)
    cz, sz = math.cos(yaw), math.sin(yaw)
    cy, sy = math.cos(pitch), math.sin(pitch)
    cx, sx = math.cos(roll), math.sin(roll)
    rz = np.array([[cz, -sz, 0.0], [sz, cz, 0.0], [0.0, 0.0, 1.0]])
    ry = np.array([[cy, 0.0, sy], [0.0, 1.0, 0.0], [-sy, 0.0, cy]])
    rx = np.array([[1.0, 0.0, 0.0], [0.0, cx, -sx], [0.0, sx, cx]])
    return rz @ ry @ rx, yaw
