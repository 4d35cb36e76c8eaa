"""The report's figures, one function per figure, each returning a matplotlib ``Figure``.

Figures are built on ``matplotlib.figure.Figure`` directly, never through ``pyplot``: no
global figure registry, no backend selection, no display; ``Figure.savefig`` renders PNG
with the Agg canvas. Each figure carries its own title, axis labels with units and legend,
so it reads on its own outside the HTML page.

Scatter plots draw at most ``_MAX_POINTS`` points (an evenly spaced subsample: the same
picture every run) over binned medians or means computed from all of them.
"""
from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
from matplotlib.axes import Axes
from matplotlib.colors import Normalize
from matplotlib.figure import Figure
from matplotlib.lines import Line2D
from matplotlib.patches import Polygon, Rectangle
from scipy.spatial import ConvexHull, QhullError

from radar_calib_ros.config import CalibConfig, VehicleConfig
from radar_calib_ros.core import reflection
from radar_calib_ros.core import vehicle as vehicle_box
from radar_calib_ros.evaluate import Evaluation
from radar_calib_ros.io.geo import LocalFrame
from radar_calib_ros.recording import interpolate_poses
from radar_calib_ros.types import F64, Extrinsics, GroundPlane, HypothesisSelection, Refinement

#: Most points a scatter plot draws.
_MAX_POINTS = 20_000
#: Gap between the calibration vehicle's targets that separates two passes [s].
_PASS_GAP_S = 5.0
#: Smallest travel between two vehicle boxes drawn in the bird's-eye view, in vehicle
#: lengths: boxes overlap a little, as in the paper's figure, yet stay apart.
_BOX_SPACING_LENGTHS = 0.6
_DPI = 110
#: Colour of the estimated sensor position (the paper's Fig. 4 uses a cyan cross).
_SENSOR_COLOUR = 'tab:cyan'


def _figure(width_in: float, height_in: float) -> Figure:
    return Figure(figsize=(width_in, height_in), dpi=_DPI, layout='constrained')


def save_figure(figure: Figure, path: Any) -> None:
    """Write a figure as PNG (Agg canvas)."""
    figure.savefig(path, format='png', dpi=_DPI)


def _thin(n: int, limit: int = _MAX_POINTS) -> np.ndarray:
    """Evenly spaced indices of at most ``limit`` of n items."""
    if n <= limit:
        return np.arange(n)
    return np.linspace(0, n - 1, limit).round().astype(np.int64)


def _binned(x: F64, y: F64, edges: F64, stat: str = 'median',
            min_count: int = 5) -> tuple[F64, F64, F64, F64]:
    """(bin centres, statistic, 25th, 75th percentile) of y per bin of x, bins with at
    least ``min_count`` samples only (a few dozen bins: a plain loop)."""
    idx = np.searchsorted(edges, x, side='right') - 1
    centres, values, lo, hi = [], [], [], []
    for k in range(edges.size - 1):
        v = y[idx == k]
        if v.size < min_count:
            continue
        centres.append(0.5 * (edges[k] + edges[k + 1]))
        values.append(float(np.median(v)) if stat == 'median' else float(np.mean(v)))
        lo.append(float(np.percentile(v, 25)))
        hi.append(float(np.percentile(v, 75)))
    return np.asarray(centres), np.asarray(values), np.asarray(lo), np.asarray(hi)


def _range_edges(r: F64, step: float = 5.0) -> F64:
    top = max(step, math.ceil(float(np.max(r)) / step) * step) if r.size else step
    return np.arange(0.0, top + step / 2, step)


def _no_data(figure: Figure, ax: Axes, message: str) -> None:
    ax.text(0.5, 0.5, message, ha='center', va='center', transform=ax.transAxes, wrap=True)
    ax.set_xticks([])
    ax.set_yticks([])


# --- the paper's evaluation figures ---------------------------------------------------------

def _utm_offset(frame: LocalFrame, xy_local: F64) -> tuple[F64, F64]:
    """UTM coordinates of local points and the round origin subtracted for the axes."""
    utm = frame.local_to_utm(np.column_stack([xy_local, np.zeros(len(xy_local))]))[:, :2]
    origin = np.floor(utm.min(axis=0) / 100.0) * 100.0
    return utm, origin


def _pick_pass(stamps_ns: np.ndarray, positions_m: F64) -> np.ndarray:
    """Mask of the frames of the pass with the longest travel of the vehicle (the clearest
    picture of the test track; a pass that queues at a light piles boxes on one spot)."""
    order = np.argsort(stamps_ns)
    gaps = np.diff(stamps_ns[order]) > _PASS_GAP_S * 1e9
    pass_id = np.empty(stamps_ns.size, np.int64)
    pass_id[order] = np.concatenate([[0], np.cumsum(gaps)])
    best, best_len = 0, -1.0
    for p in range(int(pass_id.max()) + 1):
        pts = positions_m[order][pass_id[order] == p, :2]
        length = float(np.sum(np.hypot(*np.diff(pts, axis=0).T))) if len(pts) > 1 else 0.0
        if length > best_len:
            best, best_len = p, length
    return np.asarray(pass_id == best, dtype=np.bool_)


