"""run_calibration(): the stages of the method, called in the paper's order.

The node and the offline tool both call this on a ``Recording``; nothing here knows
whether the data came from a bag or from live messages.
"""
from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager, suppress
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from threadpoolctl import threadpool_limits

from radar_calib_ros.config import CalibConfig, RadarConfig, VehicleConfig
from radar_calib_ros.core import associate, cluster, ground_plane, hypotheses, moving, polygon
from radar_calib_ros.core import quality, refine, refine_noise, track, uncertainty
from radar_calib_ros.core import velocity_folding
from radar_calib_ros.errors import InsufficientDataError
from radar_calib_ros.io.geo import zone_note
from radar_calib_ros.recording import Recording, interpolate_poses
from radar_calib_ros.result import calibration_dict, quality_dict
from radar_calib_ros.types import (
    F64, Extrinsics, GroundPlane, Hypothesis, HypothesisSelection, MountTurn, QualityReport,
    Refinement, SmoothedTrack, Targets, TrackedTargets)
from radar_calib_ros.vehicle_track import TWIST_MAX_MPS, heading_offset_is_grid

_LOG = logging.getLogger(__name__)

#: Called as progress(stage_name, fraction_done) between stages.
ProgressFn = Callable[[str, float], None]

STAGES = ('moving', 'cluster', 'associate', 'ground_plane', 'track', 'hypotheses',
          'polygon', 'refine', 'quality')


@dataclass(frozen=True, slots=True)
class CalibrationResult:
    """Everything a calibration run produced.

    ``extrinsics`` is the final estimate in ``recording.frame`` (local metric frame);
    ``stage_extrinsics`` the estimate after stages 6, 7 and 8 (for the bench table).
    """

    extrinsics: Extrinsics
    quality: QualityReport
    recording: Recording
    tracked: TrackedTargets
    ground: GroundPlane
    tracks: tuple[SmoothedTrack, ...]
    selection: HypothesisSelection
    refinement: Refinement | None
    stage_extrinsics: dict[str, Extrinsics]
    stage_times_s: dict[str, float] = field(default_factory=dict)

    def calibration(self, config: CalibConfig, stamp: str | None = None) -> dict[str, Any]:
        """The contract's result mapping (UTM)."""
        quality = quality_dict(self.quality)
        # the box the figures and the fit used: ``evaluate`` on another recording with
        # another box reads a mismatch as a bad calibration (a thirty-seventh probe's van
        # drive with the car's box: r_i 51 %, delta_op 0.39 m, as a 1 m error)
        quality['vehicle'] = {name: float(getattr(config.vehicle, name))
                              for name in VEHICLE_BOX_PARAMETERS}
        # the part of time_offset_s that was given, not fitted: evaluate on a recording of
        # another clock takes that recording's sync.time_offset plus the fitted rest (a
        # forty-first probe's 18 s GPS/UTC drive was 'never seen' with it set in --params)
        quality['sync_time_offset_s'] = float(config.sync.time_offset)
        # the radar stamps the calibration saw [s]: evaluate on the same recording says it
        # checks nothing there
        # (never an empty list: it has no parameter type for a node reading the file)
        stamps = self.recording.frame_stamps_ns
        if stamps.size:
            quality['recording_span_s'] = [float(stamps[0]) * 1e-9, float(stamps[-1]) * 1e-9]
            quality['recording_frames'] = int(stamps.size)
            quality['recording_targets'] = len(self.recording.targets)
        return calibration_dict(self.extrinsics, self.recording.frame,
                                world_frame=config.world.frame_id,
                                radar_frame=self.recording.radar_frame_id,
                                quality=quality, stamp=stamp)


#: The ``vehicle.*`` parameters that place the vehicle's box, recorded in the result.
VEHICLE_BOX_PARAMETERS = ('length', 'width', 'height', 'rear_overhang', 'ref_height')


class _StageClock:
    """Times the stages and reports progress between them."""

    def __init__(self, progress: ProgressFn | None = None) -> None:
        self.progress = progress
        self.times: dict[str, float] = {}

    @contextmanager
    def __call__(self, name: str) -> Iterator[None]:
        if self.progress is not None:
            self.progress(name, STAGES.index(name) / len(STAGES))
        start = time.perf_counter()
        yield
        # a stage run twice (the sparse-radar retry) counts both runs
        self.times[name] = self.times.get(name, 0.0) + time.perf_counter() - start
        _LOG.debug('stage %s took %.3f s', name, self.times[name])


def track_targets(recording: Recording, config: CalibConfig, *,
                  clock: _StageClock | None = None) -> TrackedTargets:
    """Stages 1-3 (moving targets, clusters, tracks): the paper's object-tracking step, also
    all that ``evaluate`` runs on a second recording.

    Returns every moving target (``track_id`` -1 where it joined no track); empty when
    nothing moves.
    """
    stage = clock or _StageClock()
    targets = recording.targets
    with stage('moving'):
        moving_index = np.flatnonzero(moving.filter_moving_targets(
            targets.radial_velocity_mps, config.moving))
    if moving_index.size == 0:
        return TrackedTargets(np.zeros(0, np.int64), np.zeros(0, np.int64))
    moving_targets = targets.subset(moving_index)
    with stage('cluster'):
        clusters = cluster.cluster_targets(moving_targets, config.cluster)
    with stage('associate'):
        local = associate.associate_clusters(moving_targets, clusters, config.associate)
        index = moving_index[local.target_index]
        track_id = associate.split_tracks_at_time_gaps(
            local.track_id, recording.frame_stamps_ns[targets.frame_index[index]])
    return TrackedTargets(index, track_id)


#: Road users' targets per frame (median over the tracks' frames) at or below which the
#: radar may be too sparse for the paper's clustering defaults (three targets over three
#: frames, tracks of eight frames): an independent 10 Hz radar with ~1.2 targets on a car
#: was refused with its defaults and calibrated with ``_sparse_radar_settings``; our
#: simulator's drives thinned to a fifth of their targets (2 a frame) failed one draw in two
#: with the defaults and none with those settings.
_SPARSE_TARGETS_PER_FRAME = 2.0


#: Length of the car the paper's stage-6 thresholds are for [m], and those thresholds: a
#: longer calibration vehicle (a bus, a truck, an automated shuttle) spreads its
#: reflections over its length, so its tracks' centres wander along it and its hypotheses
#: scatter in proportion. A seventh probe's 12 m bus and 16.5 m truck were refused ("only 3
#: agree ... within 1.2 m") with the defaults and calibrated to 1-4 cm with these scaled.
_PAPER_VEHICLE_LENGTH_M = 6.0
_LENGTH_SCALED = ('hypotheses.eps_m', 'hypotheses.max_rms_m', 'hypotheses.max_cluster_rms_m')


def _scaled_to_vehicle(config: CalibConfig) -> CalibConfig:
    """The config with the stage-6 distance thresholds still at their defaults scaled by
    ``vehicle.length`` / ``_PAPER_VEHICLE_LENGTH_M`` (longer vehicles only); a value the
    user changed is kept as given."""
    scale = config.vehicle.length / _PAPER_VEHICLE_LENGTH_M
    if scale <= 1.0:
        return config
    defaults = CalibConfig()
    hypotheses = {name.split('.', 1)[1]: config.get(name) * scale for name in _LENGTH_SCALED
                  if config.get(name) == defaults.get(name)}
    if not hypotheses:
        return config
    _LOG.info('stage 6 thresholds scaled by %.2f for a %.1f m vehicle: %s', scale,
              config.vehicle.length, hypotheses)
    return replace(config, hypotheses=replace(config.hypotheses, **hypotheses))


def _targets_per_frame(recording: Recording, tracked: TrackedTargets) -> float | None:
    """Median number of targets a track has in a frame (None without tracks)."""
    in_track = tracked.track_id >= 0
    if not in_track.any():
        return None
    frames = recording.targets.frame_index[tracked.target_index[in_track]]
    _, per_frame = np.unique(np.column_stack([tracked.track_id[in_track], frames]), axis=0,
                             return_counts=True)
    return float(np.median(per_frame))


#: Association gate for a sparse radar [m]: a car's one to three targets a frame jump
#: about its length from frame to frame, on top of a frame's travel (1.7 m at 17 m/s and
#: 10 Hz), beyond the default 3 m (a nineteenth probe's 10 Hz radar was refused with the
#: other sparse settings and calibrated to 0.23 m with this gate).
_SPARSE_GATE_M = 5.0


def _sparse_radar_settings(config: CalibConfig) -> dict[str, float]:
    """The clustering and tracking settings for a radar with about one target per road user
    a frame: clusters of two over six frames, tracks of five and six frames, a wider
    association gate. Only ever looser than ``config``'s."""
    cl, assoc, hyp = config.cluster, config.associate, config.hypotheses
    return {'cluster.min_samples': max(1, min(cl.min_samples, 2)),
            'cluster.accumulate_frames': max(cl.accumulate_frames, 6),
            'associate.min_track_frames': min(assoc.min_track_frames, 5),
            'associate.gate_m': max(assoc.gate_m, _SPARSE_GATE_M),
            'hypotheses.min_track_frames': min(hyp.min_track_frames, 6)}


def _settings_text(settings: dict[str, float]) -> str:
    parts = [f'{name}: {value}' for name, value in settings.items()]
    return ', '.join(parts[:-1]) + ' and ' + parts[-1]


def _sparse_radar_config(recording: Recording, tracked: TrackedTargets,
                         config: CalibConfig) -> tuple[CalibConfig, float] | None:
    """``config`` with the sparse-radar settings, and the targets a frame that call for
    them; None when the radar is not sparse or ``config`` already has them."""
    median = _targets_per_frame(recording, tracked)
    if median is None or median > _SPARSE_TARGETS_PER_FRAME:
        return None
    settings = _sparse_radar_settings(config)
    if all(config.get(name) == value for name, value in settings.items()):
        return None
    return config.replaced(settings), median


#: Targets a frame on road users' tracks below which they, not the clutter, make the
#: clutter's share high (``_ground_plane``), where the clutter itself is fewer than twice
#: as many a frame: a seventy-third probe's rain bursts, 34-46 a frame against 5 on road
#: users' tracks, were put down to road users giving few targets.
_FEW_ROAD_USER_TARGETS = 5.0


def _ground_plane(recording: Recording, tracked: TrackedTargets,
                  config: CalibConfig) -> tuple[GroundPlane, str | None]:
    """Stage 4 on the targets ``ground.targets`` names; with 'moving', kept clear of clutter
    that moves (``ground_plane.fit_road_plane``), with a note where it was."""
    positions = recording.targets.positions_m
    if config.ground.targets != 'moving':
        return ground_plane.fit_ground_plane(positions, config.ground), None
    frame_s = (recording.frame_stamps_ns[recording.targets.frame_index[tracked.target_index]]
               - recording.frame_stamps_ns[0]) * 1e-9
    ground, clutter = ground_plane.fit_road_plane(positions[tracked.target_index], frame_s,
                                                  tracked.track_id, config.ground)
    level = np.eye(3)      # the tilt from the radar's own up: under no rotation
    if _plane_tilt_deg(ground.normal, level) > _MAX_PLANE_TILT_DEG and recording.has_elevation:
        # The moving targets all lie near one line (the vehicle alone along one road): any
        # plane through that line fits them, and the one found turned the radar on its side
        # (a sixty-sixth probe: 16 of 53 thin drives rolled 31-93 deg and 2-13 m off, exit
        # 0). No roadside radar is mounted so: the plane of all targets (the road's own
        # returns and low clutter among them) is taken where it is upright enough.
        every = ground_plane.fit_ground_plane(positions, config.ground)
        moving_deg, every_deg = (_plane_tilt_deg(g.normal, level) for g in (ground, every))
        if every_deg <= _MAX_PLANE_TILT_DEG:
            note = (f'The moving targets put the road plane {moving_deg:.0f} deg from the '
                    'radar\'s up (they lie along one line: a plane turns freely about it); '
                    f'the plane of all targets, {every_deg:.0f} deg from it, was fitted '
                    'instead.')
            _LOG.warning('%s', note)
            return every, note
    if clutter is None:
        return ground, None
    # 'over 99 %', not '100 %', where the road users' targets are a sliver (a probe read
    # '100 %' as nothing real having moved)
    share = ('over 99' if clutter.share > 0.99 else f'{100 * clutter.share:.0f}')
    # A few clutter targets a frame are most of them where road users give the radar few (a
    # fifty-fourth probe's snow: 2.5 on the car, 4 false alarms, 'rain, snow or spray'
    # named first for clutter that was not there): the counts say which it is.
    frames = max(recording.frame_stamps_ns.size, 1)
    on_tracks = (1.0 - clutter.share) * tracked.target_index.size / frames
    other = clutter.share * tracked.target_index.size / frames
    note = (f'{share} % of the moving targets did not move as road users do ({other:.1f} a '
            f'frame against {on_tracks:.1f} on road users\' tracks: '
            f'{_clutter_cause(on_tracks, other)}) and tilted the '
            f'ground plane by {clutter.tilt_deg:.1f} deg: the plane was fitted to the road '
            'users\' tracks alone.')
    _LOG.warning('%s', note)
    return ground, note


def _clutter_cause(on_tracks: float, other: float) -> str:
    """What made most moving targets clutter, from the targets a frame on road users'
    tracks and off them (``_FEW_ROAD_USER_TARGETS``)."""
    if on_tracks < _FEW_ROAD_USER_TARGETS and other < 2.0 * _FEW_ROAD_USER_TARGETS:
        return 'road users gave the radar few targets'
    return ('the radar\'s false alarms, rain, snow or spray near it, ghosts of far targets '
            'folded into its range or of multipath, or other clutter that moves')


#: Largest angle between the road plane's normal and the radar's z axis believed [deg]: a
#: roadside radar looks down at the road by 3-25 deg, rolled by a few, never from its side
#: (a sixty-sixth probe's one-road planes were 31-93 deg off; a radar truly pitched further
#: keeps its plane, as the plane of all its targets is then no more upright).
_MAX_PLANE_TILT_DEG = 30.0


#: Step of the clock offsets tried when the hypotheses do not agree at the given one [s].
_CLOCK_STEP_S = 0.05


def _hypotheses(tracks: tuple[SmoothedTrack, ...], recording: Recording, ground: GroundPlane,
                config: CalibConfig, *, leaps: bool = True,
                tracked: TrackedTargets | None = None
                ) -> tuple[list[Hypothesis], HypothesisSelection]:
    """Stage 6, and again at other clock offsets when its hypotheses do not agree.

    The paper's stages pair radar stamps with vehicle poses as given (plus
    ``sync.time_offset``); only the final refinement estimates the clock offset. An offset
    displaces the vehicle by its speed times the offset along its direction of travel, so
    passes driven in opposite directions give translations metres apart (0.2 s at 12 m/s
    is 2.4 m each way) and never agree, while ``sync.max_time_offset`` promises offsets up
    to a quarter of a second. When stage 6 finds no agreement, it is tried again at offsets
    in steps of ``_CLOCK_STEP_S`` within that bound, and the offset whose agreeing group
    has the most tracks (then correspondences) is taken as the starting clock offset of
    the later stages. Only on failure: at the given offset nothing changes, and chance
    agreements of other road users at some offset are still refused by the final
    detection check.
    """
    max_off = config.sync.max_time_offset
    retry = config.sync.estimate_time_offset and max_off >= _CLOCK_STEP_S
    try:
        hyps = hypotheses.generate_hypotheses(tracks, recording, ground, config)
        selection = hypotheses.prune_hypotheses(hyps, tracks, recording, ground, config,
                                                tracked=tracked)
    except InsufficientDataError as first:
        if not retry:
            raise
        failure = first
    else:
        # A clock offset on straight roads driven both ways shifts the two directions
        # apart along the road, so only one direction agrees, and the rest of the method
        # takes its passes alone: an independent motorway gantry, radar 50 ms late, kept
        # 3 eastbound passes of 6 and was 1.4-2.4 m off at a 0.5 m sigma. Where fewer than
        # ``_AGREEING_SHARE`` of the passes in view agree, the other offsets are tried as
        # well, and one on which ``_AGREEING_GAIN`` more passes agree is taken.
        if not retry or selection.n_passes >= _AGREEING_SHARE * selection.passes_in_view:
            return hyps, selection
        shifted = _best_shifted(tracks, recording, ground, config,
                                key=lambda s: (s.n_passes, len(s.accepted_track_ids)),
                                tracked=tracked)
        if shifted is None or shifted[2].n_passes < selection.n_passes + _AGREEING_GAIN:
            return hyps, selection
        _LOG.info('%d of the %d passes in view agree as stamped, %d with the radar stamps '
                  'shifted by %+.2f s', selection.n_passes, selection.passes_in_view,
                  shifted[2].n_passes, shifted[0])
        return shifted[1], replace(_shifted_selection(shifted[2], shifted[0]),
                                   passes_as_stamped=selection.n_passes)
    best = _best_shifted(tracks, recording, ground, config,
                         key=lambda s: (len(s.accepted_track_ids), s.n_correspondences),
                         tracked=tracked)
    if best is None:
        reason = f'{failure.reason} (also at clock offsets up to +-{max_off:g} s)'
        beyond = _beyond_offset(tracks, recording, ground, config) if leaps else None
        leap = (_leap_offset(tracks, recording, ground, config)
                if leaps and beyond is None else None)
        if beyond is not None:
            reason += (f'; they agree with the radar stamps shifted by {beyond:+.2f} s, beyond '
                       f'sync.max_time_offset ({max_off:g} s): the radar\'s stamps are that '
                       'far off the vehicle\'s (a driver stamping at publication, an object '
                       f'tracker\'s latency?). Set sync.time_offset to '
                       f'{config.sync.time_offset + beyond:.2f} (or sync.max_time_offset to '
                       f'{math.ceil(abs(beyond) / _CLOCK_STEP_S) * _CLOCK_STEP_S + 0.1:.2f}) '
                       'and calibrate again')
        elif leap is not None:
            reason += (f'; they agree with the radar stamps shifted by {leap:+g} s, a whole '
                       'number of leap seconds (GPS, UTC and TAI time differ by 18, 19 and 37 '
                       f's): set sync.time_offset to {config.sync.time_offset + leap:g} and '
                       'calibrate again')
        elif leaps and _BEYOND_CLOCK_S > max_off:
            # a radar recorded on its own clock, seconds off and with nothing in the
            # recording to show it (a fifty-eighth probe's roadside bag, 2 s off: refused
            # with no hint; sync.max_time_offset 2.0 calibrated it to 4.6 cm)
            reason += (f', nor beyond that up to +-{_BEYOND_CLOCK_S:g} s: where the radar\'s '
                       'clock may be further off the vehicle\'s (no time sync between them), '
                       'raise sync.max_time_offset to search as far (a few seconds; it takes '
                       'longer)')
        raise InsufficientDataError(failure.stage, reason)
    offset, hyps, selection = best
    # said (or not) once the final refinement has fitted the offset: ``_shift_note``
    _LOG.info('the hypotheses agree only with the radar stamps shifted by %+.2f s', offset)
    return hyps, _shifted_selection(selection, offset)


