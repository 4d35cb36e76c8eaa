"""Small frozen dataclasses of numpy arrays passed between the steps of the flow.

messages or bag -> decoded samples (``RadarFrame``, ``FixSample``, ``OdomSample``)
-> ``Recording`` -> stage outputs (one class per stage, paper order) -> ``Extrinsics``.

Conventions: arrays have the sample on the first axis; units are suffixes; time is
``stamp_ns`` (int64 header stamps). Positions of the world side are in the recording's
local metric frame (``io.geo.LocalFrame``: transverse Mercator with unit scale at the
site, z = ellipsoidal altitude); only the result is converted to UTM.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]
B = NDArray[np.bool_]


def _freeze(obj: Any) -> None:
    """Make every ndarray field read-only, so 'frozen' covers the contents."""
    for name in getattr(obj, '__dataclass_fields__', {}):
        value = getattr(obj, name)
        if isinstance(value, np.ndarray):
            value.setflags(write=False)


# --- decoded messages -------------------------------------------------------------------

@dataclass(frozen=True, slots=True)
class RadarFrame:
    """One radar cycle: its header stamp and its targets in the sensor frame.

    positions_m : ndarray of shape (n, 3), x forward, y left, z up [m]
    radial_velocity_mps : ndarray of shape (n,), positive = moving away [m/s]
    dropped_nonfinite : points with NaN/inf in a used field, left out;
    invalid_declared : the message said it may hold such points (PointCloud2 ``is_dense``
        false: a driver's invalid points, not a fault)
    velocity_components : the fields whose projection on the line of sight gave the radial
        velocity (an object list's vx, vy), empty where the radar gave it
    """

    stamp_ns: int
    positions_m: F64
    radial_velocity_mps: F64
    dropped_nonfinite: int = 0
    invalid_declared: bool = False
    velocity_components: tuple[str, ...] = ()


@dataclass(frozen=True, slots=True)
class FixSample:
    """One NavSatFix: WGS 84 latitude/longitude [deg], ellipsoidal altitude [m], its
    status, its 1-sigma (horizontal, vertical) from ``position_covariance`` [m] (NaN
    when the covariance type is unknown) and its header frame_id."""

    stamp_ns: int
    lat_deg: float
    lon_deg: float
    alt_m: float
    status: int
    position_sigma_m: tuple[float, float] = (math.nan, math.nan)
    frame_id: str = ''


@dataclass(frozen=True, slots=True)
class OdomSample:
    """One Odometry message.

    quaternion_xyzw: orientation, ENU against true north. position_m: as in the message
    (UTM only when ``vehicle.odom_is_utm``). velocity_body_mps: twist.linear in the child
    (vehicle) frame. yaw_rate_rps: twist.angular.z.
    """

    stamp_ns: int
    position_m: tuple[float, float, float]
    quaternion_xyzw: tuple[float, float, float, float]
    velocity_body_mps: tuple[float, float, float]
    yaw_rate_rps: float


# --- the recording ----------------------------------------------------------------------

@dataclass(frozen=True, slots=True)
class Targets:
    """All radar targets of a recording, columnar.

    positions_m : (n, 3) sensor frame [m]; radial_velocity_mps : (n,) [m/s];
    frame_index : (n,) index into ``Recording.frame_stamps_ns``.
    """

    positions_m: F64
    radial_velocity_mps: F64
    frame_index: I64

    def __post_init__(self) -> None:
        _freeze(self)

    def __len__(self) -> int:
        return int(self.frame_index.shape[0])

    def subset(self, mask_or_index: NDArray[Any]) -> Targets:
        """Targets selected by a boolean mask or an index array."""
        return Targets(self.positions_m[mask_or_index], self.radial_velocity_mps[mask_or_index],
                       self.frame_index[mask_or_index])


@dataclass(frozen=True, slots=True)
class RadarView:
    """The radar's field of view as its targets outline it (the contract has no
    field-of-view parameter): percentiles of an even sample of all targets, so the edges
    are blurred by the noise and a few far false alarms do not widen it."""
    range_m: float             # 99th percentile of the targets' range
    horizontal_range_m: float  # 99th percentile of their horizontal range
    azimuth_rad: tuple[float, float]    # 1st and 99th percentiles
    elevation_rad: tuple[float, float]  # 1st and 99th percentiles


@dataclass(frozen=True, slots=True)
class VehicleTrack:
    """The calibration vehicle's pose stream in the local metric frame.

    stamps_ns : (p,) sorted header stamps; positions_m : (p, 3) reference point [m];
    yaw_rad : (p,) heading, counter-clockwise from the local grid east [rad];
    velocities_mps : (p, 3) world-frame velocity of the reference point [m/s];
    yaw_rate_rps : (p,) [rad/s].
    """

    stamps_ns: I64
    positions_m: F64
    yaw_rad: F64
    velocities_mps: F64
    yaw_rate_rps: F64

    def __post_init__(self) -> None:
        _freeze(self)

    def __len__(self) -> int:
        return int(self.stamps_ns.shape[0])


@dataclass(frozen=True, slots=True)
class PoseSamples:
    """Vehicle poses interpolated to given stamps; ``valid`` is False outside the data or
    across a gap longer than ``sync.max_pose_gap``."""

    positions_m: F64
    yaw_rad: F64
    velocities_mps: F64
    yaw_rate_rps: F64
    valid: B


# --- stage outputs (paper order) --------------------------------------------------------

@dataclass(frozen=True, slots=True)
class TrackedTargets:
    """Stages 1-3: moving targets with their cluster and track identities.

    target_index : (m,) index of each moving target into ``Recording.targets``;
    track_id : (m,) track of each moving target, -1 = noise (no cluster).
    """

    target_index: I64
    track_id: I64

    def __post_init__(self) -> None:
        _freeze(self)


@dataclass(frozen=True, slots=True)
class GroundPlane:
    """Stage 4: the road plane in the sensor frame.

    normal : (3,) unit normal, pointing up (towards the sensor side); offset_m: signed
    distance of the plane from the sensor along ``normal`` (negative: the road is below);
    rotation_level : (3, 3) R_αβ, rotates sensor coordinates so the normal becomes +z;
    used : (k,) indices of the targets that survived the density filter; tilt_sigma_deg:
    how far another plane the data hold (the road users' alone) lies from it [deg], where
    the two could not be told apart (0 where they agree or one was chosen).
    """

    normal: F64
    offset_m: float
    rotation_level: F64
    density_threshold: float
    used: I64
    tilt_sigma_deg: float = 0.0

    def __post_init__(self) -> None:
        _freeze(self)


@dataclass(frozen=True, slots=True)
class SmoothedTrack:
    """Stage 5: one track's cluster centres, UKF-filtered and RTS-smoothed, in the levelled
    bird's-eye-view frame (sensor frame rotated by R_αβ).

    frame_index : (k,) frames the track was seen in; stamps_ns : (k,) their stamps;
    positions_m : (k, 2) smoothed centre; heights_m : (k,) mean levelled z of its targets;
    states : (k, 6) CTRA state [x, y, yaw, v, yaw_rate, a]; covariances : (k, 6, 6).
    """

    track_id: int
    frame_index: I64
    stamps_ns: I64
    positions_m: F64
    heights_m: F64
    states: F64
    covariances: F64

    def __post_init__(self) -> None:
        _freeze(self)


@dataclass(frozen=True, slots=True)
class Extrinsics:
    """A calibration in the local world frame: x_world = R x_sensor + t.

    time_offset_s is the clock offset added to radar stamps on top of ``sync.time_offset``.
    """

    rotation: F64
    translation_m: F64
    time_offset_s: float = 0.0

    def __post_init__(self) -> None:
        _freeze(self)

    def apply(self, points_sensor: F64) -> F64:
        """Sensor-frame points (n, 3) to world (n, 3)."""
        return points_sensor @ self.rotation.T + self.translation_m

    def inverse_apply(self, points_world: F64) -> F64:
        """World points (n, 3) to the sensor frame (n, 3)."""
        return (points_world - self.translation_m) @ self.rotation


@dataclass(frozen=True, slots=True)
class Hypothesis:
    """Stage 6: one track's candidate transform, levelled BEV frame -> world."""

    track_id: int
    rotation: F64
    translation_m: F64
    n_correspondences: int
    rms_m: float


@dataclass(frozen=True, slots=True)
class MountTurn:
    """The radar's mount turned during the recording: two groups of the vehicle's tracks,
    one before and one after, each agreeing within itself, that place the radar at the same
    spot looking ``yaw_change_deg`` apart (counter-clockwise seen from above positive).

    at_ns : a radar stamp between the two groups (the turn happened in that gap);
    gap_ns : (2,) [end of the earlier group, start of the later group];
    passes_before, passes_after : the vehicle passes each group agrees on;
    tilt_change_deg : the turn about a horizontal axis (pitch and roll), where the final
    fit found it (stage 6 sees yaw only).
    """

    at_ns: int
    gap_ns: tuple[int, int]
    yaw_change_deg: float
    passes_before: int
    passes_after: int
    tilt_change_deg: float = 0.0


@dataclass(frozen=True, slots=True)
class HypothesisSelection:
    """Stage 6: the hypotheses, their translation clusters and the accepted one.

    labels : (h,) DBSCAN label of each hypothesis (-1 noise); accepted_label: the chosen
    cluster; mean_angles_deg: mean pairwise rotation angle per cluster label;
    extrinsics: the transform re-estimated on the accepted cluster's merged
    correspondences, concatenated with R_αβ (sensor -> world); pass_intervals_ns: (p, 2)
    [start, end] stamps of the distinct vehicle passes of the accepted tracks (fragments
    of one pass merged); rivals: (horizontal distance [m], passes) of every other agreeing
    group seen in nearly as many passes that places the radar elsewhere
    (``hypotheses.prune_hypotheses``); mount_turn: where the tracks show the mount turned
    during the recording (``hypotheses.mount_turn``), else None; passes_in_view: the
    vehicle's passes through the view under the accepted calibration
    (``hypotheses.vehicle_view_passes``), agreeing or not; passes_as_stamped: where the
    radar stamps were shifted because more passes agree so (``pipeline._hypotheses``), how
    many agreed as stamped, else -1; outfitted: where a group of tracks agreeing across
    nearly as many passes was set aside because the accepted one fills the vehicle's box
    far better, (its distance [m], its passes, the accepted group's share of targets in
    the box, its own), else None.
    """

    hypotheses: tuple[Hypothesis, ...]
    labels: I64
    accepted_label: int
    mean_angles_deg: dict[int, float]
    accepted_track_ids: tuple[int, ...]
    extrinsics: Extrinsics
    n_correspondences: int
    pass_intervals_ns: I64 = field(default_factory=lambda: np.zeros((0, 2), np.int64))
    rivals: tuple[tuple[float, int], ...] = ()
    mount_turn: MountTurn | None = None
    passes_in_view: int = 0
    passes_as_stamped: int = -1
    outfitted: tuple[float, int, float, float] | None = None

    @property
    def n_passes(self) -> int:
        """Distinct vehicle passes of the accepted tracks."""
        return int(self.pass_intervals_ns.shape[0])


@dataclass(frozen=True, slots=True)
class Refinement:
    """Stage 8 output: the final estimate, its covariance and what the fit learned.

    covariance: (7, 7) over [rotation vector (3, rad), translation (3, m), time offset (s)],
    in the world frame, from agreement across passes (bootstrap) or an equally honest
    method. reflection_profile: coefficients of the mean target offset in the vehicle frame
    over aspect angle (model-specific, documented in core/refine.py).
    """

    extrinsics: Extrinsics
    covariance: F64
    n_targets: int
    n_passes: int
    reflection_profile: F64 = field(default_factory=lambda: np.zeros(0))
    diagnostics: dict[str, Any] = field(default_factory=dict)


@dataclass(frozen=True, slots=True)
class QualityReport:
    """Stage 9: the paper's metrics and ours (CONTRACT.md "Quality figures")."""

    inlier_ratio: float
    outlier_distance_m: float
    closest_target_offset_m: float
    tracks_used: int
    hypotheses: int
    correspondences: int
    passes: int
    time_offset_s: float
    sigma_translation_m: float
    sigma_along_boresight_m: float
    sigma_across_boresight_m: float
    sigma_vertical_m: float
    sigma_rotation_deg: float
    advice: tuple[str, ...] = ()
    extra: dict[str, Any] = field(default_factory=dict)
    # NaN where the clock offset was not estimated (sync.estimate_time_offset false, or
    # the paper's stages only)
    sigma_time_offset_s: float = math.nan
    # of the result's rpy_deg: roll, pitch, yaw (``quality.rpy_sigmas_deg``)
    sigma_rotation_axes_deg: tuple[float, float, float] = (math.nan, math.nan, math.nan)