def figure_bev_track(evaluation: Evaluation, config: CalibConfig) -> Figure:
    """Bird's-eye view of one test track (the paper's Fig. 4), on UTM axes.

    One pass of the calibration vehicle: its box at frames at least ``_BOX_SPACING_M``
    apart, the targets of its associated tracks in those frames (convex hulls for clusters
    of three or more) coloured by time from black to yellow, and the estimated sensor
    position as a cyan cross.
    """
    ev = evaluation
    rec = ev.recording
    fig = _figure(8.0, 7.0)
    ax = fig.add_subplot()
    frame_of_target = rec.targets.frame_index[ev.target_index]
    frames = np.unique(frame_of_target)
    stamps = rec.frame_stamps_ns[frames]
    offset_ns = np.int64(round((config.sync.time_offset + ev.extrinsics.time_offset_s) * 1e9))
    poses = interpolate_poses(rec.vehicle, stamps + offset_ns, config.sync.max_pose_gap)
    frames, stamps = frames[poses.valid], stamps[poses.valid]
    pos, yaw = poses.positions_m[poses.valid], poses.yaw_rad[poses.valid]
    epsg = int(ev.calibration['epsg'])
    frame = rec.frame if epsg == rec.frame.epsg else LocalFrame(rec.frame.lat0_deg,
                                                                rec.frame.lon0_deg, epsg)
    if frames.size == 0:
        _no_data(fig, ax, 'no frame of the calibration vehicle with a valid pose')
        return fig
    chosen = _pick_pass(stamps, pos)
    frames, stamps, pos, yaw = frames[chosen], stamps[chosen], pos[chosen], yaw[chosen]
    spacing_m = _BOX_SPACING_LENGTHS * config.vehicle.length
    keep = [0]
    for k in range(1, frames.size):   # a few hundred frames: plain loop
        if math.hypot(*(pos[k, :2] - pos[keep[-1], :2])) >= spacing_m:
            keep.append(k)
    keep_arr = np.asarray(keep)
    frames, stamps, pos, yaw = frames[keep_arr], stamps[keep_arr], pos[keep_arr], yaw[keep_arr]
    t_s = (stamps - stamps[0]) * 1e-9
    corners = vehicle_box.box_corners_world(pos, yaw, config.vehicle)
    sensor = np.asarray(ev.extrinsics.translation_m, float)
    all_xy = np.concatenate([corners.reshape(-1, 2), sensor[None, :2]])
    _, origin = _utm_offset(frame, all_xy)

    def to_axes(xy: F64) -> F64:
        return _utm_offset(frame, xy)[0] - origin

    norm = Normalize(0.0, max(float(t_s[-1]), 1e-3))
    cmap = _time_cmap()
    world = ev.extrinsics.apply(rec.targets.positions_m[ev.target_index])
    for k, f in enumerate(frames):
        colour = cmap(norm(t_s[k]))
        box = to_axes(corners[k])
        ax.add_patch(Polygon(box, closed=True, fill=False, edgecolor=colour, lw=1.0, zorder=2))
        # front edge thicker: the driving direction reads at a glance
        ax.plot(box[1:3, 0], box[1:3, 1], color=colour, lw=2.5, zorder=2)
        pts = to_axes(world[frame_of_target == f, :2])
        ax.scatter(pts[:, 0], pts[:, 1], s=9, color=colour, edgecolors='none', zorder=3)
        if len(pts) >= 3:
            try:
                hull = ConvexHull(pts)
            except QhullError:   # collinear or repeated targets: the dots say it all
                continue
            ax.add_patch(Polygon(pts[hull.vertices], closed=True, facecolor=colour, alpha=0.35,
                                 edgecolor=colour, lw=0.8, zorder=3))
    s = to_axes(sensor[None, :2])[0]
    ax.plot(s[0], s[1], marker='x', ms=14, mew=3, color=_SENSOR_COLOUR, zorder=5,
            linestyle='none')
    shown = np.concatenate([to_axes(all_xy), s[None, :]])
    lo, hi = shown.min(axis=0), shown.max(axis=0)
    centre, half = 0.5 * (lo + hi), 0.5 * float(np.max(hi - lo)) + 5.0
    ax.set_xlim(centre[0] - half, centre[0] + half)
    ax.set_ylim(centre[1] - half, centre[1] + half)
    ax.set_aspect('equal', adjustable='box')
    sm = _scalar_mappable(norm, cmap)
    fig.colorbar(sm, ax=ax, shrink=0.8, label='time since the first box of the pass [s]')
    ax.set_xlabel(f'easting - {origin[0]:,.0f} m [m]  (UTM, EPSG:{epsg})')
    ax.set_ylabel(f'northing - {origin[1]:,.0f} m [m]')
    ax.grid(True, alpha=0.3)
    fig.suptitle(f"Bird's-eye view of one test track: {t_s[-1]:.1f} s, {frames.size} boxes "
                 f'of the calibration vehicle\n(every {spacing_m:.1f} m) and its target '
                 'clusters (hulls for 3+ targets), coloured by time', fontsize=11)
    ax.legend(handles=[
        Line2D([], [], color='0.3', lw=1.0, label='vehicle box (front edge thick)'),
        Line2D([], [], marker='o', color='0.3', ls='none', ms=4, label='its targets'),
        Line2D([], [], marker='x', color=_SENSOR_COLOUR, mew=3, ms=10, ls='none',
               label='estimated sensor position')], loc='best', fontsize=8)
    return fig