#: The least share of the vehicle's passes through the view that must agree at stage 6
#: before other clock offsets are tried on success too (a direction of travel lost to an
#: offset is half of them; other road users hiding a pass or two are fewer).
_AGREEING_SHARE = 0.6
#: ... and how many more passes another offset must bring in to be taken: one pass on the
#: edge of agreement comes and goes with a shift of 50 ms, the other direction's many do not
_AGREEING_GAIN = 2


def _shifted_selection(selection: HypothesisSelection, offset_s: float) -> HypothesisSelection:
    ext = selection.extrinsics
    return replace(selection, extrinsics=Extrinsics(ext.rotation, ext.translation_m,
                                                    ext.time_offset_s + offset_s))


def _best_shifted(tracks: tuple[SmoothedTrack, ...], recording: Recording, ground: GroundPlane,
                  config: CalibConfig, key: Callable[[HypothesisSelection], tuple[int, int]],
                  tracked: TrackedTargets | None = None
                  ) -> tuple[float, list[Hypothesis], HypothesisSelection] | None:
    """Stage 6 at the radar stamps shifted by each offset within ``sync.max_time_offset``
    (and around the fixes' own clock, see ``_hypotheses``): the (offset, hypotheses,
    selection) whose selection ranks highest by ``key``, None where none agrees."""
    max_off = config.sync.max_time_offset
    n_steps = int(max_off / _CLOCK_STEP_S + 1e-9)
    offsets = [sign * k * _CLOCK_STEP_S for k in range(1, n_steps + 1) for sign in (1, -1)]
    # Where the fixes' stamps were found to lag the Odometry's, the poses run on the
    # Odometry's clock; a radar on the fixes' clock as stamped is then -lag away, maybe
    # beyond the bound (a ninth probe's Odometry stamped 0.5-1 s late): tried too.
    lag_s = recording.counters.get('fix_lag_ms', 0) / 1000.0
    if abs(lag_s) > max_off:
        offsets += [-lag_s + k * _CLOCK_STEP_S for k in range(-2, 3)]
    best: tuple[tuple[int, int], float, list[Hypothesis], HypothesisSelection] | None = None
    for offset in offsets:
        shifted = replace(config, sync=replace(config.sync,
                                               time_offset=config.sync.time_offset + offset))
        try:
            hyps = hypotheses.generate_hypotheses(tracks, recording, ground, shifted)
            selection = hypotheses.prune_hypotheses(hyps, tracks, recording, ground, shifted,
                                                    tracked=tracked)
        except InsufficientDataError:
            continue
        score = key(selection)
        if best is None or score > best[0]:
            best = (score, offset, hyps, selection)
    return None if best is None else best[1:]


#: How far the final fit's clock offset may lie from the shift stage 6 needed [s] for
#: that shift to be taken as the clocks' (steps of ``_CLOCK_STEP_S``, half of one beyond).
_SHIFT_CONFIRMED_S = 0.1


def _company_reason(company: quality.Company) -> str:
    east, north = company.offset_m
    bearing = math.degrees(math.atan2(east, north)) % 360.0
    if company.between:
        return (f'two road users kept pace side by side through the view on {company.drives} '
                f'of the vehicle\'s {company.judged} drives, {math.hypot(east, north):.1f} m '
                f'apart (along {bearing % 180.0:.0f}-{bearing % 180.0 + 180.0:.0f} deg from '
                'grid north) and at the same two places in the world on every drive: a '
                'straight road driven to and fro with company in the next lane? The best '
                'calibration put the vehicle between the two; a radar placed where either of '
                'them is the vehicle would see these drives alike, so which of the two is the '
                'calibration vehicle they cannot tell (its radial velocities neither: the two '
                'move alike). Drive again with no road user keeping pace beside the vehicle, '
                'or turn through the view and cross it on other roads, where company changes '
                'sides in the world.')
    return (f'another road user kept pace beside the vehicle on {company.drives} of its '
            f'{company.judged} drives through the view, {math.hypot(east, north):.1f} m from '
            f'it and always on the same side in the world (towards {bearing:.0f} deg from '
            'grid north): a straight road driven to and fro with company in the next lane? '
            'A radar placed that far over would see that road user where the vehicle was, '
            'just as these drives show it, so which of the two is the calibration vehicle '
            'they cannot tell (its radial velocities neither: the two move alike). Drive '
            'again with no road user keeping pace beside the vehicle, or turn through the '
            'view and cross it on other roads, where company changes sides in the world.')


#: The share of a close follower's headway that joins the clock offset's 1-sigma: a
#: fifty-ninth probe's follower 0.5 s behind left the clock 0.05-0.40 s off.
_IN_LINE_CLOCK_SHARE = 0.5


def _in_line_clock_sigma_s(in_line: quality.InLine, config: CalibConfig) -> float:
    """What a close follower or leader adds to the clock offset's 1-sigma [s]: a share of
    its headway, at most the range the offset was searched in, which the fit never left (a
    walker 1.7 m behind a car creeping at 0.8 m/s is 2.1 s of headway: a sixty-fourth
    probe's queue read 1.08 s, searched within 0.25 s and 11 ms off)."""
    return min(_IN_LINE_CLOCK_SHARE * in_line.headway_s, config.sync.max_time_offset)


def _in_line_note(in_line: quality.InLine, config: CalibConfig) -> str:
    """The note for a close follower or leader (``quality.company_in_line``)."""
    return (f'Another road user followed or led the vehicle closely in its lane on '
            f'{in_line.drives} of its {in_line.judged} drives through the view, '
            f'{in_line.gap_m:.1f} m centre to centre ({in_line.headway_s:.2f} s at its speed). '
            'Its targets move as the vehicle\'s do and lie where the vehicle\'s would with '
            'the radar\'s clock that much off, so the clock offset found is as much the '
            f'headway\'s: its uncertainty counts {_in_line_clock_sigma_s(in_line, config):.2f}'
            ' s for it, and sync.time_offset is not to be set from this recording. Drive with '
            'a gap of a second or more where the traffic allows.')


def _outfitted_note(outfitted: tuple[float, int, float, float], config: CalibConfig) -> str:
    distance, passes, share, other = outfitted
    # A bus or a truck shows the radar a flat face at each end, tracked apart from the rest
    # of it, and those tracks agree among themselves: a seventy-fifth probe's 12 m bus alone
    # on its road (no company) was told a road user had kept pace, 5.3-5.4 m away.
    length = config.vehicle.length
    who = (f'most likely the vehicle\'s own front or rear ({length:g} m apart), tracked apart '
           'from the rest of it, or a road user that kept pace with it'
           if hypotheses.long_vehicle(config) and distance <= length else
           'a road user that kept pace with the vehicle')
    return (f'Another group of tracks agreed across {passes} passes as well, placing the radar '
            f'{distance:.1f} m from this result: {who} '
            '(alongside it, or ahead or behind). Its targets filled the vehicle\'s box '
            f'(vehicle.*) {100 * other:.0f} % of the time, those taken {100 * share:.0f} %, so '
            'it was taken for another vehicle of another size. Check that vehicle.* describe '
            'the calibration vehicle; drive with no company keeping pace where the roads '
            'allow.')


def _held_clock_note(held_sigma_s: float, offset_s: float, config: CalibConfig) -> str:
    """What to say of a clock offset the final fit could not measure and held at stage 6's
    ``offset_s`` (on top of ``sync.time_offset``)."""
    # Held away from zero, the offset is what made stage 6's passes agree, not a measured
    # one, and a box misplaced along the vehicle makes them agree there as readily as the
    # clocks (a nineteenth probe's rear_overhang told 2.6 m for 1.1: held at +0.150 s with
    # the clocks in step; an eighteenth's 12 m bus told a 4.9 m car: at the +0.250 s limit)
    shifted = abs(offset_s) >= 0.5 * _CLOCK_STEP_S
    at_limit = (config.sync.max_time_offset > 0
                and abs(offset_s) >= config.sync.max_time_offset - 0.5 * _CLOCK_STEP_S)
    text = ('The drives did not show the radar\'s clock offset (the vehicle kept its speed '
            'through the view, where an offset only moves it along its own travel; it is '
            f'uncertain by {held_sigma_s:.2f} s, 1 sigma, as far as the search reaches, and '
            'the position along the drives by the vehicle\'s speed times that, both in the '
            f'result\'s uncertainty): it was held at {offset_s:+.3f} s on top of '
            'sync.time_offset')
    if shifted:
        text += (', where the paper\'s stages found the passes to agree best'
                 + (', at the limit of their search (sync.max_time_offset)' if at_limit else '')
                 + ': a shift there is ' + ('more often' if at_limit else 'as often')
                 + ' vehicle.* not describing the vehicle (a wrong vehicle.rear_overhang or '
                 'vehicle.length misplaces each pass along its travel) '
                 + ('than' if at_limit else 'as') + ' the clocks. Check vehicle.* first; set ')
    else:
        text += '. Set '
    return (text + 'sync.time_offset if the clocks are known to differ, or drive through the '
            'view with a stop or a turn to measure it.')


def _beyond_search(shift_s: float, fitted_s: float, max_off: float) -> bool:
    """Whether stage 6 agreed at the limit of its clock search (``shift_s``) and the final
    fit (``fitted_s``) went on past it the same way: the clocks are further apart than
    ``sync.max_time_offset`` (``max_off``)."""
    return (max_off > 0.0 and abs(shift_s) >= max_off - 0.5 * _CLOCK_STEP_S
            and shift_s * fitted_s > 0.0 and abs(fitted_s) > max_off)


#: Median interval [s] of the vehicle's own poses (before any spline between fixes) up to
#: which they place it in time well enough that a clock offset fitted beyond the search is
#: the clocks', not the poses'.
_DENSE_POSE_INTERVAL_S = 0.2


def azimuth_corrected(recording: Recording, bias: refine_noise.AzimuthBias) -> Recording:
    """The recording with every target turned about the radar's z axis by the azimuth
    error ``bias`` shows, back to where the radar should have put it."""
    p = recording.targets.positions_m
    turn = -bias.at(np.arctan2(p[:, 1], p[:, 0]))
    c, s = np.cos(turn), np.sin(turn)
    turned = np.column_stack([c * p[:, 0] - s * p[:, 1], s * p[:, 0] + c * p[:, 1], p[:, 2]])
    return replace(recording, targets=replace(recording.targets, positions_m=turned))


def _azimuth_bias_refuted_note(bias: refine_noise.AzimuthBias, kept: int, had: int) -> str:
    """Where the radial velocities showed an azimuth error that, taken off, fit the vehicle
    worse: the velocities are off its motion, not the azimuths."""
    return (f'The radial velocities read as the radar\'s azimuths off by {bias.edge_deg:+.2f} '
            f'deg at {math.degrees(bias.half_width_rad):.0f} deg from its boresight, but '
            f'azimuths corrected by it fit the vehicle worse ({kept} of its {had} targets '
            'kept): the radial velocities are off its motion for another reason (an object '
            'list\'s tracker velocities, smoothed and lagging on turns?). The azimuths were '
            'left as measured; check what the radar reports as velocity.')


def _azimuth_bias_note(bias: refine_noise.AzimuthBias) -> str:
    """What the radial velocities showed of the radar's azimuths, and what was done."""
    edge = math.degrees(bias.half_width_rad)
    half = math.degrees(float(bias.at(np.array([0.5 * bias.half_width_rad]))[0]))
    return (f'The radial velocities show the radar\'s azimuths off by {bias.edge_deg:+.2f} deg '
            f'(+-{bias.edge_sigma_deg:.2f}) at {edge:.0f} deg from its boresight and '
            f'{half:+.2f} at {edge / 2:.0f}, growing towards the edges of its view (an antenna '
            'array\'s angle calibration?); left in, such an error moves the position along '
            'the boresight by decimetres to metres. The targets\' azimuths were corrected by '
            'it and the radar fitted again. Have the radar\'s angle calibration checked.')


def _poses_dense(recording: Recording) -> bool:
    """Whether the vehicle's recorded poses come at least every ``_DENSE_POSE_INTERVAL_S``
    (the fixes' own interval where poses were splined between them)."""
    fix_ms = recording.counters.get('fix_interval_ms', 0)
    if recording.counters.get('poses_splined_between_fixes') and fix_ms:
        return fix_ms / 1000.0 <= _DENSE_POSE_INTERVAL_S
    stamps = recording.vehicle.stamps_ns
    return stamps.size > 1 and float(np.median(np.diff(stamps))) * 1e-9 <= _DENSE_POSE_INTERVAL_S


def _shift_note(shift_s: float, fitted_s: float | None) -> str | None:
    """What stage 6's need of a clock shift says, once the final fit has its own offset
    (None: not fitted). A shift the fit confirms is the clocks'; one it does not came from
    elsewhere (a fifth probe's 12 m bus under a car's vehicle.*: stage 6 agreed only at
    +0.20 s, the fit put the clocks 4 ms apart), and blaming the clocks misled."""
    if shift_s == 0.0:
        return None
    if (fitted_s is not None and abs(shift_s) <= _CLOCK_STEP_S + 1e-9
            and abs(fitted_s) < 0.5 * _CLOCK_STEP_S):
        # one step of stage 6's coarse grid, where agreement was marginal at zero; the fit
        # finds the clocks together: no offset to set (a probe read 'shifted by +0.05 s: a
        # clock offset' for clocks 0.3 ms apart). Larger shifts the fit does not confirm
        # are the note below.
        _LOG.info('the hypotheses agreed best with the radar stamps shifted by %+.2f s; the '
                  'final fit puts the clocks %+.3f s apart: no clock offset to set', shift_s,
                  fitted_s)
        return None
    # Confirmed where the fit lies nearer the shift than the clocks in step: a -0.10 s
    # shift with the fit at -0.004 s was within 0.1 s and named a clock offset, where a
    # forty-sixth probe's clocks were one and its fixes of a roof antenna 1 m ahead of the
    # declared reference point misplaced each pass along its travel.
    if fitted_s is None or abs(fitted_s - shift_s) <= min(_SHIFT_CONFIRMED_S,
                                                          0.5 * abs(shift_s)):
        _LOG.warning('the hypotheses agree best with the radar stamps shifted by %+.2f s: a '
                     'clock offset between radar and vehicle (sync.time_offset)%s', shift_s,
                     '' if fitted_s is None else f'; the final fit puts it at {fitted_s:+.3f} s')
        return None
    return (f'The paper\'s stages found the passes in agreement only with the radar stamps '
            f'shifted by {shift_s:+.2f} s, but the final fit puts the clocks {fitted_s:+.3f} s '
            'apart: the passes disagreed for another reason, most often vehicle.* not '
            'describing the vehicle (its box misplaces each pass\'s track), or other road '
            'users taken for it. Check those before sync.time_offset.')


#: Clock offsets of a radar and a vehicle on different time scales [s]: GPS - UTC, TAI -
#: GPS, TAI - UTC (leap seconds since 2017), either way round.
_LEAP_OFFSETS_S = (18.0, -18.0, 19.0, -19.0, 37.0, -37.0)


#: How far beyond ``sync.max_time_offset`` a failure looks for the offset at which stage 6
#: agrees [s] (in steps of ``_CLOCK_STEP_S``), to name it, not to take it.
_BEYOND_CLOCK_S = 1.0


def _beyond_offset(tracks: tuple[SmoothedTrack, ...], recording: Recording,
                   ground: GroundPlane, config: CalibConfig, least_passes: int = 0
                   ) -> float | None:
    """The offset nearest the given one, beyond ``sync.max_time_offset`` and within
    ``_BEYOND_CLOCK_S``, at which stage 6 agrees (as one group of at least
    ``least_passes`` passes, where that is given) and the vehicle is seen where that puts
    it, else None.

    Why: radar stamps 0.3-0.6 s late are ordinary where a driver stamps a frame when it is
    published, or an object tracker's output is recorded: a thirty-fifth probe's 0.6 s
    were refused with 'hypotheses do not agree', naming neither the clocks nor the
    parameter that finds them (sync.max_time_offset 1.0 calibrated them to the same
    centimetres as stamped right). Named, not taken: the bound is the user's.
    """
    max_off = config.sync.max_time_offset
    steps = np.arange(max_off + _CLOCK_STEP_S, _BEYOND_CLOCK_S + 1e-9, _CLOCK_STEP_S)
    best: tuple[tuple[int, int], float] | None = None
    for magnitude in steps:
        for off in (-float(magnitude), float(magnitude)):
            selection = _seen_agreeing(tracks, recording, ground, replace(config, sync=replace(
                config.sync, time_offset=config.sync.time_offset + off, max_time_offset=0.0)))
            if selection is None or (least_passes and (
                    selection.rivals or selection.n_passes < least_passes)):
                continue
            # the most agreeing tracks, as within the bound (``_best_shifted``): agreement
            # begins a few steps short of the clocks' offset
            key = (len(selection.accepted_track_ids), selection.n_correspondences)
            if best is None or key > best[0]:
                best = (key, off)
    return None if best is None else best[1]


