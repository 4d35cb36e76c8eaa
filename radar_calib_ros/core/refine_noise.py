"""The noise a fit of the final refinement (stage 8, ``core/refine.py``) shows, for the
whitening of its next gate round.

From the fit's geometry (``_Model.geometry``): the reflectors' scatter around the profile
(``_scatter``), and the radar's azimuth and elevation noise as the radial velocities and the
heights show it (``_azimuth_noise_deg``, ``_elevation_noise_deg``), with the thresholds
from which a measured noise replaces the configured one and is named. Separate because these
are estimates from residuals that feed back into the weights, neither part of the model nor
of the choice of targets.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from radar_calib_ros.config import CalibConfig
from radar_calib_ros.core.refine_model import _Selected
from radar_calib_ros.types import F64


#: Azimuth noise shown by the radial velocities [deg] from which, when also twice
#: ``refine.azimuth_sigma_deg``, it replaces that in the whitening and is named. Our
#: simulator's radar (0.25-0.5 deg) shows 0.3-0.8 there (other noise grows with the
#: tangential speed too), an independent generator's 0.3 / 0.6 / 1 / 2 deg show 0.28 /
#: 0.52 / 0.89 / 1.80.
_AZIMUTH_NOISE_NOTE_DEG = 1.0


def _noisy_azimuth(shown_deg: float, configured_deg: float) -> bool:
    return shown_deg >= max(_AZIMUTH_NOISE_NOTE_DEG, 2.0 * configured_deg)


def _azimuth_noise_deg(g: dict[str, F64], data: _Selected) -> float:
    """The radar's azimuth noise [deg] as the radial velocities show it, from the fit's
    geometry ``g`` (``_Model.geometry``) over ``data``.

    A line of sight turned by azimuth noise n changes the predicted v_r by n times the
    speed across it (W_perp, the rigid car's velocity field at the radar, across the line
    of sight), whatever point of the car reflected: the v_r residuals' variance grows as
    s_v^2 + s_az^2 W_perp^2. Fitted over ten quantile bins of |W_perp| with a robust spread
    per bin (wheel micro-Doppler and stray targets are not Gaussian); 0 where the slope is
    not three of its standard errors above zero or the car never crossed the lines of sight
    fast. Position residuals cannot show it: the car's own extent across the line of sight
    swamps the noise there. Only a car driving straight counts (yaw rate below
    ``_NOISE_MAX_YAW_RATE_RPS``): turning, its velocity field carries what the pose stream
    and a rigid model get wrong in proportion to the rate (a real car's side slip, the
    reference point, the poses' timing under centripetal acceleration), and it crosses the
    lines of sight fastest just then; a forty-eighth probe's radar that saw U-turns and
    otherwise the car head-on read 1.1 deg of 'azimuth noise' from its 0.3 deg.
    """
    straight, w_perp = _straight_crossing(g)
    if w_perp.size < 10 * _NOISE_BIN_TARGETS:
        return 0.0
    slope, top = _spread_growth(np.abs(w_perp), (g['v_pred'] - data.v_mps)[straight])
    if top < _NOISE_CROSS_SPEED_MPS ** 2:
        return 0.0    # seen head-on only: too little speed across the lines of sight
    return float(np.degrees(math.sqrt(slope)))


def _straight_crossing(g: dict[str, F64]) -> tuple[np.ndarray, F64]:
    """The targets of a car driving straight (yaw rate below ``_NOISE_MAX_YAW_RATE_RPS``)
    and, for those, the speed of the rigid car's velocity field across their lines of sight
    (W_perp), from the fit's geometry ``g``."""
    straight = np.abs(g['rate']) < _NOISE_MAX_YAW_RATE_RPS
    unit, velocity = g['unit_v'][straight], g['point_velocity'][straight]
    return straight, velocity[:, 1] * unit[:, 0] - velocity[:, 0] * unit[:, 1]


def tilt_slopes(sensor_m: F64, rotation: F64, velocity: F64) -> F64:
    """(n, 2) change of each target's radial velocity per radian of the radar's roll and
    pitch (turns about its own x and y axes): ``v . R (e x u)``, with ``u`` the target's
    direction in the sensor frame (``sensor_m``, (n, 3)), ``R`` the sensor-to-world
    rotation and ``v`` the target's velocity (n, 3)."""
    unit = sensor_m / np.maximum(np.linalg.norm(sensor_m, axis=1), 1e-9)[:, None]
    zeros = np.zeros(unit.shape[0])
    rotation = np.asarray(rotation, np.float64)
    roll = np.column_stack([zeros, -unit[:, 2], unit[:, 1]]) @ rotation.T
    pitch = np.column_stack([unit[:, 2], zeros, -unit[:, 0]]) @ rotation.T
    return np.column_stack([np.sum(velocity * roll, axis=1), np.sum(velocity * pitch, axis=1)])


@dataclass(frozen=True, slots=True)
class AzimuthBias:
    """An error of the radar's azimuths that grows towards the edges of its view, as the
    radial velocities show it: ``linear_rad * t + cubic_rad * t**3`` at ``t`` = azimuth /
    ``half_width_rad``; ``edge_deg`` its size at the edge, ``edge_sigma_deg`` 1-sigma."""

    linear_rad: float
    cubic_rad: float
    half_width_rad: float
    edge_deg: float
    edge_sigma_deg: float

    def at(self, azimuth_rad: F64) -> F64:
        """The error [rad] at these azimuths."""
        t = np.asarray(azimuth_rad, np.float64) / self.half_width_rad
        return np.asarray(self.linear_rad * t + self.cubic_rad * t ** 3, np.float64)


def _azimuth_bias(g: dict[str, F64], data: _Selected) -> AzimuthBias | None:
    """The radar's azimuth error as an odd function of azimuth, from the radial velocities
    at the fit's geometry ``g`` (``_Model.geometry``) over ``data``; None where too few
    targets show it.

    Why: a target whose azimuth is off by d has its line of sight turned by d, so its
    predicted v_r is off by d times the speed across it (W_perp), whatever point of the car
    reflected. A constant d is the yaw the fit takes; one that grows towards the edges (an
    antenna array's angle calibration) no rotation absorbs, and it moved a forty-ninth
    probe's radar 0.6-2.0 m along its boresight at 0.5-1.5 deg at +-50 deg, with no word.
    Fitted over a car driving straight (as ``_azimuth_noise_deg``), with outliers beyond
    three robust deviations left out; the residual yaw is fitted with it.
    """
    straight, w_perp = _straight_crossing(g)
    if w_perp.size < 10 * _NOISE_BIN_TARGETS:
        return None
    residual = (g['v_pred'] - data.v_mps)[straight]
    azimuth = np.arctan2(data.sensor_m[straight, 1], data.sensor_m[straight, 0])
    half_width = float(np.percentile(np.abs(azimuth), 99))
    if half_width < math.radians(10.0):
        return None     # a narrow beam: nothing to grow over
    t = azimuth / half_width
    # A roll or pitch the fit has wrong turns the lines of sight too, pitch by its angle
    # times the sine of the azimuth (and the dip): fitted alongside, as the residual yaw is,
    # so that a tilt error is not read as one of the azimuths.
    design = np.column_stack([w_perp, w_perp * t, w_perp * t ** 3,
                              tilt_slopes(data.sensor_m[straight], g['rot'],
                                          g['point_velocity'][straight])])
    keep = np.ones(residual.size, bool)
    spread = 0.0
    for _ in range(3):
        coef, *_ = np.linalg.lstsq(design[keep], residual[keep], rcond=None)
        error = residual - design @ coef
        spread = max(1.4826 * float(np.median(np.abs(error[keep]))), 1e-3)
        keep = np.abs(error) <= 3.0 * spread
    normal = design[keep].T @ design[keep]
    if np.linalg.cond(normal) > 1e12:
        return None
    bread = np.linalg.inv(normal)
    covariance = bread * spread ** 2
    # The residuals are not independent where the radar's pointing moves with time (a pole
    # swaying in the wind, 0.5-3 s a period): every target of a frame, and of the frames
    # around it, shares the moment's yaw error, and over a pass that crosses the view the
    # moments map onto azimuths. A fifty-fourth probe's swaying poles were named an
    # azimuth bias 'of the antenna array's calibration' in 9 of 30 runs, its sign changing
    # from seed to seed, and corrected. The standard error is also taken clustered by pass
    # and stretch of ``_BIAS_BLOCK_S`` (a sandwich), and the larger counts.
    t_target = data.times.t_s[straight][keep]
    block = np.floor(t_target / _BIAS_BLOCK_S).astype(np.int64)
    _, cluster = np.unique(np.column_stack([data.pass_id[straight][keep], block]), axis=0,
                           return_inverse=True)
    cluster = cluster.ravel()
    n_clusters = int(cluster.max()) + 1
    if n_clusters > 1:
        score = np.zeros((n_clusters, design.shape[1]))
        np.add.at(score, cluster, design[keep] * error[keep][:, None])
        meat = score.T @ score * n_clusters / (n_clusters - 1)
        clustered = bread @ meat @ bread
        pick = np.array([0.0, 1.0, 1.0] + [0.0] * (design.shape[1] - 3))
        if float(pick @ clustered @ pick) > float(pick @ covariance @ pick):
            covariance = clustered
    edge = float(coef[1] + coef[2])
    edge_sigma = math.sqrt(max(float(covariance[1, 1] + covariance[2, 2]
                                     + 2.0 * covariance[1, 2]), 0.0))
    return AzimuthBias(float(coef[1]), float(coef[2]), half_width, math.degrees(edge),
                       math.degrees(edge_sigma))


#: Stretch of a pass [s] within which the radial velocities' residuals may share an error
#: of the radar's pointing (``_azimuth_bias``).
_BIAS_BLOCK_S = 3.0


#: An azimuth error at the edge of the view this large [deg], and this many of its
#: standard errors, is named and taken off (``pipeline``): our simulator's unbiased radars
#: and independent ones show 0.00-0.02 +- 0.02 deg; a probe's 0.5 / 1.5 deg read 0.48 / 1.39.
AZIMUTH_BIAS_MIN_DEG = 0.2
AZIMUTH_BIAS_MIN_Z = 6.0


def significant_azimuth_bias(bias: AzimuthBias | None) -> bool:
    """Whether ``bias`` is one to name and take off."""
    return (bias is not None and abs(bias.edge_deg) >= AZIMUTH_BIAS_MIN_DEG
            and abs(bias.edge_deg) >= AZIMUTH_BIAS_MIN_Z * bias.edge_sigma_deg)


def _spread_growth(driver: F64, residual: F64) -> tuple[float, float]:
    """How the residuals' variance grows with the square of ``driver`` (>= 0): over ten
    quantile bins of the driver, the robust spread (1.4826 MAD about the bin's median) of
    the residuals against the bin's mean driver squared, fitted by a straight line. Returns
    its slope (0 where not three of its standard errors above zero: no growth beyond the
    scatter of the bins) and the top bin's mean driver squared."""
    edges = np.quantile(driver, np.linspace(0.0, 1.0, 11))
    bins = np.clip(np.searchsorted(edges, driver, side='right') - 1, 0, 9)
    d2 = np.bincount(bins, driver ** 2, minlength=10) / np.maximum(
        np.bincount(bins, minlength=10), 1)
    spread2 = np.array([(1.4826 * np.median(np.abs(r - np.median(r)))) ** 2 if r.size else 0.0
                        for r in (residual[bins == b] for b in range(10))])
    design = np.column_stack([np.ones(10), d2])
    coef, *_ = np.linalg.lstsq(design, spread2, rcond=None)
    misfit = spread2 - design @ coef
    slope_var = float(misfit @ misfit) / 8.0 * np.linalg.inv(design.T @ design)[1, 1]
    slope = float(coef[1]) if coef[1] > 3.0 * math.sqrt(max(slope_var, 0.0)) else 0.0
    return slope, float(d2[-1])


def _noisy_elevation(shown_deg: float, configured_deg: float) -> bool:
    return shown_deg >= _ELEVATION_NOISE_RATIO * configured_deg


#: Elevation noise shown by the heights, as a multiple of ``refine.elevation_sigma_deg``,
#: from which it replaces that in the whitening and is named.
_ELEVATION_NOISE_RATIO = 1.4


def _elevation_noise_deg(g: dict[str, F64], data: _Selected) -> float:
    """The radar's elevation noise [deg] as the heights of the vehicle's targets show it,
    from the fit's geometry ``g`` (``_Model.geometry``) over ``data``.

    Elevation noise e moves a target vertically by its range times e, so the vertical
    residuals' variance grows as s_z^2 + (r s_el)^2, s_z the reflectors' own scatter in
    height. Fitted over ten quantile bins of range with a robust spread per bin (each bin
    centred on its own median, so a mean height that changes with range does not count);
    0 where the slope is not three of its standard errors above zero. Only targets that
    give height information count (``_inside_elevation_view``).
    """
    ok = data.vertical_ok
    if int(ok.sum()) < 10 * _NOISE_BIN_TARGETS:
        return 0.0
    slope, _ = _spread_growth(g['range'][ok], g['err'][ok, 2])
    return float(np.degrees(math.sqrt(slope)))


#: Fewest targets per bin of the azimuth-noise fit, and the least RMS speed across the
#: lines of sight [m/s] its top bin must reach (1 deg of noise then adds 0.07 m/s).
_NOISE_BIN_TARGETS = 30
_NOISE_CROSS_SPEED_MPS = 4.0
#: Yaw rate [rad/s] from which the car counts as turning for the azimuth-noise fit (a
#: 200 m radius at 10 m/s).
_NOISE_MAX_YAW_RATE_RPS = 0.05


def _scatter(g: dict[str, F64], floor_m: float, config: CalibConfig) -> F64:
    """Spread of the reflectors around the profile in the vehicle frame (x, y, z) for the
    next round's whitening, from the fit's geometry ``g`` (``_Model.geometry``): the robust
    spread (1.4826 MAD) of the position residuals minus the typical radar noise along that
    axis (range/azimuth horizontally, elevation vertically), floored."""
    c, s = g['c'], g['s']
    e = g['err']
    local = np.column_stack([c * e[:, 0] + s * e[:, 1], -s * e[:, 0] + c * e[:, 1], e[:, 2]])
    mad = 1.4826 * np.median(np.abs(local - np.median(local, axis=0)), axis=0)
    rng = g['range']
    cfg = config.refine
    noise_h = np.median(0.5 * (cfg.range_sigma_m ** 2
                               + (rng * math.radians(cfg.azimuth_sigma_deg)) ** 2))
    noise_v = np.median((rng * math.radians(cfg.elevation_sigma_deg)) ** 2)
    var = mad ** 2 - np.array([noise_h, noise_h, noise_v])
    return np.sqrt(np.maximum(var, (0.2 * floor_m) ** 2))