def _time_cmap() -> Any:
    from matplotlib import colormaps
    from matplotlib.colors import ListedColormap
    # inferno from black to yellow, without its last, almost white tenth
    return ListedColormap(colormaps['inferno'](np.linspace(0.0, 0.9, 256)))


def _scalar_mappable(norm: Normalize, cmap: Any) -> Any:
    from matplotlib.cm import ScalarMappable
    return ScalarMappable(norm=norm, cmap=cmap)


def figure_outlier_distance(evaluation: Evaluation) -> Figure:
    """delta_op over target range (the paper's Fig. 2) and r_i per range bin."""
    p = evaluation.paper
    fig = _figure(9.0, 6.5)
    ax, ax_ri = fig.subplots(2, 1, sharex=True, height_ratios=[3, 1.3])
    out = p.distance_m > 0.0
    r, d = p.range_m[out], p.distance_m[out]
    if r.size:
        sel = _thin(r.size)
        ax.scatter(r[sel], d[sel], s=4, alpha=0.35, color='tab:red', edgecolors='none',
                   label=f'outlier targets ({r.size})')
        c, mean, _, _ = _binned(r, d, _range_edges(p.range_m), stat='mean')
        ax.plot(c, mean, '-o', color='k', ms=4, label='mean per 5 m of range')
        ax.axhline(p.outlier_distance_m, color='tab:blue', ls='--',
                   label=f'delta_op = {p.outlier_distance_m:.2f} m (all outliers)')
        top = max(float(np.max(d)) * 1.1, 0.5)
        if float(np.percentile(d, 99)) > 4.0:
            # far strays (other road users in a merged track, ghosts) would squash the
            # decimetres that matter: linear up to 1 m, logarithmic beyond
            ax.set_yscale('symlog', linthresh=1.0, linscale=1.5)
            ax.set_ylabel('distance to the vehicle box [m]\n(linear to 1 m, log beyond)')
            # symlog labels only its decades: a probe's bad calibration (delta_op 1.35 m)
            # showed no label above 1 m to read the line and the strays against
            ticks = [0.0, 0.25, 0.5, 0.75, 1.0] + [v for v in (2.0, 5.0, 10.0, 20.0, 50.0,
                                                               100.0, 200.0) if v < top]
            ax.set_yticks(ticks, [f'{t:g}' for t in ticks])
        else:
            ax.set_ylabel('distance to the vehicle box [m]')
        ax.set_ylim(0.0, top)
        # where the data leave room: a fixed corner covered a bad calibration's outliers
        ax.legend(fontsize=8, loc='best')
    else:
        ax.text(0.5, 0.5, 'every target lies inside the vehicle box', ha='center',
                transform=ax.transAxes)
        ax.set_ylabel('distance to the vehicle box [m]')

    ax.grid(True, alpha=0.3)
    ax.set_title('Outlier distance delta_op over the distance between target and sensor\n'
                 f'(targets outside the vehicle box; r_i = {100 * p.inlier_ratio:.1f} % of '
                 f'{p.n_targets} targets inside)', fontsize=10)
    bins = [b for b in evaluation.range_bins if b.n_targets > 0]
    for b in bins:
        hi = b.hi_m if math.isfinite(b.hi_m) else max(b.lo_m + 20.0, float(p.range_m.max()))
        ax_ri.bar(0.5 * (b.lo_m + hi), 100 * b.inlier_ratio, width=0.9 * (hi - b.lo_m),
                  color='tab:green', alpha=0.7)
        ax_ri.text(0.5 * (b.lo_m + hi), 4, f'n={b.n_targets}', ha='center', va='bottom',
                   fontsize=7)
    ax_ri.set_ylim(0, 105)
    ax_ri.set_ylabel('r_i [%]')
    ax_ri.set_xlabel('distance between target and sensor (horizontal) [m]')
    ax_ri.grid(True, alpha=0.3)
    ax_ri.set_xlim(left=0.0)
    return fig