#: Least share of the frames that put the moving vehicle in view which must show it
#: (``quality.vehicle_detection_ratio``) before a leap offset is named: a hint to move the
#: clocks by seconds needs more than a result's acceptance (``quality.min_vehicle_detection``).
#: Dense fast traffic agrees by chance somewhere: a sixty-eighth probe's gantry and
#: side-fire drives (true offsets 0.12-0.15 s) were told to set sync.time_offset to 19, and
#: at it the vehicle was seen in 25 and 40 % of those frames; nine recordings of three
#: probes with their parameters 18-37 s off showed it in 59-100 %.
_LEAP_MIN_DETECTION = 0.5


def _leap_offset(tracks: tuple[SmoothedTrack, ...], recording: Recording, ground: GroundPlane,
                 config: CalibConfig) -> float | None:
    """The first of ``_LEAP_OFFSETS_S`` at which stage 6 agrees (with its search of small
    offsets around it) and the vehicle is seen where that puts it in view
    (``_LEAP_MIN_DETECTION``), else None. Only named in the failure, not taken: a whole
    time scale apart is a set-up fault to fix at the source (and the result's clock offset
    must stay the one the user's parameters define)."""
    for leap in _LEAP_OFFSETS_S:
        shifted = replace(config, sync=replace(config.sync,
                                               time_offset=config.sync.time_offset + leap))
        if _seen_agreeing(tracks, recording, ground, shifted,
                          least_seen=_LEAP_MIN_DETECTION) is not None:
            return leap
    return None


def _seen_agreeing(tracks: tuple[SmoothedTrack, ...], recording: Recording,
                   ground: GroundPlane, shifted: CalibConfig, *, least_seen: float = 0.0
                   ) -> HypothesisSelection | None:
    """Stage 6 under ``shifted`` (another clock offset, searched no further) where its
    hypotheses agree and the vehicle is seen where they put it, else None: other road
    users' tracks agree by chance at some offset (seen on a recording whose vehicle never
    came into view), and the vehicle must be seen where that calibration puts it, as for
    every result (``quality.min_vehicle_detection`` of the frames that put it in view, and
    at least ``least_seen`` of them where that is asked; where no frame could be checked,
    nothing contradicts it)."""
    try:
        _, selection = _hypotheses(tracks, recording, ground, shifted, leaps=False)
        seen = quality.check_vehicle_detection(selection.extrinsics, recording, shifted)
    except InsufficientDataError:
        return None
    return None if seen < least_seen else selection


def _check_pose_stream(recording: Recording, config: CalibConfig) -> None:
    """Raise when no radar frame can be paired with a vehicle pose at all, naming why
    (otherwise stage 6 would report a vehicle 'never seen')."""
    sync = config.sync
    stamps = hypotheses.pose_stamps_ns(recording.frame_stamps_ns, sync.time_offset)
    if interpolate_poses(recording.vehicle, stamps, sync.max_pose_gap).valid.any():
        return
    poses = recording.vehicle.stamps_ns
    if stamps[-1] < poses[0] or stamps[0] > poses[-1]:
        raise InsufficientDataError(
            'read', f'the radar frames ({_span(stamps)}, sync.time_offset included) and the '
            f'vehicle poses ({_span(poses)}) do not overlap in time; check the clocks and '
            'sync.time_offset')
    interval = float(np.median(np.diff(poses))) * 1e-9
    # Odometry beside slow fixes gives the heading between them, not the position (a fifth
    # probe's 1 Hz fixes with 50 Hz Odometry were refused without saying what to set;
    # raised to 1.5 s, they gave 8.5 cm)
    odometry = recording.counters.get('odometry', 0)
    beside = (f'; the {odometry} Odometry samples give the heading between the fixes, and '
              f'sync.max_pose_gap {1.5 * interval:.1f} s would interpolate the positions '
              'linearly between them (fine while the vehicle drives steadily)'
              if odometry > 2 * len(poses) else '')
    raise InsufficientDataError(
        'read', f'the vehicle poses come every {interval:.2f} s (median), more than '
        f'sync.max_pose_gap {sync.max_pose_gap:g} s, so no radar frame can be paired with a '
        'pose: record the poses faster or, for straight steady driving, raise '
        f'sync.max_pose_gap{beside}')


#: Moving time of the vehicle while the radar recorded below which a failure of stage 6 is
#: said to be the drive's [s]: three passes through a view take more.
_SHORT_DRIVE_S = 20.0


def _lattice_note(recording: Recording) -> str | None:
    """The fixes' latitudes and longitudes on a lattice (``vehicle_track._lattice_m``),
    with what it costs, else None."""
    counters = recording.counters
    if 'fix_lattice_east_mm' not in counters:
        return None
    steps = [f'{counters[key] / 1000.0:.2f} m {way}'
             for key, way in (('fix_lattice_east_mm', 'east'),
                              ('fix_lattice_north_mm', 'north')) if counters[key]]
    sigma_m = counters.get('fix_lattice_sigma_mm', 0) / 1000.0
    cost = (f'with no Odometry to carry the motion between them, each fix is off by up to '
            f'half a step and the course over ground wobbles with them: the uncertainty counts '
            f'{_length(sigma_m)} for it'
            if sigma_m else
            'the Odometry\'s twist and yaw carry the motion between them, but each fix is '
            'off by up to half a step')
    return (f'The fixes\' latitudes and longitudes lie on a lattice, {" and ".join(steps)} '
            'apart (32-bit floats or rounded decimals on the way, from the receiver to the '
            f'bag?): {cost}. NavSatFix latitude and longitude are 64-bit floats; record them '
            'as such.')


def _short_drive_note(recording: Recording, config: CalibConfig) -> str | None:
    """Where stage 6 failed on a drive too short for three passes: the cause in the user's
    words (a probe's parked car and one-pass recording read 'hypotheses do not agree' and a
    sparse-radar retry, not that the vehicle hardly drove)."""
    vehicle = recording.vehicle
    stamps = hypotheses.pose_stamps_ns(recording.frame_stamps_ns[[0, -1]],
                                       config.sync.time_offset)
    during = (vehicle.stamps_ns >= stamps[0]) & (vehicle.stamps_ns <= stamps[1])
    if during.sum() < 2:
        return None
    t = vehicle.stamps_ns[during] * 1e-9
    speed = np.hypot(vehicle.velocities_mps[during, 0], vehicle.velocities_mps[during, 1])
    dt = np.diff(t)
    moving = speed[1:] >= hypotheses.TRACKABLE_SPEED_MPS
    moving_s = float(dt[moving].sum())
    if moving_s >= _SHORT_DRIVE_S:
        return None
    driven = float((speed[1:] * dt)[moving].sum())
    crept = float((speed[1:] * dt)[~moving].sum())
    if crept >= _CREPT_M and crept >= driven:
        # it did drive, below the speed its targets are tracked at: 'hardly moved' or
        # 'record a longer drive' sent a sixty-fourth probe's queue (207 m driven, 27 m of
        # it at 1 m/s or more) and car-park crawl (157 m) off to the wrong remedy
        return (f'The calibration vehicle crept {crept:.0f} m below '
                f'{hypotheses.TRACKABLE_SPEED_MPS:g} m/s while the radar recorded, and drove '
                f'only {driven:.0f} m faster: its targets are tracked from that speed on. '
                f'Drive it through the view at {2 * hypotheses.TRACKABLE_SPEED_MPS:g} m/s or '
                f'more, at least {config.hypotheses.min_passes} times, on different lanes and '
                'in both directions.')
    if moving_s < 1.0:
        return (f'The calibration vehicle hardly moved while the radar recorded ({driven:.0f} m'
                f' at 1 m/s or more in {t[-1] - t[0]:.0f} s): drive it through the view, at '
                f'least {config.hypotheses.min_passes} times, on different lanes and in both '
                'directions.')
    return (f'The calibration vehicle drove only {driven:.0f} m in {moving_s:.0f} s while the '
            f'radar recorded: {config.hypotheses.min_passes} passes through the view take '
            'more; record a longer drive.')


#: Distance crept below the tracked speed that the short-drive note names instead [m].
_CREPT_M = 20.0


#: Radar frames outside the pose stream worth a note (share), and a jump of the radar's
#: stamps worth naming [s].
_OUTSIDE_POSES_SHARE = 0.05
_CLOCK_JUMP_S = 10.0
#: Radar stamps off the poses' as received, after sync.time_offset, worth a note [s]
#: (transport latencies are milliseconds to a few hundred).
_RECEIPT_NOTE_S = 1.0


#: How near the fitted clock offset must lie to minus the fixes' lag for the radar to be
#: taken as on the fixes' clock: at least [s], or this share of the lag.
_LATE_AGREE_S = 0.03
_LATE_AGREE_SHARE = 0.2


def _odometry_late_note(recording: Recording, fitted_offset_s: float) -> str | None:
    """The note for fixes found to lag the Odometry by L (``vehicle_track._fix_lag``) when the
    fitted clock offset is -L, not 0: the radar is on the fixes' clock, so it is rather the
    Odometry that runs late (a ninth probe's Odometry stamped 0.3-1 s late was reported
    as late fixes and a radar clock offset beyond its bound), else None."""
    lag_s = recording.counters.get('fix_lag_ms', 0) / 1000.0
    # Both are measured to milliseconds: -L within a few tens of them, not a tenth of a
    # second (a sixteenth probe's radar 150 ms late beside fixes 55 ms late was said to be
    # on the fixes' clock).
    agree_s = max(_LATE_AGREE_S, _LATE_AGREE_SHARE * abs(lag_s))
    if not (abs(fitted_offset_s + lag_s) <= agree_s and abs(fitted_offset_s) > _SHIFT_CONFIRMED_S):
        return None
    late_ms = -1000.0 * lag_s
    # (seconds: a stream offset, ``fix_stream_offset_ds``, of GPS against UTC time)
    late = f'{abs(late_ms):.0f} ms' if abs(late_ms) < 1000.0 else f'{abs(lag_s):.1f} s'
    how = (f'lag both by {late} (seen where the vehicle turned or changed speed): '
           'most likely the Odometry is stamped late (at output, on a clock of its own, or '
           'in another time scale: GPS and UTC differ by 18 s)'
           if late_ms > 0 else
           f'run {late} ahead of both (seen where the vehicle turned or changed '
           'speed): the Odometry stamped early, or the fixes and the radar both stamped late '
           '(at output, or in another time scale: GPS and UTC differ by 18 s)')
    return (f'The radar\'s stamps agree with the NavSatFix\'s as stamped, and the '
            f'Odometry\'s {how}. The poses were put on the '
            f'Odometry\'s clock, so the clock offset reported ({fitted_offset_s:+.3f} s) is the '
            'radar\'s against the Odometry\'s stamps. Check how each is stamped.')


def _degraded_fixes_note(recording: Recording) -> str | None:
    """A note where RTK fixes that had lost the solution were left out, else None."""
    counters = recording.counters
    dropped, fixes = counters.get('fixes_degraded_dropped', 0), counters.get('fixes', 0)
    if not dropped or not fixes or recording.fix_grade != 'rtk':
        return None
    stretches = counters.get('fixes_unaugmented_stretches', 0)
    longest_s = counters.get('fixes_unaugmented_longest_ms', 0) / 1000.0
    where = (f'; standalone (NavSatFix status 0) in {stretches} stretch'
             f'{"es" if stretches != 1 else ""}, the longest {longest_s:.0f} s'
             if counters.get('fixes_unaugmented', 0) else '')
    return (f'{dropped} of the vehicle\'s {fixes} fixes ({100 * dropped / fixes:.0f} %) '
            'had lost the RTK solution (status 0 or 1, or a declared accuracy far below '
            f'the rest){where}: those poses, decimetres to metres off, were left out '
            'with the radar frames they would have placed. Check the correction link, or '
            'drive those passes again.')


#: A failure names the fixes left out for a lost RTK solution from this share of them: the
#: passes driven then are gone (a seventy-second probe's 58 % of float fixes, flagged
#: honestly, left three passes and the failure said the vehicle was never in view).
_DEGRADED_FAILURE_SHARE = 0.1


def _passes_lost_to_float(recording: Recording) -> bool:
    """Whether RTK fixes were left out for a lost solution, ``_DEGRADED_FAILURE_SHARE`` of
    them or more (``_degraded_fixes_note``)."""
    counters = recording.counters
    dropped = counters.get('fixes_degraded_dropped', 0)
    return (recording.fix_grade == 'rtk' and dropped > 0
            and dropped >= _DEGRADED_FAILURE_SHARE * counters.get('fixes', 0))


def _fix_grade_failure_note(recording: Recording) -> list[str]:
    """For a failure: the vehicle's fixes are not RTK, named with their error, which moves
    every pass's track of the vehicle by that much (a probe's standalone-GNSS drive failed
    with 'no consistent track' alone, as if the radar or the drives were at fault); or
    RTK fixes, a share of which were left out for a lost solution."""
    grade = recording.fix_grade
    if grade == 'rtk':
        degraded = _degraded_fixes_note(recording) if _passes_lost_to_float(recording) else None
        return [] if degraded is None else [degraded]
    if not recording.counters.get('fixes'):
        return []
    what = 'standalone GNSS (NavSatFix status 0)' if grade == 'standalone' else (
        'SBAS, DGPS or RTK float (NavSatFix status 1)')
    return [f'The vehicle\'s fixes are {what}, about {_length(recording.pose_sigma_m[0])} '
            '(1 sigma) horizontally: errors that move each pass\'s track of the vehicle '
            'apart by as much, so the passes seldom agree and no result could be better '
            'than that. Calibrate with an RTK fix.']


#: Below this vehicle.ref_height [m] the pose point is an axle's or the ground's, not a
#: roof antenna's (a car's roof is 1.4-1.6 m up).
_ANTENNA_MIN_HEIGHT_M = 1.0


#: 1-sigma [m] of the height above vehicle.ref_height of fixes seen off the Odometry's
#: point (``fix_lever_arm_*``) where ref_height is an axle's: a roof antenna lies 1.0-1.3 m
#: above one (a seventy-second probe's 1.1 m: the radar 0.9-1.1 m high at 2.4-2.8 sigma).
_LEVER_ARM_HEIGHT_SIGMA_M = 0.75


def _lever_arm_height_sigma_m(recording: Recording, vehicle: VehicleConfig) -> float:
    """How uncertain the height of the fixes' point above the road is beyond
    vehicle.ref_height [m]: ``_LEVER_ARM_HEIGHT_SIGMA_M`` where the fixes describe a point
    off the Odometry's (a lever arm) and ref_height is below an antenna's, else 0."""
    if (recording.counters.get('fix_lever_arm_forward_cm') is None
            or vehicle.ref_height >= _ANTENNA_MIN_HEIGHT_M):
        return 0.0
    return _LEVER_ARM_HEIGHT_SIGMA_M


def _antenna_height_note(recording: Recording, config: CalibConfig) -> str | None:
    """A note where the fixes' header frame_id names a GNSS antenna ('gnss', 'gps_link')
    while vehicle.ref_height puts the pose point below any roof, else None.

    Why: the radar's altitude rests one to one on the height of the point the poses
    describe, which nothing in the data shows: a fifty-first probe's roof-antenna fixes
    (frame 'gnss') with a rear axle's ref_height put the radar 1.1 m high at a reported
    0.35 m, with nothing said. The frame's name is the one hint the data hold."""
    # (the fixes place the vehicle wherever there are any, in the node as offline)
    if (not recording.counters.get('fix_frame_antenna')
            or config.vehicle.ref_height >= _ANTENNA_MIN_HEIGHT_M):
        return None
    return ('The vehicle\'s fixes name a GNSS antenna\'s frame (header.frame_id), yet '
            f'vehicle.ref_height puts the point they describe {config.vehicle.ref_height:.2f} '
            'm above the road, an axle\'s height: the radar\'s altitude rests on it one to '
            'one. If the fixes are the antenna\'s position (not moved to the vehicle\'s '
            'reference point by the receiver), set vehicle.ref_height to the antenna\'s '
            'height above the road (a roof antenna: about 1.5 m) and rear_overhang to its '
            'distance ahead of the rear bumper.')


#: Targets a frame (on average) from which an imaging radar's are worth thinning.
_DENSE_TARGETS_PER_FRAME = 1500


def _dense_radar_note(recording: Recording, config: CalibConfig) -> str | None:
    """A note where the radar gave more than ``_DENSE_TARGETS_PER_FRAME`` targets a frame
    and ``radar.max_targets_per_frame`` kept them all, else None.

    Why: clustering grows with the square of the targets on each road user; a fifty-fifth
    probe's imaging radar (2,300 a frame, 10-13 minutes) took 153-278 s at 2.9-3.7 GB, and
    35-51 s at 1 GB with the setting at 400, as accurate, which nothing in the output
    named."""
    frames = recording.counters.get('radar_frames', 0)
    if config.radar.max_targets_per_frame or not frames:
        return None
    per_frame = recording.counters.get('targets', 0) / frames
    if per_frame < _DENSE_TARGETS_PER_FRAME:
        return None
    return (f'The radar gave {per_frame:.0f} targets a frame (an imaging radar\'s), and every '
            'one was calibrated with: time and memory grow with them (clustering with the '
            'square of the targets on each road user). radar.max_targets_per_frame: 400 '
            'keeps that many of each frame, evenly over its list (an independent probe\'s '
            '2,300 a frame: 35-51 s and 1 GB instead of 153-278 s and 3-3.7 GB, as '
            'accurate).')


def _clock_notes(recording: Recording, config: CalibConfig) -> list[str]:
    """Notes on the radar's clock: its stamps far off the poses' or jumping against the
    recorder's clock (counters of ``clocks.receipt_checks``, bags only), and radar
    frames outside the pose stream (``_outside_poses_notes``)."""
    notes = []
    counters = recording.counters
    offset_ms = counters.get('radar_stamp_offset_ms')
    jump_ms = counters.get('radar_stamp_jump_ms')
    # with a jump, the offset is a blend of before and after: the jump is the news; an
    # offset that sync.time_offset already takes out is no news either
    left_s = (offset_ms or 0) / 1000 + config.sync.time_offset
    # nor one that puts the radar on the fixes' clock where those were seconds off the
    # Odometry's and moved onto it: the stage-6 shift finds that, and the late-Odometry
    # note says it (``_odometry_late_note``)
    on_fix_clock = (counters.get('fix_stream_offset_ds') is not None and offset_ms is not None
                    and abs(offset_ms - counters.get('fix_lag_ms', 0)) <= 1000 * _RECEIPT_NOTE_S)
    if (offset_ms is not None and jump_ms is None and abs(left_s) > _RECEIPT_NOTE_S
            and not on_fix_clock):
        setting = (f'; sync.time_offset ({config.sync.time_offset:g} s) leaves {left_s:+.1f} s'
                   if config.sync.time_offset else '')
        notes.append(f'As the recording received them, the radar\'s header stamps are '
                     f'{abs(offset_ms) / 1000:.1f} s {"ahead of" if offset_ms > 0 else "behind"} '
                     f'the vehicle\'s{setting}: if their clocks differ (GPS, UTC or TAI time, '
                     'or no time sync), set sync.time_offset to about '
                     f'{-offset_ms / 1000:.1f}.')
    rejoined = counters.get('radar_stamps_rejoined', 0)
    if jump_ms is not None:
        digits = 1 if abs(jump_ms) >= 1000 else 2
        at_s = counters.get('radar_stamp_jump_at_ms', 0) / 1000
        said = (f'The radar\'s header stamps jump by {jump_ms / 1000:+.{digits}f} s against '
                f'the recording\'s clock {at_s:.0f} s after its first message')
        if rejoined:
            side = ('after' if counters.get('radar_stamps_rejoined_later') else 'before')
            other = 'before' if side == 'after' else 'after'
            notes.append(f'{said} (a radar that rebooted, or a clock that lost its sync): the '
                         f'{rejoined} frames {side} the jump were moved by it onto the clock '
                         f'{other} it (the one nearer the vehicle\'s), so that one clock offset '
                         'holds throughout. Check the radar\'s time sync.')
        elif counters.get('radar_stamp_rejoin_tried'):
            notes.append(f'{said}: the calibration was also run with the frames on one side '
                         'moved by it onto the other\'s clock, and no more passes agreed so; '
                         'the stamps were kept as recorded (a transport delay that settled '
                         'higher, rather than the radar\'s clock?).')
        else:
            notes.append(f'{said} (a clock that lost its sync?): the frames on one side of the '
                         'jump are paired with the wrong poses or none.')
    return notes + _outside_poses_notes(recording, config, name_jump=jump_ms is None)


#: Least share of the radar frames before the vehicle's poses, and after them, for the
#: frames outside to be a longer recording than the drive rather than a clock's fault.
_OUTSIDE_POSES_SIDE_SHARE = 0.02


def _outside_poses_notes(recording: Recording, config: CalibConfig,
                         name_jump: bool = True) -> list[str]:
    """A note when a good share of the radar frames lies outside the vehicle's pose stream
    in time, with the largest gap in the radar's stamps (unless ``name_jump`` is False: the
    recorder's clock has named the jump already): a radar clock that jumped (a lost time
    sync, a reboot) leaves those frames without a pose, and without this note the drives
    they held would only be called unused."""
    stamps = hypotheses.pose_stamps_ns(recording.frame_stamps_ns, config.sync.time_offset)
    poses = recording.vehicle.stamps_ns
    before, after = stamps < poses[0], stamps > poses[-1]
    outside = before | after
    if outside.mean() <= _OUTSIDE_POSES_SHARE:
        return []
    note = (f'{int(outside.sum())} of the {stamps.size} radar frames '
            f'({100 * outside.mean():.0f} %) lie outside the vehicle\'s pose stream in time '
            f'({_span(poses)}) and were not used')
    gaps = np.diff(stamps) * 1e-9
    jumped = bool(gaps.size and gaps.max() > _CLOCK_JUMP_S)
    if min(before.mean(), after.mean()) >= _OUTSIDE_POSES_SIDE_SHARE and not jumped:
        # frames on both sides and no jump: a roadside recording that runs before and after
        # the calibration drive, the ordinary case (a fiftieth probe's 28-46 min recordings
        # were told to check the radar's time synchronisation, their clocks 1 ms apart)
        return [note + f' ({100 * before.mean():.0f} % before the vehicle\'s first pose, '
                f'{100 * after.mean():.0f} % after its last): the recording runs longer than '
                'the vehicle\'s drive, which is as it should be where the radar records all '
                'day.']
    if name_jump and jumped:
        k = int(np.argmax(gaps))
        note += (f'; the radar\'s stamps jump by {gaps[k]:.1f} s after '
                 f'{stamps[k] * 1e-9:.3f} s (a clock that lost its sync?)')
    dropped = sum(recording.counters.get(key, 0) for key in (
        'fixes_silent_float_dropped', 'odometry_silent_float_dropped', 'fixes_degraded_dropped'))
    if dropped:
        # the tool's own cut of the pose stream, not the radar's clock (a thirty-third
        # probe: frames outside the fixes taken for RTK float were blamed on time sync)
        return [note + ': the poses left out above (RTK float or a lost solution) took '
                'them along. Only if the vehicle\'s recording itself ends before the radar\'s, '
                'check the radar\'s time synchronisation and sync.time_offset.']
    return [note + '. Check the radar\'s time synchronisation and sync.time_offset.']


def _span(stamps_ns: np.ndarray) -> str:
    return f'{stamps_ns[0] * 1e-9:.3f}-{stamps_ns[-1] * 1e-9:.3f} s'


def _length(metres: float) -> str:
    """'2 cm' below a decimetre, '0.6 m' above."""
    return f'{100 * metres:.0f} cm' if metres < 0.1 else f'{metres:.1f} m'


def _dropped(count: int, noun: str, what: Callable[[int], str], done: str) -> str:
    """'3 radar messages <what> and were <done>.', or '' for none."""
    if not count:
        return ''
    plural = count != 1
    return (f'{count} {noun}{"s" if plural else ""} {what(count)} and '
            f'{"were" if plural else "was"} {done}.')


#: A horizontal 1-sigma [m] no RTK fix declares: from it on, the fixes' covariance or
#: their status is wrong (RTK fixed declares 1-5 cm, float a decimetre or two).
_IMPLAUSIBLE_RTK_SIGMA_M = 0.5


#: An Odometry heading offset taken off is named from this size [centidegrees].
_HEADING_OFFSET_NOTE_CDEG = 30


#: A stretch [s] with no radar frame and no vehicle pose at once, inside the recording,
#: from which it is named.
_HOLE_S = 20.0


def _recording_hole_note(recording: Recording) -> str | None:
    """A note on the longest stretch in which neither the radar nor the vehicle's poses
    have anything, where it is ``_HOLE_S`` or more: a recorder stopped and started again
    (a fiftieth probe's 90 s went unsaid; a pass lost in it is then no mystery)."""
    frames = recording.frame_stamps_ns
    poses = recording.vehicle.stamps_ns
    if frames.size < 2 or poses.size < 2:
        return None
    both = np.union1d(frames, poses[(poses > frames[0]) & (poses < frames[-1])])
    gaps = np.diff(both) * 1e-9
    k = int(np.argmax(gaps))
    if gaps[k] < _HOLE_S:
        return None
    start = (both[k] - frames[0]) * 1e-9
    return (f'Neither the radar nor the vehicle\'s poses have anything for {gaps[k]:.0f} s, '
            f'from {start:.0f} s to {start + gaps[k]:.0f} s into the recording (a recorder '
            'stopped and started again?): a pass driven then is not in the data.')


#: Within this of the paper's tilt error [deg], a road plane that tilts in the world by
#: as much as that error is the road itself on a slope, not clutter.
_SLOPE_MATCH_DEG = 1.0


def _plane_tilt_deg(normal_sensor: F64, rotation: F64) -> float:
    """How far the plane of stage 4 (its normal in the sensor frame) tilts from level in
    the world under ``rotation`` [deg]."""
    up = np.asarray(rotation, float) @ np.asarray(normal_sensor, float)
    return math.degrees(math.acos(min(abs(float(up[2])) / float(np.linalg.norm(up)), 1.0)))


#: Horizontal reach [m] from the radar within which the vehicle's own climb is compared with
#: stage 4's plane (``_road_follows_plane``), the travel [m] over which a grade is taken,
#: and the fewest such stretches that tell.
_SLOPE_REACH_M = 80.0
_SLOPE_STRETCH_M = 5.0
_SLOPE_MIN_STRETCHES = 20


def _road_follows_plane(normal_sensor: F64, rotation: F64, sensor_xy_m: F64,
                        recording: Recording) -> bool | None:
    """Whether the vehicle climbs, where it drove near the radar, as stage 4's plane (its
    normal in the sensor frame, in the world under ``rotation``) slopes along its travel,
    within ``_SLOPE_MATCH_DEG``; None where it drove too little there to tell.

    Why: under the final fit stage 4's plane tilts in the world by about as much as the
    paper's tilt was off, whatever tilted it, so that alone cannot tell a sloped road from
    clutter: a seventieth probe's flat roads in rain (the plane 4.3-7.9 deg off) were told
    they sloped 8-14 %. The vehicle's RTK altitude measures the road's grade itself."""
    up = np.asarray(rotation, float) @ np.asarray(normal_sensor, float)
    if abs(float(up[2])) < 1e-6:
        return None
    vehicle = recording.vehicle
    xy = vehicle.positions_m[:, :2]
    s = hypotheses.travelled_m(vehicle)
    near = np.flatnonzero(np.hypot(*(xy - np.asarray(sensor_xy_m, float)[:2]).T)
                          <= _SLOPE_REACH_M)
    ahead = np.searchsorted(s, s[near] + _SLOPE_STRETCH_M)
    keep = ahead < s.size
    start, end = near[keep], ahead[keep]
    step = xy[end] - xy[start]
    run = np.hypot(step[:, 0], step[:, 1])
    # a stretch driven, not jumped (a hole in the poses) nor crawled round a corner
    ok = (run >= 0.8 * _SLOPE_STRETCH_M) & (run <= 1.5 * _SLOPE_STRETCH_M)
    tilt = float(np.hypot(up[0], up[1]))
    direction = step / np.maximum(run, 1e-9)[:, None]
    # only stretches driven within 60 deg of the way the plane slopes show its slope: along
    # one road it may tilt about the road, across which the vehicle never climbs
    ok &= np.abs(direction @ (up[:2] / max(tilt, 1e-12))) >= 0.5
    if int(ok.sum()) < _SLOPE_MIN_STRETCHES:
        return None
    climb = (vehicle.positions_m[end[ok], 2] - vehicle.positions_m[start[ok], 2]) / run[ok]
    plane_climb = -(direction[ok] @ up[:2]) / float(up[2])
    return bool(np.median(np.abs(plane_climb - climb))
                <= math.tan(math.radians(_SLOPE_MATCH_DEG)))


def _plane_moved_note(plane: dict[str, float], road_tilt_deg: float, clutter: bool,
                      sloped: bool | None = None) -> str:
    """What the final fit moving the paper's tilt and height says: their ground plane was
    not the road's (clutter), or, where the vehicle climbs as that plane slopes
    (``sloped``, ``_road_follows_plane``; where that cannot tell: the plane lies as tilted
    in the world as their tilt was off), the road itself is not level, which the paper's
    stages take it to be.

    Why: a fifty-second probe's junction on a 6-7 % slope was told in 6 of 6 runs that the
    ground plane 'was not the road's', tilt 3.1-3.7 deg off; it was the road's, sloped."""
    lower = 'lower' if plane['vertical_m'] > 0 else 'higher'
    off = (f'The paper\'s stages had the radar\'s tilt {plane["tilt_deg"]:.1f} deg off and '
           f'the radar {abs(plane["vertical_m"]):.1f} m {lower} than the final fit puts it: ')
    if sloped is None and abs(road_tilt_deg - plane['tilt_deg']) <= _SLOPE_MATCH_DEG:
        return (off + 'either their ground plane (stage 4) was not the road\'s'
                + (' (the clutter named above)' if clutter else '')
                + f', or the road in view is not level (that plane tilts {road_tilt_deg:.1f} '
                'deg by the final fit) across the way the vehicle drove, where its own climb '
                'cannot show which. The tilt and the height are the final fit\'s, from the '
                'vehicle\'s own targets.')
    if sloped:
        return (off + f'the road in view is not level (its plane, stage 4, tilts '
                f'{road_tilt_deg:.1f} deg, a {100 * math.tan(math.radians(road_tilt_deg)):.0f} '
                '% slope, by the final fit), and those stages take the road for level. The '
                'tilt and the height are the final fit\'s, from the vehicle\'s own targets '
                'and its RTK altitude.')
    return (off + 'their ground plane (stage 4) was not the road\'s'
            + (' (the clutter named above)' if clutter else '')
            + '. The tilt and the height are the final fit\'s, from the vehicle\'s own '
            'targets.')


def _planar_note(constant_mdeg: int | None, radar: RadarConfig) -> str:
    """What a 2-D radar's result rests on: its tilt as measured at the mount, or held
    level (``refine._with_mount_tilt``)."""
    if constant_mdeg is not None:
        seen = (f'The radar reports every target at one elevation ({constant_mdeg / 1000:.2f} '
                'deg): it measures none (a 2-D radar, its driver writing a fixed value), and '
                'its targets were taken as in its own plane.')
    else:
        seen = 'The radar reports no elevation (z = 0 for every target: a 2-D radar).'
    altitude = 'its altitude comes only from the radial velocities (decimetres)'
    if radar.mount_tilt_sigma_deg > 0.0:
        return (f'{seen} Its roll and pitch are those measured at the mount '
                f'(radar.mount_roll_deg {radar.mount_roll_deg:+.2f}, mount_pitch_deg '
                f'{radar.mount_pitch_deg:+.2f}, 1 sigma {radar.mount_tilt_sigma_deg:.2f} deg, '
                f'which joins the position\'s uncertainty); {altitude}.')
    return (f'{seen} Its roll and pitch cannot be measured from its targets and are reported '
            'level, with an uncertainty of degrees that also widens the position\'s; '
            f'{altitude}. Measure the tilt at the mount and enter it as radar.mount_roll_deg, '
            'radar.mount_pitch_deg and radar.mount_tilt_sigma_deg.')