def figure_closest_offset(evaluation: Evaluation, vehicle: VehicleConfig) -> Figure:
    """delta_p over the range of the nearest box corner, with the "max error" reference
    (the distance from the corner to the vehicle's centre; the paper's Fig. 3)."""
    p = evaluation.paper
    fig = _figure(9.0, 5.5)
    ax = fig.add_subplot()
    r, d = p.closest_range_m, p.closest_offset_m
    max_error = 0.5 * math.hypot(vehicle.length, vehicle.width)
    if r.size:
        sel = _thin(r.size)
        ax.scatter(r[sel], d[sel], s=6, alpha=0.4, color='tab:purple', edgecolors='none',
                   label=f'per frame ({r.size} frames)')
        c, mean, lo, hi = _binned(r, d, _range_edges(r), stat='mean')
        ax.plot(c, mean, '-o', color='k', ms=4, label='mean per 5 m of range')
        ax.fill_between(c, lo, hi, color='k', alpha=0.12, label='25-75 % per bin')
        ax.axhline(p.closest_target_offset_m, color='tab:blue', ls='--',
                   label=f'delta_p = {p.closest_target_offset_m:.2f} m (mean)')
        ax.set_ylim(0.0, max(float(np.percentile(d, 99)), max_error) * 1.15)
    ax.axhline(max_error, color='tab:red', lw=2,
               label=f'max error: corner to vehicle centre = {max_error:.2f} m')
    ax.set_xlabel('distance between sensor and the nearest vehicle corner (horizontal) [m]')
    ax.set_ylabel('closest target to that corner [m]')
    ax.set_xlim(left=0.0)
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=8, loc='upper right')
    ax.set_title('Offset delta_p between the target closest to the sensor and the nearest '
                 'vehicle corner,\nover range (it grows with range at the right calibration '
                 'too, fewer returns far out; a rotation\nerror adds range x angle: 1.7 m per '
                 '100 m and degree)', fontsize=10)

    return fig


# --- calibration-internal figures -------------------------------------------------------

def figure_hypotheses(selection: HypothesisSelection, final: Extrinsics) -> Figure:
    """Translations of all per-track hypotheses relative to the final estimate, the
    accepted cluster highlighted, and the mean pairwise rotation angle per cluster (against
    its size, so that dozens of chance clusters stay readable)."""
    fig = _figure(13.0, 5.8)
    ax, ax_zoom, ax_ang = fig.subplots(1, 3, width_ratios=[1.2, 1.2, 1.0])
    hyps = selection.hypotheses
    if not hyps:
        _no_data(fig, ax, 'no hypothesis')
        return fig
    t = np.array([np.asarray(h.translation_m, float)[:2] for h in hyps])
    rel = t - np.asarray(final.translation_m, float)[:2]
    labels = np.asarray(selection.labels)
    acc = selection.accepted_label
    others = [int(k) for k in np.unique(labels[(labels >= 0) & (labels != acc)])]
    # tab10 without its red (the accepted cluster's) and grey (no cluster)
    palette = [f'C{i}' for i in (0, 1, 2, 4, 5, 6, 8, 9)]
    colour_of = {k: palette[i % len(palette)] for i, k in enumerate(others)}
    noise = labels < 0
    in_other = np.isin(labels, others)
    accepted = labels == acc
    for a in (ax, ax_zoom):
        if noise.any():
            a.scatter(rel[noise, 0], rel[noise, 1], marker='x', color='0.6', s=18,
                      label=f'in no cluster ({int(noise.sum())})')
        if in_other.any():
            a.scatter(rel[in_other, 0], rel[in_other, 1], s=22, zorder=3,
                      color=[colour_of[int(k)] for k in labels[in_other]],
                      label=f'{len(others)} other cluster(s) ({int(in_other.sum())})')
        if accepted.any():
            a.scatter(rel[accepted, 0], rel[accepted, 1], s=60, color='tab:red',
                      edgecolors='k', zorder=4,
                      label=f'accepted cluster ({int(accepted.sum())})')
        a.plot(0, 0, marker='*', ms=16, color='gold', mec='k', ls='none', zorder=5,
               label='final estimate')
        # the zoom's limits are set below: it keeps them and adjusts its box instead
        a.set_aspect('equal', adjustable='datalim' if a is ax else 'box')
        a.grid(True, alpha=0.3)
        a.set_xlabel('east of the final estimate [m]')
        a.set_ylabel('north of the final estimate [m]')
    ax.set_title(f'All {len(hyps)} hypotheses (sensor positions)', fontsize=10)
    ax.legend(fontsize=8, loc='upper center', bbox_to_anchor=(0.5, -0.14), ncol=2)
    span = 2.0
    if accepted.any():
        span = max(float(np.max(np.abs(rel[accepted]))) * 1.3, 0.5)
    ax_zoom.set_xlim(-span, span)
    ax_zoom.set_ylim(-span, span)
    ax_zoom.set_title('Zoom on the accepted cluster', fontsize=10)
    angles = selection.mean_angles_deg
    sizes = {k: int(np.sum(labels == k)) for k in angles}
    finite = [v for v in angles.values() if math.isfinite(v) and v > 0]
    floor = min(finite) / 2 if finite else 0.01
    for k, v in angles.items():
        shown = v if math.isfinite(v) and v > 0 else floor
        mark = 'o' if math.isfinite(v) else 'v'
        if k == acc:
            ax_ang.plot(sizes[k], shown, mark, color='tab:red', mec='k', ms=11, zorder=4)
            text = f'{v:.2f} deg' if math.isfinite(v) else 'n/a'
            ax_ang.annotate(f'accepted: {text}', (sizes[k], shown), xytext=(-10, 8),
                            textcoords='offset points', fontsize=8, color='tab:red',
                            ha='right')

        else:
            ax_ang.plot(sizes[k], shown, mark, color=colour_of.get(k, 'C0'), ms=6, alpha=0.8)
    ax_ang.set_yscale('log')
    ax_ang.set_xlabel('hypotheses in the cluster')
    ax_ang.set_ylabel('mean pairwise rotation angle, all members [deg] (log)')
    # a probe read the accepted cluster's 9.7 deg against hypotheses.max_mean_angle_deg (5)
    # as a broken rule: the limit is on the members that agree, not on all of them
    ax_ang.set_title('Rotation agreement per cluster, all members\n(the limit holds for '
                     'those that agree;\ntriangle: not computed)', fontsize=9)
    ax_ang.grid(True, which='both', alpha=0.3)
    if sizes:
        ax_ang.set_xlim(0, max(sizes.values()) + 2)
    fig.suptitle(f'Calibration hypotheses: one per track, clustered by translation '
                 f'(accepted cluster: {int(accepted.sum())} hypotheses, of which '
                 f'{len(selection.accepted_track_ids)} tracks agree and were accepted, '
                 f'{selection.n_passes} passes)', fontsize=11)
    return fig