def _data_notes(recording: Recording, corrections: list[str],
                fitted_offset_s: float | None = None,
                radar: RadarConfig = RadarConfig(),
                vehicle: VehicleConfig | None = None) -> list[str]:
    """What the calibration had to work around in the data, for the user to fix at the
    source: ``corrections`` made on the way (a flipped radial-velocity sign, folded
    velocities), an Odometry twist that did not describe the vehicle's motion (or its
    speed), a radar without elevation, standalone GNSS fixes. ``fitted_offset_s``, the
    final fit's clock offset, tells late fixes from a late Odometry; ``radar`` says
    whether a tilt was measured at the mount."""
    notes = list(corrections)
    zone = zone_note(recording.frame)
    if zone is not None:
        notes.append(zone)
    hole = _recording_hole_note(recording)
    if hole is not None:
        notes.append(hole)
    turns = recording.counters.get('mount_turns', 0)
    if turns:
        words = hypotheses.turn_words(recording.counters.get('mount_turn_cdeg', 0) / 100,
                                      recording.counters.get('mount_turn_tilt_cdeg', 0) / 100)
        more = f' (the last of {turns} turns)' if turns > 1 else ''
        notes.append(
            f'The radar\'s mount turned {words}{more} about '
            f'{recording.counters.get("mount_turn_at_s", 0)} s into the recording: the '
            f'{recording.counters.get("mount_turn_passes_before", 0)} vehicle passes before it '
            'agree with each other, not with those after. The calibration is of the mount '
            'after the turn, from the data after it '
            f'({recording.counters.get("mount_turn_frames_left_out", 0)} radar frames before '
            'it left out). Re-aimed on purpose? Then this is the one to use; if not, check '
            'the bracket.')
    lattice = _lattice_note(recording)
    if lattice is not None:
        notes.append(lattice)
    glitches = recording.counters.get('odometry_twist_glitches', 0)
    if glitches:
        notes.append(f'{glitches} Odometry messages carry a twist beyond {TWIST_MAX_MPS:g} m/s '
                     f'({3.6 * TWIST_MAX_MPS:g} km/h), '
                     'which no road vehicle drives: left out. Check the driver that '
                     'publishes the Odometry.')
    apart_s = recording.counters.get('odometry_other_clock_s')
    if apart_s is not None:
        notes.append(f'The Odometry\'s header stamps lie {abs(apart_s)} s '
                     f'{"after" if apart_s > 0 else "before"} the NavSatFix\'s and never '
                     'overlap them: it runs on a clock of its own (a node without '
                     'use_sim_time beside a simulator, or not synchronised?). It was left out '
                     'and the heading taken from the course over ground; stamp the Odometry '
                     'on the fixes\' clock.')
    restarts = recording.counters.get('stamps_restarted', 0)
    if restarts:
        back_s = recording.counters.get('stamps_restart_back_ms', 0) / 1000.0
        at_s = recording.counters.get('stamps_restart_at_s', 0)
        more = f' (and {restarts - 1} more time(s))' if restarts > 1 else ''
        notes.append(f'The header stamps of every stream fell back by {back_s:.1f} s at once, '
                     f'{at_s} s into the recording{more}: a simulator restarted, or recordings '
                     'joined? Each part was calibrated on its own stamps, the later placed '
                     'after the earlier; record each run on its own to be sure.')
    unset = recording.counters.get('radar_stamps_unset', 0)
    if unset:
        total = unset + recording.counters.get('radar_frames', 0)
        notes.append(f'{unset} of the radar\'s {total} messages carry no header stamp (0) and '
                     'were left out: the calibration times messages by their header stamps, '
                     'never by their receipt. Have the driver stamp each scan with its '
                     'measurement time.')
    splined = recording.counters.get('poses_splined_between_fixes', 0)
    if splined:
        # said, not warned: the spline follows 14 m turns at 10 m/s to about 4 cm, yet the
        # rate is the user's to choose, and the fixes' noise shows in every sample between
        interval_s = recording.counters.get('fix_interval_ms', 0) / 1000.0
        notes.append(f'The fixes come every {interval_s:.2f} s with no Odometry: between them '
                     f'the vehicle\'s path was taken on a cubic spline through them '
                     f'({splined} poses added; a straight line between 1 s fixes cuts a tight '
                     'turn by up to a metre, the spline by a few centimetres). Fixes at 5-20 '
                     'Hz, or the INS\'s Odometry beside them, carry fast turns better.')
    if recording.counters.get('odometry_twist_replaced'):
        notes.append('The Odometry twist did not describe the vehicle\'s motion (zero, or in '
                     'another frame): the velocity was taken from the positions. Check the '
                     'driver: REP-105 puts the twist in child_frame_id.')
    if recording.counters.get('odometry_orientation_compass'):
        notes.append('The Odometry orientation is a compass heading (clockwise from north); it '
                     'was read so. REP-103 asks for yaw counter-clockwise from east (ENU).')
    if recording.counters.get('odometry_orientation_replaced'):
        notes.append('The Odometry orientation did not describe the vehicle\'s travel (identity, '
                     'or another frame\'s): the heading was taken from the course over '
                     'ground. Check the driver\'s orientation.')
    offset_cdeg = recording.counters.get('odometry_heading_offset_cdeg', 0)
    convergence = math.degrees(float(np.ravel(recording.frame.utm_convergence_rad(
        recording.frame.lat0_deg, recording.frame.lon0_deg))[0]))
    grid = bool(offset_cdeg) and heading_offset_is_grid(offset_cdeg / 100, convergence)
    # a few tenths are taken off silently: a good INS is aligned to about that; a grid
    # heading is named at any size, as the driver is what to fix
    if grid or abs(offset_cdeg) >= _HEADING_OFFSET_NOTE_CDEG:
        if grid:
            # a probe's, and two generators', yaw against the UTM grid's north was blamed on
            # a turned INS: the offset is the site's meridian convergence (a seventy-fourth
            # probe's INS turned by 0.7-0.8 deg where that is 0.7 was told only the grid)
            notes.append(f'The Odometry heading is {offset_cdeg / 100:+.2f} deg off the '
                         'vehicle\'s course over ground throughout, the meridian convergence '
                         f'here ({abs(convergence):.2f} deg): its yaw is most likely against '
                         'the UTM grid\'s north rather than true north (REP-103\'s ENU, as the '
                         'contract has it), or the INS is mounted turned by as much (the data '
                         'cannot tell the two apart). It was taken off; have the INS driver '
                         'give the yaw against true north, or check its yaw alignment.')
        else:
            notes.append(f'The Odometry heading is {offset_cdeg / 100:+.1f} deg off the '
                         'vehicle\'s course over ground throughout (an INS mounted turned, or '
                         'the heading of its own frame rather than the vehicle\'s): it was '
                         'taken off. Check the INS yaw alignment.')
    wander_cdeg = recording.counters.get('odometry_heading_wander_cdeg')
    settled_s = recording.counters.get('odometry_heading_settled_s')
    if wander_cdeg and settled_s:
        notes.append(f'The Odometry heading was {wander_cdeg / 100:.1f} deg off the vehicle\'s '
                     f'course over ground on its first straight stretch and settled within '
                     f'about {settled_s} s (an INS still aligning its heading after start-up?): '
                     'the course over ground on straight stretches corrected it, '
                     'interpolated between. Start recording once the INS has converged.')
    elif wander_cdeg:
        notes.append(f'The Odometry heading wanders from the vehicle\'s course over ground, by up '
                     f'to {wander_cdeg / 100:.1f} deg over the drive (an INS holding its heading '
                     'by its gyro between manoeuvres, without a second antenna?): the course '
                     'over ground on straight stretches corrected it, interpolated between. '
                     'Check the INS heading aiding.')
    reversed_runs = recording.counters.get('vehicle_reversed_stretches', 0)
    if reversed_runs:
        ambiguous = recording.counters.get('vehicle_reversed_ambiguous', 0)
        how = (' (where it drove as far backwards as forwards, the slower way was taken as '
               'backwards)' if ambiguous else '')
        notes.append(f'The vehicle reversed {reversed_runs} time'
                     f'{"s" if reversed_runs != 1 else ""} '
                     f'({recording.counters.get("vehicle_reversed_m", 0)} m): told by its course '
                     'turning round at a standstill, with no Odometry orientation to say which '
                     f'way it faced{how}; there it was taken to face against its travel. '
                     'Record the INS Odometry, or drive forwards through the view.')
    if recording.counters.get('radar_frames_velocity_components'):
        notes.append('The radar\'s clouds carry velocity components (vx, vy: an object list?) '
                     'rather than a radial velocity: the radial velocity was taken as their '
                     'projection on each target\'s line of sight. An object list\'s points '
                     'are where its tracker puts each object, not where the radar saw it: '
                     'record the radar\'s detections where it offers them.')
    constant_mdeg = recording.counters.get('radar_elevation_constant_mdeg')
    if not recording.has_elevation:
        notes.append(_planar_note(constant_mdeg, radar))
    elif radar.mount_tilt_sigma_deg > 0.0:
        notes.append('radar.mount_roll_deg and mount_pitch_deg were not used: this radar '
                     'measures elevation, and its targets and the road plane give its roll '
                     'and pitch (compare the result with them).')
    fixes = recording.counters.get('fixes', 0)
    # shares among the fixes the track rests on (degraded ones left out are not)
    used, standalone, sbas = recording.fix_status_counts
    if used and sbas > 0.5 * used:
        h, v = recording.pose_sigma_m
        notes.append(f'{100 * sbas / used:.0f} % of the vehicle\'s fixes are SBAS, DGPS or RTK '
                     'float (NavSatFix status 1, not RTK fixed): decimetres to a metre, which '
                     'pass into the radar\'s position one to one; the reported uncertainty '
                     f'takes at least '
                     f'{_length(h)} horizontal and {_length(v)} vertical for them, whatever '
                     'they declare. Calibrate with an RTK fix.')
    elif recording.fix_status_unreported:
        assert recording.fix_sigma_m is not None
        notes.append('Every fix of the vehicle says NavSatFix status 0 (STATUS_FIX: no RTK, '
                     f'SBAS or GBAS), yet they declare {_length(recording.fix_sigma_m[0])} '
                     'horizontal (1 sigma), RTK\'s accuracy: taken as an RTK receiver whose '
                     'driver leaves the status at its default, and that accuracy joins the '
                     'uncertainty. If the fixes really are standalone GNSS, the position is '
                     'off by metres and its uncertainty does not show it; have the driver '
                     'report RTK as status 2 (STATUS_GBAS_FIX).')
    elif used and standalone > 0.5 * used:
        h, v = recording.pose_sigma_m
        said = ('they declare no covariance' if recording.fix_sigma_m is None else
                f'they declare {recording.fix_sigma_m[0]:.2f} m horizontal and '
                f'{recording.fix_sigma_m[1]:.2f} m vertical (1 sigma)')
        declared = (f'{said}; the reported uncertainty takes {h:.1f} m horizontal and '
                    f'{v:.1f} m vertical for them')
        notes.append(f'{100 * standalone / used:.0f} % of the vehicle\'s fixes are standalone '
                     'GNSS (NavSatFix status 0: no RTK, SBAS or GBAS); their error passes '
                     f'into the radar\'s position one to one, and {declared}. Calibrate with '
                     'an RTK fix.')
    shared = recording.counters.get('fixes_stamp_shared', 0)
    if shared >= max(10, 0.01 * fixes):
        notes.append(f'{shared} of the vehicle\'s {fixes} fixes share their header stamp with '
                     'an earlier fix at another position (a receiver faster than the '
                     'resolution of its stamps, 0.1 s?): the first received of each stamp was '
                     'kept, the others left out. Stamp each fix with its own epoch, to the '
                     'millisecond.')
    stale = recording.counters.get('fixes_stale_dropped', 0)
    if stale >= max(10, 0.05 * fixes):
        notes.append(f'{stale} of the vehicle\'s {fixes} fixes repeated the position before '
                     'them under a new stamp (a receiver slower than its driver publishes, its '
                     'last position sent again): the copies were left out. Set the driver\'s '
                     'rate to the receiver\'s, or the receiver\'s to the driver\'s.')
    declared = recording.fix_sigma_m
    if (used and recording.fix_grade == 'rtk' and standalone <= 0.5 * used
            and declared is not None and declared[0] >= _IMPLAUSIBLE_RTK_SIGMA_M):
        notes.append('The vehicle\'s fixes report RTK (NavSatFix status 2) but declare '
                     f'{_length(declared[0])} horizontal and {_length(declared[1])} vertical '
                     '(1 sigma), far from an RTK fix\'s centimetres: a covariance written in '
                     'cm^2 instead of m^2, a receiver\'s conservative placeholder '
                     '(covariance type APPROXIMATED), or RTK float or DGPS reported as status 2? '
                     'The reported uncertainty takes the declared value as it stands; if the '
                     'fixes are RTK fixed, correct the driver\'s covariance and calibrate again.')
    jitter_ms = recording.counters.get('fix_stamp_jitter_ms')
    if jitter_ms:
        along_cm = recording.counters.get('fix_stamp_jitter_cm', 0)
        notes.append(f'The vehicle\'s fixes scatter by {along_cm} cm (1 sigma) along their '
                     'travel from a smooth path, and hardly at all across it: their stamps '
                     f'vary by about {jitter_ms} ms, as when a driver stamps each fix on '
                     'arrival rather than at the receiver\'s epoch. The fixes were smoothed '
                     'along their path, up to a second either side (what is left adds '
                     'centimetres along the travel). Stamp the fixes with the receiver\'s time '
                     '(e.g. nmea_navsat_driver\'s use_GNSS_time) and calibrate again.')
    c = recording.counters
    jumps = c.get('fix_jumps', 0)
    if jumps or c.get('silent_float_by_noise'):
        # silent RTK float, found by its jumps or by its noise alone (``_fix_steps``)
        odometry = bool(c.get('fix_jumps_in_odometry')) or 'odometry_silent_float_dropped' in c
        source, pose, poses = (('Odometry positions', 'pose', 'poses') if odometry
                               else ('fixes', 'fix', 'fixes'))
        total = c.get('odometry', 0) if odometry else fixes
        dropped = c.get('odometry_silent_float_dropped' if odometry
                        else 'fixes_silent_float_dropped', 0)
        share = f'{dropped} {poses} ({100 * dropped / max(total, 1):.0f} %)'
        said = f'{"the pose" if odometry else "the status and the"} covariance still said'
        fix = ('Have the INS report the GNSS solution it rests on (its pose covariance), and '
               'check the correction link.' if odometry else
               'Have the GNSS driver report RTK float in the fixes\' covariance (decimetres, '
               'not RTK fixed\'s centimetres) or as a status below GBAS_FIX (2; NavSatFix '
               'has no RTK float of its own, and drivers map it differently), and check the '
               'correction link.')
        if jumps:
            sizes = (f'{c["fix_jump_median_cm"]}-{c["fix_jump_max_cm"]} cm'
                     if c['fix_jump_median_cm'] != c['fix_jump_max_cm'] else
                     f'{c["fix_jump_max_cm"]} cm')
            when = (f'between {c["fix_jumps_first_s"]} and {c["fix_jumps_last_s"]} s'
                    if jumps > 1 else f'at {c["fix_jumps_first_s"]} s')
            smooth = ('the Odometry\'s twist' if c.get('odometry', 0)
                      and not c.get('odometry_twist_replaced') else 'its path')
            which = ('where they scattered by centimetres more than elsewhere, as RTK float does'
                     if c.get('silent_float_by_noise') else
                     'between the jumps, the shorter share of the drive')
            what = (f'{share} {which}, were taken as float and left out with the radar frames '
                    'they would have placed'
                    if dropped else
                    'which stretches are float is not clear (they would be much of the drive), so '
                    f'every {pose} was kept and the reported uncertainty takes half a jump as '
                    f'the {poses}\' error')
            notes.append(f'The vehicle\'s {source} jump {jumps} time{"s" if jumps > 1 else ""} '
                         f'by {sizes} ({when}, {poses}\' time) where {smooth} shows smooth '
                         f'motion: an RTK fix lost for RTK float and regained, while {said} RTK '
                         f'fixed? {what[0].upper()}{what[1:]}. {fix}')
        else:
            when = (f'between {c["fix_noisy_first_s"]} and {c["fix_noisy_last_s"]} s'
                    if c['fix_noisy_first_s'] != c['fix_noisy_last_s']
                    else f'at {c["fix_noisy_first_s"]} s')
            notes.append(f'The vehicle\'s {source} scattered by centimetres more than '
                         f'elsewhere for seconds at a time ({when}, {poses}\' time), across the '
                         f'travel and in height, while {said} RTK fixed: RTK float? {share} were '
                         'taken as float and left out with the radar frames they would have '
                         f'placed. {fix}')
    degraded = _degraded_fixes_note(recording)
    if degraded is not None:
        notes.append(degraded)
    lag_ms = recording.counters.get('fix_lag_ms')
    late = (_odometry_late_note(recording, fitted_offset_s) if fitted_offset_s is not None
            else None)
    if late is not None:
        notes.append(late)
    elif recording.counters.get('fix_stream_offset_ds'):
        notes.append(f'The NavSatFix stamps lie {lag_ms / 1000:+.1f} s from the Odometry\'s '
                     '(seen in the vehicle\'s stops and starts): the fixes were put on the '
                     'Odometry\'s clock, and the radar\'s clock offset is reported against '
                     'it. A whole number of seconds is most often one stream in GPS time and '
                     'the other in UTC (18 s apart): check how the GNSS driver stamps its '
                     'fixes.')
    elif lag_ms:
        notes.append(f'The NavSatFix stamps lag the Odometry\'s by {lag_ms} ms (seen where the '
                     'vehicle turned or changed speed): each fix was taken at its stamp minus '
                     'that. Check how the GNSS driver stamps its fixes (at the epoch, not at '
                     'output).')
    counters = recording.counters
    forward_cm = counters.get('fix_lever_arm_forward_cm')
    if forward_cm is not None:
        left_cm = counters.get('fix_lever_arm_left_cm', 0)
        seen = (f'The NavSatFix positions describe a point {abs(forward_cm) / 100:.2f} m '
                f'{"ahead of" if forward_cm >= 0 else "behind"} and {abs(left_cm) / 100:.2f} '
                f'm {"left" if left_cm >= 0 else "right"} of the Odometry\'s (seen in every '
                'turn: a GNSS antenna\'s lever arm?). The calibration places the vehicle '
                'by the fixes (the Odometry\'s twist moved to their point), so vehicle.* '
                'must describe the box around the fixes\' point '
                '(overhangs from it, vehicle.ref_height its height above the road)')
        if vehicle is not None and _lever_arm_height_sigma_m(recording, vehicle) == 0.0:
            # the parameters already put that point at an antenna's height: said as done
            # (a seventy-second probe, having moved them there, was told the same 'fix the
            # parameters' and could not tell the fix had worked)
            notes.append(f'{seen}: vehicle.ref_height ({vehicle.ref_height:.2f} m) puts it at '
                         'an antenna\'s height, as that needs; check that rear_overhang is '
                         'measured to it too.')
        else:
            notes.append(f'{seen}; drawn around the Odometry\'s point, the radar\'s altitude '
                         'is off by the antenna\'s height (and its position by up to the lever '
                         'arm), which the data cannot show: the altitude\'s uncertainty '
                         f'includes {_LEVER_ARM_HEIGHT_SIGMA_M:g} m (1 sigma) for it. Fix the '
                         'parameters, or publish the fixes at the reference point, and '
                         'calibrate again.')
    odometry = max(counters.get('odometry', 0), 1)
    notes += [_dropped(counters.get('radar_messages_malformed', 0), 'radar message',
                       lambda n: 'could not be decoded (truncated, malformed, or without a '
                       'field the others have: the first one\'s reason was logged)',
                       'skipped; check the driver'),
              _dropped(counters.get('odometry_invalid', 0), 'Odometry message',
                       lambda n: f'({100 * n / odometry:.0f} %) had no usable pose (a NaN, or a '
                       'quaternion far from unit length: an INS still aligning writes zeros)',
                       'left out; where no other pose covers them, the radar frames there '
                       'wait for a later pass'),
              _dropped(counters.get('fixes_no_fix', 0), 'NavSatFix message',
                       lambda n: 'reported no fix (status -1: a receiver without a solution, '
                       'starting up or in an outage under a bridge or in a tunnel)',
                       'left out; the radar frames there have no pose'),
              _dropped(counters.get('fixes_invalid', 0), 'NavSatFix message',
                       lambda n: 'had no usable position (NaN, latitude / longitude out of '
                       'range, or 0 / 0: a receiver without a solution yet)', 'left out'),
              _dropped(counters.get('targets_at_origin', 0), 'radar target',
                       lambda n: 'lay at exactly (0, 0, 0), the radar\'s own antenna,',
                       'dropped (a driver that pads a fixed-size target list with zeros?)'),
              _dropped(counters.get('radar_messages_duplicate', 0), 'radar message',
                       lambda n: 'repeated an earlier one exactly (same stamp, same targets: '
                       'the topic recorded twice?)', 'dropped')]
    notes = [n for n in notes if n]
    whole = recording.counters.get('radar_scans_shared_stamp', 0)
    if whole:
        by_receipt = recording.counters.get('radar_scans_shared_stamp_by_receipt', 0)
        how = ('by when they were received' if by_receipt == whole else
               f'{recording.counters.get("radar_scan_interval_ms", 0)} ms apart (the radar\'s '
               'scan interval), back from the stamp' if not by_receipt else
               'by when they were received where that told them apart, else at the radar\'s '
               'scan interval')
        notes.append(f'{whole} radar messages shared their header stamp with another, though '
                     'each held a whole scan (their moving targets lay further along their '
                     'radial velocities than in the message before): a driver that '
                     'stamps a batch of scans with the time it publishes them, or re-uses a '
                     f'stale stamp? They were timed {how}; the fitted clock offset takes the '
                     'rest. Have the driver stamp each scan with its own measurement time.')
    merged = recording.counters.get('radar_messages_merged', 0)
    if merged:
        notes.append(f'{merged} radar messages shared their header stamp with another and were '
                     'taken as parts of one scan (a driver that publishes a scan in pieces).')
    permille = recording.counters.get('odometry_speed_scale_permille')
    if permille:
        # with vehicle.odom_is_utm and no fixes, the Odometry's own positions
        source = 'fixes' if recording.counters.get('fixes') else 'Odometry\'s positions'
        notes.append(f'The Odometry twist speed is {-permille / 10:.1f} % off the speed of the '
                     f'{source} on straight driving and was rescaled to them (1 % would tilt the '
                     'fitted pitch by about half a degree); check the odometry\'s scale.')
    if recording.counters.get('odometry_twist_kmh'):
        notes.append('The Odometry twist is 3.6 times the vehicle\'s speed: it is in km/h, not '
                     'the m/s REP-103 asks for, and was read so. Check the driver\'s units.')
    if recording.counters.get('odometry_twist_in_parent_frame'):
        notes.append('The Odometry twist is in the parent (ENU) frame and was read so; REP-105 '
                     'puts it in child_frame_id.')
    return notes