def figure_ground_plane(points_sensor_m: F64, ground: GroundPlane, config: CalibConfig,
                        ) -> Figure:
    """The ground-plane fit: targets in the sensor frame from above (density selection),
    from the side (x-z, pitch) and from the front (y-z, roll), with the fitted plane."""
    pts = np.asarray(points_sensor_m, float)
    used = np.zeros(len(pts), bool)
    used[np.asarray(ground.used, np.int64)] = True
    fig = _figure(13.0, 9.5)
    (ax_top, ax_side), (ax_front, ax_height) = fig.subplots(2, 2)
    sel = _thin(len(pts), 30_000)
    p, u = pts[sel], used[sel]
    n = np.asarray(ground.normal, float)
    # slope of the plane along the sensor's x and y axes
    slope_x = math.degrees(math.atan2(-n[0], n[2]))
    slope_y = math.degrees(math.atan2(-n[1], n[2]))
    ok = pts[used] if used.any() else pts
    dropped_label = 'dropped (sparser than the threshold, or gated)'
    used_label = (f'used in the fit ({int(used.sum())}): density >= '
                  f'{ground.density_threshold:.0f} targets within {config.ground.radius_m:g} m')
    for a, (i, j) in ((ax_top, (0, 1)), (ax_side, (0, 2)), (ax_front, (1, 2))):
        a.scatter(p[~u, i], p[~u, j], s=2, color='0.7', edgecolors='none', label=dropped_label)
        a.scatter(p[u, i], p[u, j], s=2, color='tab:blue', alpha=0.5, edgecolors='none',
                  label=used_label)
        a.grid(True, alpha=0.3)
    # the plane n . p = offset, drawn through the used targets' mean in the hidden axis
    xs = np.linspace(float(ok[:, 0].min()), float(ok[:, 0].max()), 50)
    y_mid = float(np.mean(ok[:, 1]))
    ax_side.plot(xs, (ground.offset_m - n[0] * xs - n[1] * y_mid) / n[2], color='tab:red',
                 lw=2, label=f'fitted plane at y = {y_mid:.1f} m')
    ys = np.linspace(float(ok[:, 1].min()), float(ok[:, 1].max()), 50)
    x_mid = float(np.mean(ok[:, 0]))
    ax_front.plot(ys, (ground.offset_m - n[0] * x_mid - n[1] * ys) / n[2], color='tab:red',
                  lw=2, label=f'fitted plane at x = {x_mid:.1f} m')
    z_lo, z_hi = np.percentile(ok[:, 2], [0.5, 99.5])
    pad = max(1.0, 0.3 * (z_hi - z_lo))
    for a in (ax_side, ax_front):
        a.set_ylim(z_lo - pad, z_hi + pad)
        a.set_ylabel('z (sensor up) [m]')
    ax_top.set_aspect('equal', adjustable='datalim')
    ax_top.set_xlabel('x (sensor forward) [m]')
    ax_top.set_ylabel('y (sensor left) [m]')
    ax_top.set_title('From above: the dense places over the lanes', fontsize=10)
    ax_side.set_xlabel('x (sensor forward) [m]')
    ax_side.set_title(f'From the side: the plane rises {slope_x:+.2f} deg along x '
                      '(sensor pitch)', fontsize=10)
    ax_front.set_xlabel('y (sensor left) [m]')
    ax_front.set_title(f'From the front: the plane rises {slope_y:+.2f} deg along y '
                       '(sensor roll)', fontsize=10)
    # Height above the fitted plane over the distance along it: a well-fitted plane leaves
    # the used targets' median level; a tilt error shows as a slope.
    height = ok @ n - ground.offset_m
    along = np.sqrt(np.maximum(np.sum(ok ** 2, axis=1) - (ok @ n) ** 2, 0.0))
    _scatter_with_median(ax_height, along, height, _range_edges(along), 'tab:blue',
                         trend='range')
    ax_height.set_xlabel('distance along the plane from the sensor [m]')
    ax_height.set_ylabel('height above the fitted plane [m]')
    ax_height.set_title('Used targets relative to the fitted plane (level median: '
                        'plane and targets agree)', fontsize=10)
    ax_height.legend(fontsize=7, loc='upper right')

    ax_top.legend(fontsize=7, loc='upper left', markerscale=4)
    ax_side.legend(fontsize=7, loc='upper right', handles=ax_side.get_lines())
    ax_front.legend(fontsize=7, loc='upper right', handles=ax_front.get_lines())
    fig.suptitle('Ground-plane fit of the moving targets in the sensor frame: normal '
                 f'({n[0]:+.4f}, {n[1]:+.4f}, {n[2]:+.4f}), plane {abs(ground.offset_m):.2f} m '
                 'below the sensor', fontsize=11)
    return fig


def _residual_arrays(refinement: Refinement | None) -> Mapping[str, Any] | None:
    if refinement is None:
        return None
    res = refinement.diagnostics.get('residuals')
    if not isinstance(res, Mapping) or 'range_m' not in res:
        return None
    return res


def _scatter_with_median(ax: Axes, x: F64, y: F64, edges: F64, colour: str,
                         trend: str | None = None, mean: bool = False) -> None:
    """Scatter, binned median and quartiles (and with ``mean`` the binned mean); with
    ``trend`` ('range' or 'azimuth') the straight-line trend of the binned medians and the
    rotation it corresponds to."""
    sel = _thin(x.size)
    ax.scatter(x[sel], y[sel], s=3, alpha=0.25, color=colour, edgecolors='none')
    # bins of a handful of targets (a stray cluster) draw wild quartiles: 15 at least
    c, med, lo, hi = _binned(x, y, edges, min_count=15)
    if c.size:
        ax.plot(c, med, '-', color='k', lw=1.8, label='median')
        ax.fill_between(c, lo, hi, color='k', alpha=0.15, label='25-75 %')
    if mean:
        cm, avg, _, _ = _binned(x, y, edges, stat='mean', min_count=15)
        ax.plot(cm, avg, '--', color='tab:purple', lw=1.4, label='mean')
    if trend is not None and c.size >= 4:
        # Each bin median weighted by its standard error (1.253 sigma / sqrt(n), sigma from
        # the quartiles): sparse, wide far bins must not set the slope. The slope's error
        # is scaled by the misfit, so an uneven profile widens it instead of faking a trend.
        counts = np.histogram(x, edges)[0]
        n = counts[np.searchsorted(edges, c, side='right') - 1].astype(float)
        sigma = np.maximum(1.253 * (hi - lo) / 1.349, 1e-6) / np.sqrt(n)
        (slope, intercept), cov = np.polyfit(c, med, 1, w=1.0 / sigma, cov=True)
        slope_se = math.sqrt(max(float(cov[0, 0]), 0.0))
        ax.plot(c, intercept + slope * c, color='tab:red', lw=1.2, ls='--', label='trend')
        if trend == 'range':
            text = (f'trend {1000 * slope:+.1f} +- {1000 * slope_se:.1f} cm per 10 m '
                    f'(= {math.degrees(math.atan(slope)):+.3f} +- '
                    f'{math.degrees(slope_se):.3f} deg)')
        else:
            text = f'trend {100 * slope:+.2f} +- {100 * slope_se:.2f} cm per deg'

        ax.text(0.02, 0.95, text, transform=ax.transAxes, va='top', fontsize=8,
                color='tab:red', bbox={'facecolor': 'white', 'alpha': 0.8, 'edgecolor': 'none'})
    ax.axhline(0.0, color='0.4', lw=0.8)
    ax.grid(True, alpha=0.3)
    if y.size:
        lo_y, hi_y = np.percentile(y, [1, 99])
        pad = 0.15 * max(hi_y - lo_y, 1e-3)
        ax.set_ylim(lo_y - pad, hi_y + pad)