def run_calibration(recording: Recording, config: CalibConfig, *,
                    progress: ProgressFn | None = None) -> CalibrationResult:
    """Calibrate the radar of a recording.

    Raises
    ------
    InsufficientDataError
        The data cannot be calibrated (vehicle never seen, too few passes, hypotheses that
        do not agree); the message says which and with what numbers, and what the clocks
        showed (radar stamps seconds off the poses' as received, a jump, frames outside
        the poses): a failure is where that matters most.
    """
    try:
        # Every stage multiplies tall, skinny arrays (millions of targets by 3 columns):
        # multi-threaded BLAS only spins on them, the more so on a busy machine. Placing a
        # dense radar's 9.6 million targets in the world took 1.4 s a time with two
        # threads and 0.2 s with one (the quality stage does it three times); one thread
        # gives the very same numbers.
        with threadpool_limits(limits=1, user_api='blas'):
            return _calibration_clock_rejoined(recording, _scaled_to_vehicle(config),
                                               progress)
    except InsufficientDataError as err:
        notes = _clock_notes(recording, config) + _fix_grade_failure_note(recording)
        fast = fast_vehicle_config(recording, _scaled_to_vehicle(config))
        if fast is not None:
            # the vehicle's own travel a frame breaks its tracks, whatever else is said
            notes.append(f'{fast[1]}. At that travel its tracks may still break up: where '
                         'it drove that fast through the view, drive slower there, or record '
                         'the radar at a higher frame rate.')
        if 'set sync.time_offset to' in err.reason:
            # the stages found the offset that makes the passes agree: the clock notes would
            # say it twice more (a probe read the 18 s three times in one error)
            notes = [n for n in notes if 'sync.time_offset' not in n]
        if type(err) is not InsufficientDataError or not notes:
            raise
        raise InsufficientDataError(err.stage, ' '.join((err.reason.rstrip('.') + '.',
                                                         *notes))) from err


def _calibration_clock_rejoined(recording: Recording, config: CalibConfig,
                                progress: ProgressFn | None) -> CalibrationResult:
    """The calibration of the recording, or of it with the radar stamps of one side of a
    small clock step rejoined (``Recording.radar_clock_rejoin_ns``) where that lets more
    passes agree.

    Why: a step of the radar's clock under a second (an NTP correction) is not rejoined
    when the recording is built, since from the receipts alone it looks like a transport
    latency that settled higher. With one clock offset for both sides, the paper's stages
    agree on the passes of one side only (a sixteenth probe's +0.15 s step: 9 of 17
    passes, a drift of -91 ppm named; an eighth probe's -0.5 s: 3 of 6, 0.36 m off). The
    calibration is run both ways and the one on more passes kept: a clock that stepped
    gains the other side's passes when rejoined, a latency loses them.
    """
    failure: InsufficientDataError | None = None
    rejoined = _rejoined_clock(recording)
    if rejoined is not None:
        # (its notes, if it is kept, say that the other way was tried)
        recording = replace(recording, counters={**recording.counters,
                                                 'radar_stamp_rejoin_tried': 1})
    try:
        result: CalibrationResult | None = _calibration_of_current_mount(recording, config,
                                                                         progress)
    except InsufficientDataError as err:
        result, failure = None, err
    if rejoined is not None:
        try:
            other = _calibration_of_current_mount(rejoined, config, progress)
        except InsufficientDataError:
            other = None
        if other is not None and (result is None or _passes(other) > _passes(result)):
            _LOG.warning('with the radar stamps rejoined across the step of its clock, %d '
                         'passes agree (%s as stamped): kept', _passes(other),
                         'none' if result is None else _passes(result))
            return other
    if result is None:
        assert failure is not None
        raise failure
    return result


def _calibration_of_current_mount(recording: Recording, config: CalibConfig,
                                  progress: ProgressFn | None) -> CalibrationResult:
    """The calibration of the radar as it is mounted at the end of the recording.

    Why: a mount turned during the recording (re-aimed, a bracket that slipped) gives two
    calibrations, and averaging them is neither (a thirteenth probe's +3 deg mid-drive: yaw
    between the two, 1.5 m off). Where stage 6 (``hypotheses.mount_turn``) or the final
    fit (``refine``, where the drives' halves disagree) finds the turn, the data before it
    are left out and the calibration starts again: the mount as it is now is the one a
    user calibrates for. Too few passes after the turn is a failure that says so, not a
    calibration of a mount that no longer exists.
    """
    turns: list[str] = []
    while True:
        try:
            return _run_calibration(recording, config, progress)
        except _MountTurned as turned:
            turn = turned.turn
            # in words before the cut, while its time counts from the recording's start
            turns.append(hypotheses.mount_turn_text(turn, recording))
            _LOG.warning('%s Calibrating the data after it.', turns[-1])
            if turn.at_ns <= int(recording.frame_stamps_ns[0]):
                # nothing to leave out (cannot happen between two groups of passes; a
                # guard against calibrating the same data again and again)
                raise InsufficientDataError('hypotheses', f'{turns[-1]} No data before it '
                                            'to leave out.')
            recording = _frames_from(recording, turn.at_ns)
            recording.counters.update(
                mount_turns=len(turns), mount_turn_cdeg=int(round(turn.yaw_change_deg * 100)),
                mount_turn_tilt_cdeg=int(round(turn.tilt_change_deg * 100)),
                mount_turn_passes_before=turn.passes_before)
        except InsufficientDataError as err:
            if not turns:
                raise
            raise type(err)(err.stage, (
                f'{turns[-1]} The data after it were calibrated on their own and '
                f'failed: {err.reason.rstrip(".")}. Drive more passes through the view (the '
                'mount as it is now) and calibrate again.')) from err


def _frames_from(recording: Recording, start_ns: int) -> Recording:
    """The recording's radar frames from ``start_ns`` on (poses kept whole), with counters
    that say where it was cut and by how much."""
    first = int(np.searchsorted(recording.frame_stamps_ns, start_ns))
    targets = recording.targets.subset(recording.targets.frame_index >= first)
    targets = Targets(targets.positions_m, targets.radial_velocity_mps,
                      targets.frame_index - first)
    shift = recording.radar_clock_rejoin_ns
    counters = dict(recording.counters)
    counters['mount_turn_frames_left_out'] = (
        counters.get('mount_turn_frames_left_out', 0) + first)
    counters['mount_turn_at_s'] = (
        counters.get('mount_turn_at_s', 0)
        + int(round((start_ns - int(recording.frame_stamps_ns[0])) * 1e-9)))
    return replace(recording, frame_stamps_ns=recording.frame_stamps_ns[first:],
                   targets=targets, counters=counters,
                   radar_clock_rejoin_ns=None if shift is None else shift[first:])


def _passes(result: CalibrationResult) -> int:
    """Passes on which the paper's stages agree (the final fit takes every pass the result
    places the vehicle in, agreeing or not)."""
    return result.selection.n_passes


def _rejoined_clock(recording: Recording) -> Recording | None:
    """The recording with ``radar_clock_rejoin_ns`` added to its frames' stamps (frames and
    targets sorted again: the two sides may interleave by milliseconds), else None."""
    shift = recording.radar_clock_rejoin_ns
    if shift is None:
        return None
    stamps = recording.frame_stamps_ns + shift
    order = np.argsort(stamps, kind='stable')
    rank = np.empty_like(order)
    rank[order] = np.arange(order.size)
    targets = recording.targets
    new_index = rank[targets.frame_index]
    by_frame = np.argsort(new_index, kind='stable')
    return replace(
        recording, frame_stamps_ns=stamps[order],
        targets=Targets(targets.positions_m[by_frame], targets.radial_velocity_mps[by_frame],
                        new_index[by_frame]),
        radar_clock_rejoin_ns=None, counters={
            **recording.counters, 'radar_stamps_rejoined': int(np.count_nonzero(shift)),
            'radar_stamps_rejoined_later': int(shift[-1] != 0)})


def _stages_4_to_6(recording: Recording, tracked: TrackedTargets, config: CalibConfig,
                   stage: _StageClock, *, leaps: bool = True,
                   tracks_out: list[tuple[GroundPlane, tuple[SmoothedTrack, ...]]] | None = None
                   ) -> tuple[GroundPlane, str | None, tuple[SmoothedTrack, ...],
                              list[Hypothesis], HypothesisSelection]:
    """Ground plane, tracking and hypotheses: the ground plane with its clutter note, the
    smoothed tracks, the hypotheses and the accepted selection (``leaps``: see
    ``_hypotheses``). ``tracks_out`` gets the ground plane and the tracks as soon as they
    are made, for what a failure of stage 6 says (``_never_in_view_lead``)."""
    with stage('ground_plane'):
        ground, clutter_note = _ground_plane(recording, tracked, config)
    with stage('track'):
        tracks = tuple(track.track_clusters(recording, tracked, ground, config.track))
    if tracks_out is not None:
        tracks_out.append((ground, tracks))
    with stage('hypotheses'):
        hyps, selection = _hypotheses(tracks, recording, ground, config, leaps=leaps,
                                      tracked=tracked)
    if selection.rivals:
        distance, passes = selection.rivals[0]
        groups = (f'two groups of tracks each agree across passes ({selection.n_passes} and '
                  f'{passes}) but place the radar {distance:.0f} m apart')
        # A clock offset beyond the search shifts the passes driven one way and those
        # driven the other apart along the road, each way agreeing within itself: a
        # fiftieth probe's pose stamps 0.4-0.5 s off the radar's were taken for a convoy
        # in 11 of 14 drives, and the user sent to drive again.
        beyond = (_beyond_offset(tracks, recording, ground, config,
                                 least_passes=selection.n_passes + passes)
                  if leaps and config.sync.estimate_time_offset else None)
        if beyond is not None:
            raise InsufficientDataError('hypotheses', (
                f'{groups}, and agree as one with the radar stamps shifted by {beyond:+.2f} '
                f's, beyond sync.max_time_offset ({config.sync.max_time_offset:g} s): the '
                'radar\'s and the vehicle\'s clocks are that far apart (the passes driven '
                'one way and those driven the other part by twice the speed times the '
                f'offset). Set sync.time_offset to {config.sync.time_offset + beyond:.2f} (or '
                'sync.max_time_offset to '
                f'{math.ceil(abs(beyond) / _CLOCK_STEP_S) * _CLOCK_STEP_S + 0.1:.2f}) and '
                'calibrate again'))
        raise InsufficientDataError('hypotheses', (
            f'{groups}: another vehicle of the '
            'calibration vehicle\'s size kept pace with it through the view (a convoy, or a '
            'car alongside), and which group is the calibration vehicle the data cannot '
            'tell. Drive the passes with no vehicle of its size keeping pace with it (ahead, '
            'behind or alongside)'))
    if selection.mount_turn is not None:
        raise _MountTurned(selection.mount_turn)
    return ground, clutter_note, tracks, hyps, selection


def _stage_6_lead(err: InsufficientDataError,
                  made: list[tuple[GroundPlane, tuple[SmoothedTrack, ...]]],
                  recording: Recording, config: CalibConfig, *,
                  sparse_per_frame: float | None = None) -> str | None:
    """``_never_in_view_lead`` for a failure of stage 6 on the tracks ``_stages_4_to_6``
    made, else None."""
    if err.stage != 'hypotheses' or type(err) is not InsufficientDataError or not made:
        return None
    ground, tracks = made[0]
    return _never_in_view_lead(err.reason, tracks, ground, recording, config,
                               sparse_per_frame=sparse_per_frame)


#: Clock offsets [s] on top of the given one at which the vehicle must have no company
#: either before a failure says it was never in view, and the step between them: radar
#: stamps 0.6 s off (beyond ``sync.max_time_offset``'s search) moved a seen vehicle's
#: hypotheses metres, and it had company on 3 of 5 passes at best, as chance has.
_NEVER_IN_VIEW_CLOCK_S = 1.0
_NEVER_IN_VIEW_CLOCK_STEP_S = 0.25
#: Fewest passes through the view (under the best of the hypotheses) the claim is made on.
_NEVER_IN_VIEW_MIN_PASSES = 3
#: Below this many targets a road user a frame (median in its tracks) the vehicle's tracks
#: cannot keep it company: one track each.
_SPARSE_COMPANY_TARGETS = 2.0