def figure_refinement_residuals(refinement: Refinement | None) -> Figure | None:
    """Position residuals of the final refinement (target minus the reflection profile)
    along the line of sight, across it and vertically, over range and over azimuth. A
    systematic rotation error shows as a slope over range (across: yaw; vertical: pitch)
    or over azimuth. None without a refinement."""
    res = _residual_arrays(refinement)
    if res is None:
        return None
    rng = np.asarray(res['range_m'], float)
    az = np.degrees(np.asarray(res['azimuth_rad'], float))
    comps = [('along_los_m', 'along the line of sight [m]', 'tab:blue'),
             ('across_los_m', 'across the line of sight [m]', 'tab:orange'),
             ('vertical_m', 'vertical [m]', 'tab:green')]
    fig = _figure(11.0, 9.0)
    axes = fig.subplots(3, 2, sharex='col')
    r_edges = _range_edges(rng)
    a_edges = np.arange(np.floor(az.min() / 5) * 5, np.ceil(az.max() / 5) * 5 + 5, 5.0)
    for row, (key, label, colour) in enumerate(comps):
        y = np.asarray(res.get(key, np.zeros(0)), float)
        if y.size != rng.size:
            continue
        along = key == 'along_los_m'
        _scatter_with_median(axes[row, 0], rng, y, r_edges, colour,
                             trend=None if along else 'range', mean=along)
        _scatter_with_median(axes[row, 1], az, y, a_edges, colour, trend='azimuth',
                             mean=along)

        axes[row, 0].set_ylabel(f'residual {label}')
        axes[row, 1].set_ylabel(f'residual {label}')

    axes[0, 0].legend(fontsize=7, loc='upper right')
    axes[2, 0].set_xlabel('target range [m]')
    axes[2, 1].set_xlabel('target azimuth in the sensor frame [deg] (left positive)')
    fig.suptitle(f'Position residuals of the final refinement ({rng.size} targets, target '
                 'minus reflection profile)\na slope over range or azimuth would mean a '
                 'rotation error\nthe profile follows the targets\' (robust) mean: where they '
                 'spread unevenly along the line of sight, the median sits off zero',
                 fontsize=10)
    return fig


def figure_reflection_profile(refinement: Refinement | None, vehicle: VehicleConfig,
                              ) -> Figure | None:
    """The estimated reflection profile (mean target offset in the vehicle frame over the
    aspect angle) with the targets behind it, and in a top view of the vehicle box. None
    without a refinement or a profile."""
    res = _residual_arrays(refinement)
    if res is None or refinement is None or refinement.reflection_profile.size == 0:
        return None
    aspect = np.asarray(res.get('aspect_rad', np.zeros(0)), float)
    offsets = np.asarray(res.get('offset_vehicle_m', np.zeros((0, 3))), float).reshape(-1, 3)
    if aspect.size != offsets.shape[0] or aspect.size == 0:
        return None
    coeffs = np.asarray(refinement.reflection_profile, float)
    grid = np.linspace(-np.pi, np.pi, 361)
    try:
        profile = reflection.evaluate_profile(coeffs, grid)
    except ValueError:
        return None
    x0, x1, y0, y1 = vehicle_box.box_limits(vehicle)
    z0, z1 = -vehicle.ref_height, vehicle.height - vehicle.ref_height
    fig = _figure(13.0, 8.5)
    gs = fig.add_gridspec(3, 2, width_ratios=[1.5, 1.0])
    sel = _thin(aspect.size)
    a_deg = np.degrees(aspect)
    g_deg = np.degrees(grid)
    a_edges = np.arange(-180.0, 181.0, 10.0)
    names = [('x (forward)', (x0, x1)), ('y (left)', (y0, y1)), ('z (up)', (z0, z1))]
    for i, (name, (lo, hi)) in enumerate(names):
        a = fig.add_subplot(gs[i, 0])
        a.scatter(a_deg[sel], offsets[sel, i], s=3, alpha=0.2, color='0.45', edgecolors='none',
                  label='targets (vehicle frame)')
        c, med, _, _ = _binned(a_deg, offsets[:, i], a_edges)
        a.plot(c, med, 'o', color='k', ms=4, label='median of the targets per 10 deg')
        a.plot(g_deg, profile[:, i], color='tab:red', lw=2.2, label='estimated profile')
        a.axhline(lo, color='tab:blue', ls='--', lw=1)
        a.axhline(hi, color='tab:blue', ls='--', lw=1, label='box limits')
        a.set_ylabel(f'offset {name} [m]')
        a.set_xlim(-180, 180)
        a.set_xticks(np.arange(-180, 181, 45))
        a.grid(True, alpha=0.3)
        spread = hi - lo
        a.set_ylim(lo - 0.6 * spread, hi + 0.6 * spread)
        if i == 0:
            a.legend(fontsize=7, loc='upper right', markerscale=2, ncol=2)
        if i == 2:
            a.set_xlabel('aspect angle [deg]: the side of the car facing the radar '
                         '(0 front, 90 left, +-180 rear, -90 right)')
    top = fig.add_subplot(gs[:, 1])
    top.add_patch(Rectangle((x0, y0), x1 - x0, y1 - y0, fill=False, edgecolor='tab:blue',
                            lw=1.5, label='vehicle box'))
    top.scatter(offsets[sel, 0], offsets[sel, 1], s=2, alpha=0.15, color='0.45',
                edgecolors='none', label='targets')
    top.plot(profile[:, 0], profile[:, 1], color='tab:red', lw=1.5, label='profile m(aspect)')
    # every 30 deg: where the targets centre (dot) when the radar looks from the arrow's
    # direction
    step = np.arange(-180, 180, 30)
    p30 = reflection.evaluate_profile(coeffs, np.radians(step))
    direction = np.column_stack([np.cos(np.radians(step)), np.sin(np.radians(step))])
    top.quiver(p30[:, 0], p30[:, 1], direction[:, 0], direction[:, 1], color='tab:purple',
               angles='xy', scale_units='xy', scale=0.8, width=0.005, zorder=4,
               label='towards the radar')
    top.plot(p30[:, 0], p30[:, 1], 'o', color='tab:red', mec='k', ms=5, zorder=5,
             label='mean target position')
    for angle, name in ((0, 'front'), (90, 'left'), (-180, 'rear'), (-90, 'right')):
        k = int(np.flatnonzero(step == angle)[0])
        tip = p30[k, :2] + (1.6 if angle in (90, -90) else 2.2) * direction[k]

        top.text(tip[0], tip[1], f'{name} seen', ha='center', va='center', fontsize=8,
                 color='tab:purple')
    top.annotate('', xy=(x1 + 1.0, y0 - 0.6), xytext=(x1 - 0.5, y0 - 0.6),
                 arrowprops={'arrowstyle': '->', 'color': 'k'})
    top.text(x1 + 0.25, y0 - 0.45, 'forward', ha='center', fontsize=8)
    top.plot(0, 0, marker='+', color='k', ms=8, ls='none', label='reference point')
    top.set_xlim(x0 - 2.2, x1 + 2.2)
    top.set_ylim(y0 - 2.5, y1 + 2.5)
    top.set_aspect('equal', adjustable='box')
    top.set_xlabel('x, vehicle frame [m]')
    top.set_ylabel('y, vehicle frame [m]')
    top.grid(True, alpha=0.3)
    top.legend(fontsize=7, loc='upper center', bbox_to_anchor=(0.5, -0.12), ncol=2)
    top.set_title('Top view: the mean target position (dot) when\nthe radar looks from the '
                  "arrow's direction, every 30 deg", fontsize=10)

    fig.suptitle('Estimated reflection profile: mean target offset on the calibration '
                 f'vehicle over the aspect angle ({aspect.size} targets)', fontsize=11)
    return fig