def _never_in_view_lead(reason: str, tracks: tuple[SmoothedTrack, ...], ground: GroundPlane,
                        recording: Recording, config: CalibConfig, *,
                        sparse_per_frame: float | None = None) -> str | None:
    """The sentence that leads a failure (``reason``) where the vehicle was most likely
    never in the radar's view, with what shows it (``hypotheses.view_company``), else None.

    Why: there the failure read as one of agreement ('the cluster of 4 hypotheses over 3
    passes has only 1 that agree') or of radial velocities ('the final refinement ran
    6.1 m and 6.8 deg away'), as other road users' tracks fit stretches of the drive and
    even agree by chance (an operator probe's M2). Said only where no track, taken for the
    vehicle's, has tracks moving with it on most of the passes it then makes through the
    view, at the given clock offset and at others up to ``_NEVER_IN_VIEW_CLOCK_S`` away:
    where the vehicle is seen, its own tracks do at the right one. Not said where the
    reason or the clock notes already name a sync.time_offset to set (checked first, as
    the search costs up to nine hypothesis generations): the vehicle was in view, on
    another clock (``_clock_remedy_named``). ``sparse_per_frame``: the median targets a road
    user a frame, where the sparse radar's settings were tried and failed too.
    """
    if _clock_remedy_named(reason, _clock_notes(recording, config)):
        return None
    if _passes_lost_to_float(recording):
        # a share of the fixes left out for a lost RTK solution took the passes driven then
        # with them: that is said instead (``_fix_grade_failure_note``)
        return None
    steps = int(round(_NEVER_IN_VIEW_CLOCK_S / _NEVER_IN_VIEW_CLOCK_STEP_S))
    first: tuple[int, list[hypotheses.ViewCompany]] | None = None
    for k in [0, *(sign * i for i in range(1, steps + 1) for sign in (1, -1))]:
        shifted = config if k == 0 else replace(config, sync=replace(
            config.sync, time_offset=config.sync.time_offset + k * _NEVER_IN_VIEW_CLOCK_STEP_S))
        hyps = hypotheses.generate_hypotheses(tracks, recording, ground, shifted)
        if k == 0 and not hyps:
            return None  # stage 6 already says 'never seen'
        companies = hypotheses.view_company(hyps, tracks, recording, shifted)
        if hypotheses.vehicle_kept_company(companies) is not False:
            return None
        if first is None:
            first = (len(hyps), companies)
    assert first is not None
    n_hyps, companies = first
    wide = [c for c in companies if c.in_view >= 2]
    # the most passes any of them had company on
    best = max(wide, key=lambda c: (c.met, c.met / c.in_view))
    if max(c.in_view for c in wide) < _NEVER_IN_VIEW_MIN_PASSES:
        # two passes through the view, one of them alone, show nothing: a car creeping at
        # 0.5-1.5 m/s breaks into tracks that keep it no company (a sixty-fourth probe's
        # car park: in view for 240 s, 33 808 of its targets, told 'never in the radar's
        # view' for what was two passes where three are needed); the stages' reason stands
        return None
    no_follower = (f'No track follows the calibration vehicle on most of its passes: of the '
                   f'{n_hyps} tracks that fit a stretch of its drive, none, taken for the '
                   f'vehicle\'s, has tracks moving with it on more than {best.met} of the '
                   f'{best.in_view} passes it then makes through the view.')
    if sparse_per_frame is not None and sparse_per_frame < _SPARSE_COMPANY_TARGETS:
        # With a target or two a road user a frame, each road user is one track: the
        # vehicle's own keep it no company however well the radar sees it (a seventy-first
        # probe's low-resolution radars on straight roads, 97-215 frames of the car a pass,
        # were told it was never in view).
        return (f'{no_follower} With {sparse_per_frame:g} '
                f'target{"" if sparse_per_frame == 1 else "s"} a road user a frame, each is '
                'one track, which keeps no company even where the radar sees it (or the '
                'vehicle was never in the radar\'s view). In detail:')
    travel = _frame_travel(recording)[0]
    if travel > _FRAME_TRAVEL_M:
        # A vehicle that drives metres between frames breaks into short tracks whose
        # hypotheses scatter, so it keeps no company even in view: a forty-fifth probe's
        # highway drive with no other road user at all (22 m/s at 10 Hz) was told its
        # tracks were other road users'. The note on its travel follows the reason.
        return (f'{no_follower} At {travel:.1f} m between radar frames its targets may have '
                'broken into tracks too short to agree (or it was never in the radar\'s '
                'view). In detail:')
    # Tracks that move with it on two passes are what chance gives (our simulator's vehicle
    # far out of range: 2 of 213 tracks' calibrations), and what a vehicle seen on two
    # passes only gives too (a seventy-sixth probe's radars, 2 900 of its targets on 2
    # passes, were told only that it was never in view): both are said.
    need = config.hypotheses.min_passes
    seen = (f' (or it was seen on those {best.met} passes only, fewer than the {need} needed)'
            if 2 <= best.met < need else '')
    return (f'The calibration vehicle was most likely never in the radar\'s view: of the '
            f'{n_hyps} tracks that fit a stretch of its drive, '
            'none, taken for the vehicle\'s, has tracks moving with it (within '
            f'{hypotheses.COMPANY_M:g} m and {hypotheses.COMPANY_MPS:g} m/s) on most of the '
            'passes it then makes through the area the radar\'s moving targets cover (up to '
            f'{best.reach_m:.0f} m from the radar): at best on {best.met} of {best.in_view}, '
            f'nor with the radar stamps shifted by up to +-{_NEVER_IN_VIEW_CLOCK_S:g} s. '
            f'They are other road users\'{seen}; drive the vehicle through the radar\'s view '
            f'{need} times or more (or, if it did drive there, the radar\'s clock is further '
            'off than that: check sync.time_offset). In detail:')


def _clock_remedy_named(reason: str, notes: list[str]) -> bool:
    """Whether a failure's reason (leap seconds found by stage 6) or the clock notes (the
    receipts) name a sync.time_offset to set: then the vehicle was in view on another
    clock, and the never-in-view lead would mislead (an independent sweep: radars stamped
    18 s and 2 s off were told 'most likely never in the radar's view' over the right
    remedy; the lead's own search covers +-1 s only)."""
    return 'set sync.time_offset to' in reason or any('sync.time_offset' in n for n in notes)


class _MountTurned(Exception):
    """Stage 6 or the final fit found the radar's mount turned during the recording
    (``MountTurn``): the calibration starts again on the data after the turn
    (``_calibration_of_current_mount``)."""

    def __init__(self, turn: MountTurn) -> None:
        super().__init__('the mount turned '
                         + hypotheses.turn_words(turn.yaw_change_deg, turn.tilt_change_deg))
        self.turn = turn


def _mirrored_axis(recording: Recording, config: CalibConfig) -> str | None:
    """Which axis of the radar's targets was most likely reversed ('y' or 'z') when stages
    2-6 agree on the vehicle, and the detection check passes, with the cloud mirrored;
    else None. Only on a failure of stage 6.

    Why: a driver that writes a left-handed cloud (azimuths positive to the right, as some
    simulators' native frames) or elevations positive downwards gives a mirror image, which
    no rotation of the mount turns into the scene; stage 6 then failed with other road
    users blamed (a thirteenth probe). Mirrored back, the vehicle's tracks agree at once.
    Reversing y or z is the same mirror up to a roll of 180 deg, so one test serves both,
    and the roll of the mirrored fit tells which is likelier (a radar hung upside down is
    rarer than a reversed elevation).
    """
    positions = recording.targets.positions_m.copy()
    positions[:, 1] *= -1.0
    mirrored = replace(recording, targets=replace(recording.targets, positions_m=positions))
    try:
        *_, selection = _stages_4_to_6(mirrored, track_targets(mirrored, config), config,
                                       _StageClock(), leaps=False)
        quality.check_vehicle_detection(selection.extrinsics, mirrored, config)
    except (InsufficientDataError, _MountTurned):
        return None
    rot = selection.extrinsics.rotation
    return 'z' if abs(math.atan2(rot[2, 1], rot[2, 2])) > math.pi / 2 else 'y'


#: The vehicle's travel between two radar frames [m] beyond which the clustering and the
#: association are fitted to it (``fast_vehicle_config``), what the association gate
#: allows besides that travel [m], and the frames accumulated for clustering then.
_FRAME_TRAVEL_M = 1.5
_GATE_BESIDES_TRAVEL_M = 2.5
_FAST_ACCUMULATE_FRAMES = 2


def _frame_travel(recording: Recording) -> tuple[float, float, float]:
    """How far the vehicle drives between radar frames when fast [m] (0 where it never
    moves), that speed (the 90th percentile while it moves) [m/s] and the frame interval [s]."""
    stamps = recording.frame_stamps_ns
    speed = np.hypot(*recording.vehicle.velocities_mps[:, :2].T)
    moving = speed[speed > 1.0]
    if stamps.size < 2 or moving.size == 0:
        return 0.0, 0.0, 0.0
    frame_s = float(np.median(np.diff(stamps))) * 1e-9
    fast = float(np.percentile(moving, 90.0))
    return fast * frame_s, fast, frame_s


def fast_vehicle_config(recording: Recording, config: CalibConfig
                        ) -> tuple[CalibConfig, str] | None:
    """``config`` with the clustering and association fitted to a vehicle that moves more
    than ``_FRAME_TRAVEL_M`` between radar frames, and a note saying so (one sentence, no
    full stop); None where it does not. calibrate and evaluate track with it alike.

    Why: the paper's clusters accumulate three frames within ``cluster.eps_m`` (2 m), and
    its tracks join cluster centres within ``associate.gate_m`` (3 m) a frame apart. A car
    at 22-28 m/s seen at 10 Hz moves 2.2-2.8 m a frame: its targets in consecutive frames
    fall apart into clusters too small to keep, and the tracks break; a forty-fifth probe's
    highway drives with no other traffic at all were refused as 'never in the radar's
    view' (3 of 6 at 22 m/s, 3 of 3 at 28 m/s), and calibrated with two frames accumulated
    and a gate of the travel plus 2.5 m. Fast is the 90th percentile of the vehicle's
    speed while it moves; only ever a wider gate and fewer frames than ``config``'s.
    """
    travel, fast, frame_s = _frame_travel(recording)
    if not travel > _FRAME_TRAVEL_M:
        return None
    settings = {'cluster.accumulate_frames': min(config.cluster.accumulate_frames,
                                                 _FAST_ACCUMULATE_FRAMES),
                'associate.gate_m': max(config.associate.gate_m,
                                        float(math.ceil(travel + _GATE_BESIDES_TRAVEL_M)))}
    # a value the user changed from its default is kept as given (as stage 6's thresholds
    # for a long vehicle, ``_scaled_to_vehicle``): where these do not suit the radar, a
    # user who set another is not overruled
    defaults = CalibConfig()
    settings = {name: value for name, value in settings.items()
                if config.get(name) == defaults.get(name)}
    if all(config.get(name) == value for name, value in settings.items()):
        return None
    # (the speed is the whole drive's: where the radar is is not known yet, and a seventy-
    # sixth probe's 28 m/s were on loops between passes, 145 m from every radar)
    note = (f'The vehicle drove {travel:.1f} m between radar frames ({fast:.0f} m/s at '
            f'{1.0 / frame_s:.0f} Hz, over the fastest tenth of the whole drive, in the '
            'radar\'s view or not), further than the paper\'s clustering and tracking '
            f'join: they ran with {_settings_text(settings)}')
    return config.replaced(settings), note


def _run_calibration(recording: Recording, config: CalibConfig,
                     progress: ProgressFn | None) -> CalibrationResult:
    stage = _StageClock(progress)
    targets = recording.targets
    if len(targets) == 0:
        raise InsufficientDataError('moving', 'the recording has no radar target')
    _check_pose_stream(recording, config)
    given = config
    fast = fast_vehicle_config(recording, config)
    sparse_note: str | None = None
    if fast is not None:
        config, sparse_note = fast[0], (f'{fast[1]}. Put them in the parameters file to '
                                        'make them the default for this radar and road.')
        _LOG.info('%s', sparse_note)
    tracked = track_targets(recording, config, clock=stage)
    if tracked.target_index.size == 0:
        raise InsufficientDataError('moving', 'no moving radar target in the recording')
    made: list[tuple[GroundPlane, tuple[SmoothedTrack, ...]]] = []
    try:
        ground, clutter_note, tracks, hyps, selection = _stages_4_to_6(
            recording, tracked, config, stage, tracks_out=made)
    except InsufficientDataError as err:
        again = (_without_fast_settings(recording, given, stage)
                 if fast is not None and err.stage == 'hypotheses' else None)
        if again is None:
            return _after_stage_6_failure(err, recording, tracked, config, stage, progress,
                                          made, sparse_note)
        config, sparse_note = given, None
        tracked, (ground, clutter_note, tracks, hyps, selection) = again
    return _finish(recording, config, stage, progress, tracked, ground, tracks, selection,
                   clutter_note, sparse_note)


def _without_fast_settings(recording: Recording, config: CalibConfig, stage: _StageClock
                           ) -> tuple[TrackedTargets, tuple[GroundPlane, str | None,
                                                            tuple[SmoothedTrack, ...],
                                                            list[Hypothesis],
                                                            HypothesisSelection]] | None:
    """Stages 2-6 again with ``config`` as given, where those fitted to a fast vehicle
    (``fast_vehicle_config``) found no agreement; None where these find none either.

    Why: how fast the vehicle drives is taken over its whole drive, and where it sped
    between its passes out of the radar's view (a seventy-first probe: 28 m/s out of view,
    4-12 m/s in it, at 10 Hz) the clusters of two frames were too small for an object list's
    one target a frame, and six recordings were refused as 'never seen' that calibrate
    with the defaults."""
    try:
        tracked = track_targets(recording, config, clock=stage)
        if tracked.target_index.size == 0:
            return None
        return tracked, _stages_4_to_6(recording, tracked, config, stage)
    except InsufficientDataError:
        return None


def _after_stage_6_failure(err: InsufficientDataError, recording: Recording,
                           tracked: TrackedTargets, config: CalibConfig, stage: _StageClock,
                           progress: ProgressFn | None,
                           made: list[tuple[GroundPlane, tuple[SmoothedTrack, ...]]],
                           sparse_note: str | None) -> CalibrationResult:
    """What follows a failure of stages 4-6: the retries (a sparse radar, the plane of all
    targets) or the failure with its reasons."""
    # A radar with about one target per road user a frame (a traffic radar's cluster
    # list) breaks the paper's clusters of three over three frames into fragments that
    # never make a track, and stage 6 finds nothing to agree on. Its data are not bad:
    # looser clustering and shorter tracks calibrate it (an independent 10 Hz radar with
    # ~1.2 targets on the car: refused with the defaults, 15 cm with these). So on such
    # a failure, and only then, stages 2-6 run again with them, and a note says so.
    stage_6 = err.stage == 'hypotheses' and type(err) is InsufficientDataError
    # said instead of what else was tried, should that fail too
    short = _short_drive_note(recording, config) if stage_6 else None
    short_drive = (None if short is None else
                   InsufficientDataError(err.stage, f'{err.reason.rstrip(".")}. {short}'))
    sparse = _sparse_radar_config(recording, tracked, config) if stage_6 else None
    if sparse is None and short_drive is not None:
        raise short_drive from err
    levels = (_ground_of_all_targets(recording, tracked, config, stage, made)
              if sparse is None and stage_6 else None)
    if levels is not None:
        level_config, (ground, clutter_note, tracks, hyps, selection), note = levels
        return _finish(recording, level_config, stage, progress, tracked, ground, tracks,
                       selection, clutter_note, note)
    if sparse is None:
        mirrored = _mirrored_axis(recording, config) if stage_6 else None
        if mirrored is not None:
            likely = ('the elevations (z) most likely, as the mirrored fit hangs the '
                      'radar upside down' if mirrored == 'z' else
                      'the azimuths (y) most likely')
            raise InsufficientDataError(
                err.stage, f'{err.reason.rstrip(".")}. Mirrored, the radar\'s targets do '
                'follow the vehicle: its point cloud is a mirror image (one axis reversed: '
                f'{likely}), which no mount can produce. Fix the driver\'s axes (REP-103: '
                'x forward, y left, z up) and calibrate again.') from err
        lead = _stage_6_lead(err, made, recording, config)
        if lead is None:
            raise err
        raise InsufficientDataError(err.stage, f'{lead} {err.reason}') from err
    sparse_config, per_frame = sparse
    settings = _settings_text(_sparse_radar_settings(config))
    _LOG.info('stage 6 found no agreement with a median of %g targets per road user a '
              'frame: trying again with %s', per_frame, settings)
    try:
        tracked = track_targets(recording, sparse_config, clock=stage)
        ground, clutter_note, tracks, hyps, selection = _stages_4_to_6(
            recording, tracked, sparse_config, stage)
    except InsufficientDataError as second:
        if short_drive is not None:
            raise short_drive from err
        lead = _stage_6_lead(err, made, recording, config, sparse_per_frame=per_frame)
        raise InsufficientDataError(
            err.stage, ('' if lead is None else f'{lead} ')
            + f'{err.reason.rstrip(".")}. The radar reports few targets per road '
            f'user (a median of {per_frame:g} a frame in its tracks); the settings for '
            f'such a sparse radar ({settings}) were tried as well and failed too '
            f'({second.stage}: {second.reason.rstrip(".")}).') from err
    config = sparse_config
    sparse_note = ' '.join(filter(None, (sparse_note, (
        f'The radar reports few targets per road user (a median of '
        f'{per_frame:g} a frame in its tracks), too few for the paper\'s '
        'clustering and tracking defaults, which found no passes that agree: '
        f'the calibration clustered and tracked with {settings}. Put them in '
        'the parameters file to make them the default for this radar.'))))
    _LOG.info('%s', sparse_note)
    return _finish(recording, config, stage, progress, tracked, ground, tracks, selection,
                   clutter_note, sparse_note)


#: A plane of the moving targets nearer the radar than this [m] may hold a second level of
#: road (a bridge about the radar's height): the radar's mount is higher.
_NEAR_PLANE_M = 3.5


def _ground_of_all_targets(recording: Recording, tracked: TrackedTargets, config: CalibConfig,
                           stage: _StageClock,
                           made: list[tuple[GroundPlane, tuple[SmoothedTrack, ...]]]
                           ) -> tuple[CalibConfig, tuple[Any, ...], str] | None:
    """Stages 4-6 again with the ground plane of every target, where they failed with that
    of the moving ones lying within ``_NEAR_PLANE_M`` of the radar: (that configuration,
    their output, a note), else None.

    Why: roads at two levels in view (a thirty-fourth probe's bridge 6 m up, the radar
    6.5 m up and 40 m from it) give the moving targets no one plane: fitted through both,
    it tilts by degrees and lies a few metres from the radar, stage 6 finds no agreement,
    and the recording was refused as a mirror image (2 of 4 drives). The road's surface
    and what stands on it (every target) hold the lower level: with them the probe's
    refused drives calibrated (9-36 cm beside the bridge; 40 m from it 2.0 and 25.8 cm,
    inside 2 sigma)."""
    if config.ground.targets != 'moving' or not made:
        return None
    near_m = abs(made[-1][0].offset_m)
    if near_m >= _NEAR_PLANE_M:
        return None
    level_config = config.replaced({'ground.targets': 'all'})
    try:
        out = _stages_4_to_6(recording, tracked, level_config, stage)
    except (InsufficientDataError, _MountTurned):
        return None
    note = (f'The plane of the moving targets lay only {near_m:.1f} m from the radar, and '
            'the paper\'s stages found no passes that agree on it: roads at two levels in '
            'view (a bridge about the radar\'s height?). The ground plane was fitted to every '
            'target instead (ground.targets: all), which calibrated; put that in the '
            'parameters file for this radar.')
    _LOG.info('%s', note)
    return level_config, out, note


def _finish(recording: Recording, config: CalibConfig, stage: _StageClock,
            progress: ProgressFn | None, tracked: TrackedTargets, ground: GroundPlane,
            tracks: tuple[SmoothedTrack, ...], selection: HypothesisSelection,
            clutter_note: str | None, retry_note: str | None) -> CalibrationResult:
    """Stages 7 on, with what a failure there says (``_never_in_view_lead``)."""
    try:
        return _stages_7_on(recording, config, stage, progress, tracked, ground, tracks,
                            selection, clutter_note, retry_note)
    except InsufficientDataError as err:
        # the paper's stages agreed, and what followed found no vehicle where they put it:
        # a chance agreement of other road users where the vehicle was never in view (a
        # bench drive far out of range: 'the final refinement ran 6.1 m away')
        lead = _never_in_view_lead(err.reason, tracks, ground, recording, config)
        if lead is None:
            raise
        raise InsufficientDataError(err.stage, f'{lead} {err.reason}') from err


#: Clock offset [s] between the paper's stages and the final fit beyond which, where the
#: position along the boresight is left to the start, stage 7 is run again at the fitted
#: offset (``_start_at_fitted_clock``).
_START_CLOCK_S = 0.02


def _start_at_fitted_clock(refinement: Refinement, selection: HypothesisSelection,
                           recording: Recording, tracked: TrackedTargets,
                           ground: GroundPlane, config: CalibConfig) -> Refinement:
    """The final fit started again from the paper's stage 7 at its own clock offset, where
    the drives leave the position along the boresight to the start and the offset differs
    from the paper's stages' by ``_START_CLOCK_S`` or more; kept where it explains the
    vehicle's targets better (``refine.fits_better``), else ``refinement``.

    Why: the paper's stages place the vehicle in time at their own clock offset, each pass
    by its speed times the error along its drive; where every drive runs towards or away
    from the radar, the final fit finds the clock but cannot move the position along the
    boresight off the start (the reflection depth trades against it). A sixty-eighth
    probe's gantries, radar stamps 80 ms off at 22-30 m/s: the clock found to 1-35 ms, the
    radar 1.8-2.6 m off along the boresight (0.12 m with the offset given). Where the
    fitted clock is the one off, the start it gives is worse, and so is the fit from there
    (five of that probe's drives, 0.05-0.24 m -> 0.11-0.48 m had they been kept): the
    vehicle's targets tell which start to keep."""
    fitted = float(refinement.extrinsics.time_offset_s)
    if (not config.sync.estimate_time_offset or not config.refine.polygon
            or refinement.diagnostics.get('time_offset_held_sigma_s') is not None
            or refinement.diagnostics['sigma_along_boresight_m']
            < uncertainty.OPEN_ALONG_BORESIGHT_M
            or abs(fitted - selection.extrinsics.time_offset_s) < _START_CLOCK_S):
        return refinement
    try:
        start = polygon.bracketed_start(*polygon.refine_polygon_steps(
            replace(selection.extrinsics, time_offset_s=fitted), recording, tracked,
            selection, config))
        again = refine.refine_extrinsics(start, recording, tracked, selection, config,
                                         ground_normal=ground.normal,
                                         plane_sigma_deg=ground.tilt_sigma_deg)
    except InsufficientDataError:
        return refinement
    if not refine.fits_better(again, refinement):
        return refinement
    _LOG.info('stage 7 again at the fitted clock offset %+.3f s (the paper\'s stages at '
              '%+.3f s): the radar moved %.2f m', fitted, selection.extrinsics.time_offset_s,
              float(np.linalg.norm(again.extrinsics.translation_m
                                   - refinement.extrinsics.translation_m)))
    return again


def _stages_7_on(recording: Recording, config: CalibConfig, stage: _StageClock,
                 progress: ProgressFn | None, tracked: TrackedTargets, ground: GroundPlane,
                 tracks: tuple[SmoothedTrack, ...], selection: HypothesisSelection,
                 clutter_note: str | None, retry_note: str | None) -> CalibrationResult:
    """The paper's polygon refinement, our final fit and the quality figures on stage 6's
    selection."""
    targets = recording.targets
    stage_extrinsics = {'hypotheses': selection.extrinsics}
    current = selection.extrinsics
    closest: Extrinsics | None = None
    if config.refine.polygon:
        with stage('polygon'):
            closest, current = polygon.refine_polygon_steps(current, recording, tracked,
                                                            selection, config)
        stage_extrinsics['polygon'] = current
    # The contract's v_r convention is a range rate; where the radar's is the opposite, the
    # paper's stages never noticed (they use |v_r| or compare v_r with v_r) but the final
    # fit and the detection check would be fooled: judge it on the vehicle, flip, and say so.
    # one placing of the vehicle serves both judgements of its radial velocities
    in_view = quality.vehicle_in_view(current, recording, config)
    speed = quality.velocity_is_speed(current, recording, config, in_view)
    if speed is not None:
        raise InsufficientDataError(
            'quality', f'the radar\'s velocities are the vehicle\'s speed, not its radial '
            f'velocity: near the vehicle {speed[1]} targets carry its speed where its motion '
            f'along the line of sight differs, {speed[0]} that motion (an object list whose '
            'velocity is each object\'s speed?). The calibration needs the radial velocity '
            '(the Doppler): record the radar\'s detections, or the objects\' velocity '
            'components vx, vy in the sensor frame (projected onto the line of sight), and '
            'calibrate again')
    factor, n_same, n_other = quality.radial_velocity_convention(current, recording, config,
                                                                 in_view)
    sign = 1.0 if factor > 0 else -1.0
    if factor != 1.0:
        recording = replace(recording, targets=replace(
            targets, radial_velocity_mps=targets.radial_velocity_mps / factor))
        if abs(factor) == 1.0:
            flip_note = (f'The radar reports radial velocities with the opposite sign (approach '
                         f'positive): near the vehicle {n_other} targets match its motion so, '
                         f'{n_same} as a range rate. They were flipped; set '
                         f'radar.velocity_sign to {-config.radar.velocity_sign:g} to say so.')
        else:
            approach = ', approach positive' if sign < 0 else ''
            flip_note = (f'The radar reports radial velocities in km/h{approach}: near the '
                         f'vehicle {n_other} targets match its motion {abs(factor):g} times '
                         f'over, {n_same} in m/s. They were divided by {factor:g}; have the '
                         'driver give m/s' + (f' (or set radar.velocity_sign to '
                                              f'{-config.radar.velocity_sign:g})'
                                              if sign < 0 else '') + '.')
        _LOG.warning('%s', flip_note)
    corrections = [flip_note] if factor != 1.0 else []
    if selection.outfitted is not None:
        corrections.append(_outfitted_note(selection.outfitted, config))
    if retry_note:
        corrections.insert(0, retry_note)
    if clutter_note:
        corrections.insert(0, clutter_note)
    folding = velocity_folding.detect_folding(current, recording, tracked.target_index, config)
    if folding is not None:
        recording, folding = velocity_folding.unfold_radial_velocities(
            recording, current, tracked.target_index, folding, config)
        corrections.append(
            f'The radar\'s radial velocities fold over at +-{folding.period_mps / 2:.1f} m/s '
            f'(an unambiguous interval {folding.period_mps:.1f} m/s wide): near the vehicle '
            f'{folding.n_folded} of {folding.n_near} targets were off its motion by that '
            f'width. {folding.n_unfolded} were unfolded by the vehicle\'s known motion; other '
            'road users\' stay folded.')
        _LOG.warning('%s', corrections[-1])
    refinement: Refinement | None = None
    if config.refine.final:
        with stage('refine'):
            try:
                refinement = refine.refine_extrinsics(current, recording, tracked, selection,
                                                      config, ground_normal=ground.normal,
                                                      plane_sigma_deg=ground.tilt_sigma_deg)
            except refine.Diverged as err:
                # Stage 7 fits the box to the targets nearest the radar, and a long
                # vehicle's nearest are its front or rear face: it misplaced a seventieth
                # probe's 9.5-12 m buses and trucks by up to half their length, from where
                # the fit 'ran off' to the truth and was refused as radial velocities gone
                # wrong (with refine.polygon false: 0.12 m). Such a fit starts again from
                # stage 6's estimate, which places the box by all its tracks' targets.
                if closest is None or not hypotheses.long_vehicle(config):
                    raise
                try:
                    refinement = refine.refine_extrinsics(
                        selection.extrinsics, recording, tracked, selection, config,
                        ground_normal=ground.normal, plane_sigma_deg=ground.tilt_sigma_deg)
                except InsufficientDataError:
                    raise err from None
                _LOG.info('stage 7 misplaced the %.1f m vehicle: the final fit ran %.1f m '
                          'from it, and fitted from stage 6\'s estimate', config.vehicle.length,
                          err.shift_m)
                closest = None
            if (closest is not None and refinement.diagnostics['sigma_along_boresight_m']
                    >= uncertainty.OPEN_ALONG_BORESIGHT_M):
                # The drives leave the position along the boresight to where the fit
                # started (``polygon.bracketed_start``): start where that is least wrong.
                with suppress(InsufficientDataError):
                    refinement = refine.refine_extrinsics(
                        polygon.bracketed_start(closest, current), recording, tracked,
                        selection, config, ground_normal=ground.normal,
                        plane_sigma_deg=ground.tilt_sigma_deg)
                refinement = _start_at_fitted_clock(refinement, selection, recording,
                                                    tracked, ground, config)
            bias = refinement.diagnostics.get('azimuth_bias')
            if refine_noise.significant_azimuth_bias(bias):
                corrected = azimuth_corrected(recording, bias)
                with suppress(InsufficientDataError):
                    again = refine.refine_extrinsics(
                        refinement.extrinsics, corrected, tracked, selection, config,
                        ground_normal=ground.normal, plane_sigma_deg=ground.tilt_sigma_deg)
                    # An azimuth error the targets really have, taken off, brings them
                    # nearer the box: the fit keeps more of them, at a lower cost
                    # (bench recordings turned by 1.5-3 deg at 60 deg: 6614 -> 6655, 4912
                    # -> 4995). Radial velocities off the vehicle's motion for another
                    # reason read as one too: an object list's tracker velocities showed
                    # 2-13 deg, and the corrected fit kept 35-62 % of the targets and
                    # was metres off at exit 0 (a sixty-ninth probe's a25, f166).
                    if refine.fits_better(again, refinement, held_counts=True):
                        refinement = again
                        recording = corrected
                        refinement.diagnostics['azimuth_bias_corrected'] = bias
                        corrections.append(_azimuth_bias_note(bias))
                    else:
                        corrections.append(_azimuth_bias_refuted_note(
                            bias, again.n_targets, refinement.n_targets))
                    _LOG.warning('%s', corrections[-1])
        lever = _lever_arm_height_sigma_m(recording, config.vehicle)
        if lever > 0.0:
            # the fixes' height above the road, which the altitude rests on one to one, is
            # unknown by an antenna's height (the data notes say why)
            covariance = np.array(refinement.covariance, float, copy=True)
            covariance[5, 5] += lever ** 2
            refinement = replace(refinement, covariance=covariance, diagnostics={
                **refinement.diagnostics,
                **uncertainty.sigma_summary(covariance, refinement.extrinsics.rotation)})
        current = refinement.extrinsics
        stage_extrinsics['refine'] = current
        plane = refinement.diagnostics.get('plane_moved')
        # a 2-D radar's plane is its own, level by construction: no stage erred there (a
        # forty-ninth probe's were told their ground plane was not the road's)
        if plane is not None and recording.has_elevation:
            corrections.append(_plane_moved_note(
                plane, _plane_tilt_deg(ground.normal, current.rotation), bool(clutter_note),
                _road_follows_plane(ground.normal, current.rotation,
                                    current.translation_m[:2], recording)))
            _LOG.warning('%s', corrections[-1])
        turn = refinement.diagnostics.get('mount_turn')
        if turn is not None:
            raise _MountTurned(turn)
        held = refinement.diagnostics.get('time_offset_held_sigma_s')
        if held is not None:
            corrections.append(_held_clock_note(held, current.time_offset_s, config))
        max_off = config.sync.max_time_offset
        # an offset beyond the bound that a late Odometry explains is named as that
        # (``_data_notes``), not as poses that could not be placed in time
        if (config.sync.estimate_time_offset and abs(current.time_offset_s) > max_off > 0
                and _odometry_late_note(recording, current.time_offset_s) is None):
            # The bound is a soft prior in the fit: an estimate beyond it means the vehicle
            # could not be placed in time (a fifth probe's 1 Hz fixes: -0.42 s, truth 0).
            if _beyond_search(selection.extrinsics.time_offset_s, current.time_offset_s,
                              max_off):
                # stage 6 agreed best at its limit, in the direction the fit went on: the
                # clocks are further apart than its search (a thirty-fifth probe's radar
                # stamped 0.4-0.5 s late was told 'check vehicle.* before
                # sync.time_offset' and 'fixes below 5 Hz', its fixes at 10 Hz)
                corrections.append(
                    f'The radar\'s stamps are {current.time_offset_s:+.3f} s off the '
                    'vehicle\'s (on top of sync.time_offset), beyond sync.max_time_offset '
                    f'({max_off:g} s): the paper\'s stages agreed best at the limit of their '
                    f'search ({selection.extrinsics.time_offset_s:+.2f} s), as they do when '
                    'the clocks are further apart, and the final fit found the rest. Set '
                    'sync.time_offset to '
                    f'{config.sync.time_offset + current.time_offset_s:.2f} and calibrate '
                    'again, so that every stage works at it.')
            elif _poses_dense(recording):
                # poses at 10 Hz and more place the vehicle in time to milliseconds: a
                # fiftieth probe's 10 Hz fixes and 50 Hz Odometry, clocks 0.4 s apart, were
                # told 'fixes below 5 Hz'
                corrections.append(
                    f'The fitted radar clock offset ({current.time_offset_s:+.3f} s on top of '
                    f'sync.time_offset) lies beyond sync.max_time_offset ({max_off:g} s), with '
                    'poses dense enough to place the vehicle in time: the radar\'s and the '
                    'vehicle\'s clocks are most likely that far apart. Set sync.time_offset to '
                    f'{config.sync.time_offset + current.time_offset_s:.2f} and calibrate '
                    'again, so that every stage works at it.')
            else:
                corrections.append(
                    f'The fitted radar clock offset ({current.time_offset_s:+.3f} s on top of '
                    f'sync.time_offset) lies beyond sync.max_time_offset ({max_off:g} s): the '
                    'vehicle poses may be too sparse or uneven to place it in time (fixes '
                    'below 5 Hz), or the clocks are further apart than that; check the pose '
                    'rate and the clocks before trusting the position along the travel.')
    with stage('quality'):
        detection = quality.check_vehicle_detection(current, recording, config)
        # (one selection of the targets moving with the vehicle for both company checks)
        rigid = quality.rigid_with_the_vehicle(current, recording, config)
        company = quality.company_alongside(current, recording, config, rigid)
        if company is not None:
            raise InsufficientDataError('quality', _company_reason(company))
        in_line = (quality.company_in_line(current, recording, config, rigid)
                   if refinement is not None and config.sync.estimate_time_offset else None)
        if in_line is not None:
            # the clock the fit found is as much the headway's: not one to set
            corrections = [c for c in corrections if 'Set sync.time_offset to' not in c]
            corrections.append(_in_line_note(in_line, config))
        # Said only once the vehicle is found: where it never was (a bench drive far out
        # of range), stage 6 shifted the clocks to make other road users agree, and a
        # warning that blamed vehicle.* came before the failure that names the cause.
        # A shift taken because more passes agreed with it (not because none agreed
        # without) only gathered passes; where the fit does not confirm it, the reflection
        # model's depth did the rest (simulated skin cars: 6 of 8 passes at +0.15 s, 3 as
        # stamped, the fit +1 ms), and no note is owed.
        fitted = (current.time_offset_s if refinement is not None
                  and config.sync.estimate_time_offset else None)
        # a held offset is stage 6's shift, said with the hold (``_held_clock_note``)
        held_shift = (refinement is not None
                      and 'time_offset_held_sigma_s' in refinement.diagnostics)
        beyond = (fitted is not None and _beyond_search(
            selection.extrinsics.time_offset_s, fitted, config.sync.max_time_offset))
        shift_note = (_shift_note(selection.extrinsics.time_offset_s, fitted)
                      if selection.passes_as_stamped < 0 and not held_shift and not beyond
                      else None)
        if shift_note is not None:
            _LOG.warning('%s', shift_note)
            corrections.append(shift_note)
        report = quality.assess_quality(current, refinement, recording, tracked, selection,
                                        config)
        if in_line is not None and math.isfinite(report.sigma_time_offset_s):
            report = replace(report, sigma_time_offset_s=math.hypot(
                report.sigma_time_offset_s, _in_line_clock_sigma_s(in_line, config)))
        report.extra['vehicle_detection_ratio'] = detection
        report.extra['radial_velocity_sign'] = sign * config.radar.velocity_sign
        if abs(factor) != 1.0:
            report.extra['radial_velocity_scale'] = abs(factor)
        if folding is not None:
            report.extra['radial_velocity_fold_period_mps'] = folding.period_mps
        notes = _data_notes(recording, corrections,
                            current.time_offset_s if refinement is not None else None,
                            config.radar, config.vehicle) + _clock_notes(recording, config)
        antenna = _antenna_height_note(recording, config)
        if antenna is not None:
            notes.append(antenna)
        dense = _dense_radar_note(recording, config)
        if dense is not None:
            notes.append(dense)
        if notes:
            # only when there are some: an empty list in result.yaml has no parameter type,
            # and a node declaring its parameters from the file would refuse it
            report.extra['data_notes'] = notes
        report = replace(report, advice=(*notes, *report.advice))
    if progress is not None:
        progress('done', 1.0)
    return CalibrationResult(current, report, recording, tracked, ground, tracks, selection,
                             refinement, stage_extrinsics, stage.times)