def figure_velocity_residuals(refinement: Refinement | None) -> Figure | None:
    """Radial-velocity residuals (predicted minus measured) of the final refinement: their
    distribution, and over range and aspect angle. None without a refinement."""
    res = _residual_arrays(refinement)
    if res is None:
        return None
    v = np.asarray(res.get('velocity_mps', np.zeros(0)), float)
    rng = np.asarray(res['range_m'], float)
    if v.size == 0 or v.size != rng.size:
        return None
    aspect = np.degrees(np.asarray(res.get('aspect_rad', np.zeros(v.size)), float))
    fig = _figure(13.0, 4.8)
    ax_h, ax_r, ax_a = fig.subplots(1, 3)
    median = float(np.median(v))
    robust = 1.4826 * float(np.median(np.abs(v - median)))
    lo, hi = np.percentile(v, [0.5, 99.5])
    span = max(abs(lo), abs(hi), 0.2)
    ax_h.hist(np.clip(v, -span, span), bins=201, range=(-span, span), color='tab:cyan',
              edgecolor='none')
    ax_h.set_yscale('log')
    ax_h.axvline(median, color='k', lw=1.2, label=f'median {round(median, 3) + 0.0:+.3f} m/s')

    ax_h.set_xlabel('residual v_r, predicted - measured [m/s] (clipped at the ends)')
    ax_h.set_ylabel('targets (log scale)')
    ax_h.set_title(f'Distribution: robust sigma {robust:.3f} m/s', fontsize=10)
    ax_h.legend(fontsize=8)
    ax_h.grid(True, alpha=0.3)
    # the panels over range and aspect zoom on the rigid-body core; wheels lie beyond
    zoom = max(8.0 * robust, 0.3)
    beyond = float(np.mean(np.abs(v - median) > zoom))
    _scatter_with_median(ax_r, rng, v, _range_edges(rng), 'tab:cyan')
    _scatter_with_median(ax_a, aspect, v, np.arange(-180.0, 181.0, 10.0), 'tab:cyan')
    for a in (ax_r, ax_a):
        a.set_ylim(median - zoom, median + zoom)
        a.set_ylabel('residual v_r [m/s]')
    ax_r.set_xlabel('target range [m]')
    ax_r.legend(fontsize=7, loc='upper right')
    ax_r.set_title(f'Over range ({100 * beyond:.1f} % of the targets beyond the '
                   'axis: wheels, other cars)', fontsize=9)
    ax_a.set_xlim(-180, 180)
    ax_a.set_xticks(np.arange(-180, 181, 45))
    ax_a.set_xlabel('aspect angle [deg] (0 front, 90 left, +-180 rear)')
    ax_a.set_title('Over aspect angle', fontsize=10)
    fig.suptitle('Radial-velocity residuals of the final refinement: measured v_r against '
                 f"the rigid vehicle's motion on the line of sight ({v.size} targets)",
                 fontsize=11)
    return fig


def figure_titles() -> Sequence[str]:
    """File names of every figure the report can write, in page order."""
    return ('bev_track.png', 'outlier_distance.png', 'closest_offset.png', 'ground_plane.png',
            'hypotheses.png', 'refinement_residuals.png', 'reflection_profile.png',
            'velocity_residuals.png')
