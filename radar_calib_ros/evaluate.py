"""``radar-calib evaluate``: the paper's quality figures of a calibration on a second recording.

The paper's protocol (method-paper.tex, "Data Sources and Evaluation Procedure"): on the
evaluation recording only the object tracking runs (moving targets, clusters, their
association into tracks; no ground plane, no hypotheses, no re-calibration). Each track is
associated with the calibration vehicle by synchronised time and placed in the world by the
calibration under test; tracks whose targets lie more than 5 m from the vehicle on average
belong to other road users and are dropped; the rest are merged into one set of targets on
which r_i, delta_op and delta_p are computed (``radar_calib_ros.metrics``, the same code the
quality stage uses). We add their distribution over target range (a rotation error grows
with range, a translation error does not) and, where the bag directory carries the
simulator's ``ground_truth.json``, the position and rotation errors.

The paper's figures give no verdict, and cannot: a calibration 0.3 m too far along the
boresight or 1 deg off in pitch scores as well as the right one (a thirty-seventh probe), and
altitude and roll leave them unchanged. So the evaluation also fits the radar on this
recording alone (stage 8, started from the calibration under test, the vehicle's tracks as
found above) and compares: the two estimates' difference against the uncertainty of each
says whether the calibration holds here (:func:`check_agreement`).
"""
from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from radar_calib_ros import metrics
from radar_calib_ros.core import quality, refine, refine_covariance, velocity_folding
from radar_calib_ros.config import CalibConfig
from radar_calib_ros.pipeline import (VEHICLE_BOX_PARAMETERS, azimuth_corrected,
                                      fast_vehicle_config, track_targets)
from radar_calib_ros.errors import InsufficientDataError, ResultFileError
from radar_calib_ros.groundtruth import calibration_errors
from radar_calib_ros.io.geo import LocalFrame
from radar_calib_ros.recording import Recording
from radar_calib_ros.result import utm_to_extrinsics
from radar_calib_ros.core.hypotheses import mount_turn_text
from radar_calib_ros.core.refine_noise import AzimuthBias, significant_azimuth_bias
from radar_calib_ros.types import (I64, Extrinsics, HypothesisSelection, MountTurn, Refinement,
                                   TrackedTargets)

#: Edges of the range bins of the evaluation table [m]; targets beyond the last edge get a
#: bin of their own when there are any.
DEFAULT_RANGE_EDGES_M = (0.0, 20.0, 40.0, 60.0, 80.0, 100.0, 150.0)


@dataclass(frozen=True, slots=True)
class RangeBin:
    """The paper's metrics of the targets (r_i, delta_op) and frames (delta_p) in one range
    bin; ``hi_m`` is inf for the open last bin. Metrics are NaN when the bin is empty."""

    lo_m: float
    hi_m: float
    n_targets: int
    inlier_ratio: float
    outlier_distance_m: float
    n_frames: int
    closest_target_offset_m: float


@dataclass(frozen=True, slots=True)
class Evaluation:
    """A calibration evaluated on a recording.

    calibration : the result file's mapping (UTM, contract layout);
    extrinsics : the same calibration in ``recording.frame`` (clock offset relative to
    ``sync.time_offset``, as the pipeline's);
    paper : r_i, delta_op, delta_p and the per-target numbers behind them;
    range_bins : their distribution over range;
    vehicle_track_ids : the tracks associated with the calibration vehicle (merged);
    target_index : their targets, into ``recording.targets``;
    n_tracks : all tracks of the recording;
    errors : ``groundtruth.calibration_errors`` against the simulator's truth, or None;
    recording, tracked : what the figures draw from;
    unlike_fraction : the share of those targets that move unlike the vehicle
    (``metrics.moving_unlike_vehicle``), and ``paper_alike`` the paper's metrics without
    them (None where there are none, or where most do: a radar on another velocity
    convention, whose radial velocities say nothing here).
    """

    calibration: dict[str, Any]
    extrinsics: Extrinsics
    paper: metrics.PaperMetrics
    range_bins: tuple[RangeBin, ...]
    vehicle_track_ids: I64
    target_index: I64
    n_tracks: int
    errors: dict[str, float] | None
    recording: Recording
    tracked: TrackedTargets
    unlike_fraction: float = 0.0
    paper_alike: metrics.PaperMetrics | None = None
    agreement: Agreement | None = None
    notes: tuple[str, ...] = ()


#: What the agreement compares, in the calibration's own axes: the position along and across
#: its horizontal boresight and vertically [m]; the rotation about the horizontal boresight
#: (roll), the horizontal axis left of it (pitch) and the vertical (yaw) [deg].
AGREEMENT_COMPONENTS = ('along_m', 'across_m', 'vertical_m', 'roll_deg', 'pitch_deg',
                        'yaw_deg')
#: Largest difference (in its 1-sigma) of any component at which the calibration holds, and
#: from which it does not: six components compared at once, each within 2 sigma with ~74 %
#: chance where both estimates are right, within 3 with ~98 %. In between it is doubtful.
AGREEMENT_HOLDS_SIGMA = 2.0
AGREEMENT_FAILS_SIGMA = 3.0
#: Passes the fit on the evaluation recording needs before its scatter is judged.
AGREEMENT_MIN_PASSES = 3


@dataclass(frozen=True, slots=True)
class Agreement:
    """The calibration under test against a fit of this recording alone.

    verdict : 'holds', 'doubtful', 'does not hold' or 'cannot tell';
    reason : one sentence on why;
    differences, sigmas : per ``AGREEMENT_COMPONENTS`` the fit here minus the calibration,
    and the 1-sigma of that difference (the fit's and the calibration's uncertainty
    together; empty where the fit failed);
    n_passes : the passes the fit here used;
    time_offset_s : the radar clock offset this recording shows on top of the calibration's
    (recordings of other days may differ: reported, not judged) [s];
    moved : a sentence where the radar moved during this recording (a step in the passes'
    own yaws, or the fit's own halves check), else None;
    fit_sigmas : the fit's own 1-sigma per component, its priors included.
    """

    verdict: str
    reason: str
    differences: dict[str, float] = field(default_factory=dict)
    sigmas: dict[str, float] = field(default_factory=dict)
    n_passes: int = 0
    time_offset_s: float = math.nan
    moved: str | None = None
    fit_sigmas: dict[str, float] = field(default_factory=dict)

    @property
    def headline(self) -> str:
        """The verdict as a few words."""
        if self.verdict == 'cannot tell':
            return 'cannot tell whether the calibration holds on this recording'
        if self.verdict == 'doubtful':
            return 'the calibration is doubtful on this recording'
        return f'the calibration {self.verdict} on this recording'

    @property
    def z(self) -> dict[str, float]:
        """Each difference in its 1-sigma."""
        return {k: abs(v) / self.sigmas[k] if self.sigmas.get(k, 0) > 0 else math.inf
                for k, v in self.differences.items()}


#: Share of the associated targets moving unlike the vehicle from which the evaluation
#: names them and gives the metrics without them, and above which it does not (most of them
#: unlike: the radial velocities follow another convention).
_UNLIKE_NOTE = 0.02
_UNLIKE_TRUSTED = 0.5


def calibration_time_offset_s(calibration: Mapping[str, Any]) -> float:
    """The total radar clock offset a result file carries [s] (0 when it has none).

    Our results hold it in ``quality.time_offset_s``; the combined file of several radars
    (``multi_radar.combined_parameters``) and the simulator's ground truth at the top level.
    """
    for value in ((calibration.get('quality') or {}).get('time_offset_s'),
                  calibration.get('time_offset_s')):
        if (number := _number(value)) is not None:
            return number
    return 0.0


def _number(value: Any) -> float | None:
    """A result file's value as a finite float, None where it is none (missing, null, a
    boolean, text)."""
    if isinstance(value, bool) or not isinstance(value, (int, float)) \
            or not math.isfinite(value):
        return None
    return float(value)


def calibration_extrinsics(calibration: Mapping[str, Any], frame: LocalFrame,
                           config: CalibConfig) -> Extrinsics:
    """A loaded result file (``result.load_result``) as an Extrinsics in a recording's
    local frame.

    The result's EPSG code may differ from the recording's (``world.epsg``): the local frame
    keeps its origin and converts from the result's zone. The result's clock offset is the
    total one; ``Extrinsics.time_offset_s`` is what comes on top of ``sync.time_offset``:
    the fitted part of the total where the result says which part was given
    (``quality.sync_time_offset_s``), else the total less this ``sync.time_offset``.

    Raises
    ------
    ResultFileError
        The rotation is not a rotation.
    """
    epsg = int(calibration['epsg'])
    if epsg != frame.epsg:
        frame = LocalFrame(frame.lat0_deg, frame.lon0_deg, epsg)
    rotation = Rotation.from_quat(np.asarray(calibration['quaternion_xyzw'], float)).as_matrix()
    if not np.all(np.isfinite(rotation)):
        raise ResultFileError("the calibration's quaternion_xyzw is not a rotation")
    # On top of this recording's sync.time_offset: the fitted part of the result's total
    # where the result says which part was given (its own sync.time_offset), so that a
    # recording on another clock is evaluated with its own; older results hold the total
    # only, taken as it is.
    given = _number((calibration.get('quality') or {}).get(
        'sync_time_offset_s', calibration.get('sync_time_offset_s')))
    if given is not None:
        offset = calibration_time_offset_s(calibration) - given
    else:
        offset = calibration_time_offset_s(calibration) - config.sync.time_offset
    return utm_to_extrinsics(rotation, np.asarray(calibration['translation'], float), frame,
                             offset)


def bin_by_range(paper: metrics.PaperMetrics,
                 edges_m: Sequence[float] = DEFAULT_RANGE_EDGES_M) -> tuple[RangeBin, ...]:
    """The paper's metrics per range bin.

    r_i and delta_op bin the targets by their horizontal range from the sensor; delta_p
    bins the frames by the range of the box corner nearest the sensor (as the paper's
    Fig. 3). Bins are [lo, hi); beyond the last edge an open bin is added when it holds
    anything.
    """
    edges = np.asarray(edges_m, float)
    if edges.ndim != 1 or edges.size < 2 or np.any(np.diff(edges) <= 0):
        raise ValueError(f'range edges must increase, got {list(edges_m)}')
    all_edges = np.append(edges, np.inf)
    t_bin = np.searchsorted(edges, paper.range_m, side='right') - 1
    f_bin = np.searchsorted(edges, paper.closest_range_m, side='right') - 1
    n_bins = edges.size  # the last one is the open bin
    inside = paper.distance_m <= 0.0
    n_t = np.bincount(t_bin[t_bin >= 0], minlength=n_bins)
    n_in = np.bincount(t_bin[(t_bin >= 0) & inside], minlength=n_bins)
    out_mask = (t_bin >= 0) & ~inside
    n_out = np.bincount(t_bin[out_mask], minlength=n_bins)
    sum_out = np.bincount(t_bin[out_mask], weights=paper.distance_m[out_mask],
                          minlength=n_bins)
    n_f = np.bincount(f_bin[f_bin >= 0], minlength=n_bins)
    sum_f = np.bincount(f_bin[f_bin >= 0], weights=paper.closest_offset_m[f_bin >= 0],
                        minlength=n_bins)
    bins = []
    with np.errstate(divide='ignore', invalid='ignore'):
        ratio = n_in / n_t
        delta_op = np.where(n_out > 0, sum_out / np.maximum(n_out, 1), 0.0)
        delta_op = np.where(n_t > 0, delta_op, np.nan)
        delta_p = sum_f / n_f
    for k in range(n_bins):
        if k == n_bins - 1 and n_t[k] == 0 and n_f[k] == 0:
            continue
        bins.append(RangeBin(float(all_edges[k]), float(all_edges[k + 1]), int(n_t[k]),
                             float(ratio[k]), float(delta_op[k]), int(n_f[k]),
                             float(delta_p[k])))
    return tuple(bins)


def evaluate_tracked(recording: Recording, tracked: TrackedTargets,
                     calibration: Mapping[str, Any], config: CalibConfig, *,
                     truth: Mapping[str, Any] | None = None,
                     range_edges_m: Sequence[float] = DEFAULT_RANGE_EDGES_M) -> Evaluation:
    """The paper's evaluation of a calibration on a recording already tracked.

    Parameters
    ----------
    recording : Recording
    tracked : TrackedTargets
        Stages 1-3 of the recording (``track_targets``, or a calibration run's own).
    calibration : mapping
        A result file's content (``result.load_result``).
    config : CalibConfig
        ``vehicle`` (the box), ``sync``.
    truth : mapping, optional
        The simulator's ground truth (``groundtruth.load_ground_truth``).
    range_edges_m : sequence of float
        Edges of the range bins.

    Returns
    -------
    Evaluation

    Raises
    ------
    InsufficientDataError
        The calibration vehicle is never seen: no track lies within 5 m of it on average
        under this calibration.
    """
    extrinsics = calibration_extrinsics(calibration, recording.frame, config)
    ids = metrics.vehicle_track_ids(recording, tracked, extrinsics, config)
    n_tracks = int(np.unique(tracked.track_id[tracked.track_id >= 0]).size)
    if ids.size == 0:
        raise InsufficientDataError(
            'evaluate', f'the calibration vehicle is never seen: none of the {n_tracks} tracks '
            f'lies within {metrics.PAPER_MAX_MEAN_OFFSET_M:g} m of it on average under this '
            'calibration' + (_other_site(calibration, extrinsics, recording) or
                             ' (wrong recording, another radar\'s result, vehicle '
                             'parameters or clock offset? A '
                             'recording on another clock than the calibration\'s, GPS time '
                             'against UTC, say, takes sync.time_offset in --params. Or a '
                             'calibration that no longer fits: a radar re-aimed by 20 deg '
                             'puts every track metres from the vehicle)'))
    index = metrics.track_target_index(tracked, ids)
    paper = metrics.recording_metrics(recording, index, extrinsics, config)
    if paper.n_targets == 0:
        raise InsufficientDataError(
            'evaluate', f'the calibration vehicle is never seen: its {ids.size} tracks have '
            'no target with a vehicle pose')
    # The paper's protocol merges whole tracks: where another road user came within a few
    # metres of the vehicle, its clusters merged into the vehicle's tracks and their
    # targets count as outliers (a twenty-fifth probe: delta_op 0.75 m on the recording
    # its 0.12 m calibration came from, 0.21 there). Their radial velocities tell them.
    unlike = metrics.moving_unlike_vehicle(recording, index, extrinsics, config)
    unlike_fraction = float(unlike.mean()) if unlike.size else 0.0
    paper_alike = None
    if _UNLIKE_NOTE <= unlike_fraction <= _UNLIKE_TRUSTED:
        paper_alike = metrics.recording_metrics(recording, index[~unlike], extrinsics, config)
    errors = None
    # only a truth of the same radar, in the same zone: a recording of several radars
    # holds one truth per radar frame
    same_radar = truth is not None and truth.get('radar_frame', 'radar') == calibration.get(
        'radar_frame', 'radar')
    if truth is not None and same_radar and int(truth.get('epsg', -1)) == int(
            calibration['epsg']):
        errors = calibration_errors(calibration, truth)

    return Evaluation(dict(calibration), extrinsics, paper, bin_by_range(paper, range_edges_m),
                      ids, index, n_tracks, errors, recording, tracked, unlike_fraction,
                      paper_alike, notes=tuple(n for n in (
                          _vehicle_note(calibration, config),
                          _own_recording_note(calibration, recording),
                          _company_note(extrinsics, recording, index, paper, config))
                          if n is not None))


def _company_note(extrinsics: Extrinsics, recording: Recording, index: np.ndarray,
                  paper: metrics.PaperMetrics, config: CalibConfig) -> str | None:
    """A sentence where another road user kept pace alongside the vehicle and joined its
    tracks (``quality.company_in_tracks``): its targets count against r_i and delta_op.

    Why: a sixtieth probe's good calibration (0.28 m) evaluated on a drive with a car
    alongside read r_i 0.30 and delta_op 1.7-2.2 m (0.67 / 0.42 on a clean one), with no
    word of why; a user would have thrown it away."""
    company = quality.company_in_tracks(extrinsics, recording, index, paper, config)
    if company is None:
        return None
    share, side, rest_m = company
    return (f'{100 * share:.0f} % of the targets in the vehicle\'s tracks lie a lane or more '
            f'{side} its box, moving with it: another road user kept pace alongside and joined '
            'its tracks, and its targets count against r_i and delta_op (without them '
            f'delta_op is {rest_m:.2f} m). Judge by the verdict, or evaluate on a drive '
            'without such company')


def _own_recording_note(calibration: Mapping[str, Any], recording: Recording) -> str | None:
    """A sentence where this recording is the one the calibration was made from (its first
    and last radar stamps to the millisecond, its frame and target counts:
    ``quality.recording_span_s``, ``recording_frames``, ``recording_targets``, written since
    results carry them), else None: a fit on its own data agrees with it by construction (a
    forty-first probe read that 'holds' as a check). Not by the stamps and frames alone:
    simulated drives of one length often all start at one stamp."""
    q = calibration.get('quality') or {}
    span, frames = q.get('recording_span_s'), q.get('recording_frames')
    targets = q.get('recording_targets')
    if not (isinstance(span, list) and len(span) == 2 and isinstance(frames, int)
            and isinstance(targets, int) and all(isinstance(v, (int, float)) for v in span)):
        return None
    stamps = recording.frame_stamps_ns
    same = (stamps.size == frames and len(recording.targets) == targets
            and abs(float(stamps[0]) * 1e-9 - float(span[0])) < 1e-3
            and abs(float(stamps[-1]) * 1e-9 - float(span[1])) < 1e-3)
    if not same:
        return None
    return ('this is the recording the calibration was made from: the verdict then agrees '
            'by construction and checks nothing; evaluate on another drive')


#: A box parameter that differs by more than this from the calibration's is named [m].
_BOX_DIFFERS_M = 0.05


def _vehicle_note(calibration: Mapping[str, Any], config: CalibConfig) -> str | None:
    """A sentence where the calibration's vehicle box (``quality.vehicle``, written since
    results carry it) differs from this evaluation's ``vehicle.*``, else None."""
    stated = (calibration.get('quality') or {}).get('vehicle')
    if not isinstance(stated, Mapping):
        return None
    differ = []
    for name in VEHICLE_BOX_PARAMETERS:
        if (value := _number(stated.get(name))) is None:
            continue
        here = float(getattr(config.vehicle, name))
        if abs(here - value) > _BOX_DIFFERS_M:
            differ.append(f'{name} {here:g} m here, {value:g} m there')
    if not differ:
        return None
    return ('the calibration was made with another vehicle box (' + ', '.join(differ) + '): '
            'the paper\'s figures depend on the box and read a box that is not this '
            'vehicle\'s as a calibration error (the verdict much less): check that vehicle.* '
            '(--params) describe this recording\'s vehicle')


def check_agreement(evaluation: Evaluation, config: CalibConfig) -> Agreement:
    """Fit the radar on the evaluation's recording alone and compare it with the calibration.

    The final refinement (stage 8) runs from the calibration under test on the tracks the
    evaluation associated with the vehicle (``_judged_fit``); each difference in the
    calibration's own axes (``AGREEMENT_COMPONENTS``) is judged against the two estimates'
    1-sigma together. A step in the passes' own yaws (``_yaw_step_during``) or the fit's
    own halves check says the radar moved during the recording. A knock in pitch or roll
    during the drive leaves a blend that agrees with both mounts within the scatter the
    knock itself inflates (a forty-first probe: knocks of 1.5-2 deg 'held' or were
    'doubtful'); each half judged on its own (three passes' scatter) did not find them
    either, so that is left to a second drive.

    A recording on which a road user kept pace beside the vehicle on one side in the world,
    or two side by side with the calibration between them (``quality.company_alongside``),
    cannot tell: 'cannot tell'.

    Why a refit and not the paper's figures: they are flat or point the wrong way for
    decimetres along the boresight and a degree of pitch, and blind to altitude and roll;
    the refit measures all six from the same physics calibrate used (the radial velocities
    pin the yaw, the views the position).
    """
    company = quality.company_alongside(evaluation.extrinsics, evaluation.recording, config)
    if company is not None:
        # A calibration and one placed that far over both fit such a recording: a fifty-
        # ninth probe's right calibration 'did not hold' on a straight drive with a car
        # alongside, and calibrate refuses such drives (``quality.company_alongside``).
        where = (f'two road users kept pace side by side on {company.drives} of the '
                 f'vehicle\'s {company.judged} drives through the view, '
                 f'{np.hypot(*company.offset_m):.1f} m apart and at the same two places in '
                 'the world, the calibration putting the vehicle between them'
                 if company.between else
                 f'another road user kept pace beside the vehicle on {company.drives} of its '
                 f'{company.judged} drives through the view, '
                 f'{np.hypot(*company.offset_m):.1f} m from it and always on the same side in '
                 'the world')
        return Agreement('cannot tell', (
            f'{where}: on this recording a calibration and one that places the radar that '
            'far over fit alike, so it cannot judge one. Evaluate on a drive without such '
            'company, or one that turns through the view or crosses it on other roads'))
    stated = _stated_sigmas(evaluation.calibration,
                            same_vehicle=_vehicle_note(evaluation.calibration, config) is None,
                            model_tilt_deg=config.refine.model_sigma_tilt_deg)
    agreement, diagnostics, fitted = _judged_fit(evaluation, config, stated)
    if fitted is None or (agreement.verdict == 'cannot tell' and not _checks_rotation(
            agreement)):
        return agreement
    # the passes' own yaws first: they say by how much each side is off the calibration
    # (the fit's own step is taken against its blend of the two mounts)
    tilt_sigma = (agreement.fit_sigmas.get('roll_deg', 0.0),
                  agreement.fit_sigmas.get('pitch_deg', 0.0))
    moved = (_yaw_step_during(evaluation, config, fitted, agreement.differences['yaw_deg'],
                              tilt_sigma)
             or _moved_during(diagnostics, evaluation.recording))
    if moved is not None:
        # Whatever the blend of before and after agrees with, a calibration of one mount
        # does not hold for both (a thirty-sixth probe's knock of 1.5 deg mid-drive: the
        # blend was 0.7 deg off, 'doubtful' at 1.8 sigma of a scatter the knock inflated).
        named = _named_off(agreement)
        return replace(agreement, moved=moved, verdict='does not hold', reason=(
            f'{moved[0].lower()}{moved[1:]}: a calibration holds for one mount at most, '
            'calibrate again on a recording made after the move' + (
                f' (the fit over the whole recording: {named})' if named else '')))
    return _unseen_azimuth_bias(agreement, diagnostics, evaluation.calibration)


def _unseen_azimuth_bias(agreement: Agreement, diagnostics: Mapping[str, Any],
                         calibration: Mapping[str, Any]) -> Agreement:
    """A verdict that holds made doubtful where this recording's radial velocities show
    the radar's azimuths off towards the edges of its view and the calibration took no
    such error off (one made before that check, or elsewhere): a calibration fitted on the
    raw azimuths agrees with a refit on them, both moved along the boresight alike (a
    forty-ninth probe's 2 m-off result 'held' on its second drive)."""
    bias = diagnostics.get('azimuth_bias')
    if (agreement.verdict != 'holds' or not significant_azimuth_bias(bias)
            or (calibration.get('quality') or {}).get('azimuth_bias')):
        return agreement
    assert isinstance(bias, AzimuthBias)
    return replace(agreement, verdict='doubtful', reason=(
        f'{agreement.reason}; but the radial velocities show the radar\'s azimuths off by '
        f'{bias.edge_deg:+.2f} deg (+-{bias.edge_sigma_deg:.2f}) at '
        f'{math.degrees(bias.half_width_rad):.0f} deg from its boresight, growing towards '
        'the edges, and the calibration took no such error off: both it and this fit stand '
        'moved along the boresight by it (decimetres to metres). Calibrate again: '
        'calibrate takes it off and records it (quality.azimuth_bias)'))


def _checks_rotation(agreement: Agreement) -> bool:
    """A fit whose passes are enough and whose uncertainty is finite: where it cannot
    check the position (``_unseen``), its passes' yaws still show a mount turned during
    the recording."""
    return agreement.n_passes >= AGREEMENT_MIN_PASSES and _has_uncertainty(agreement.sigmas)


def _has_uncertainty(sigmas: Mapping[str, float]) -> bool:
    """Every 1-sigma of the difference finite and above zero."""
    return all(math.isfinite(v) and v > 0 for v in sigmas.values())


def _judged_fit(evaluation: Evaluation, config: CalibConfig, stated: Mapping[str, float]
                ) -> tuple[Agreement, Mapping[str, Any], Extrinsics | None]:
    """The refit on the vehicle's tracks from the calibration, its differences per component and
    the verdict on them (nothing about a moved radar), with the fit's diagnostics and
    estimate (None where it failed).

    Each difference is judged against: this fit's scatter over passes (without the priors
    it shares with the calibration: the vehicle's mean reflection height, its change with
    range, the model's tilt, which bias both alike and do not part them), plus what the
    start's own error adds where the drives leave the position to it (the start is the
    calibration under test: a straight drive left a metre along the boresight unseen, at a
    13-28 cm scatter), plus the calibration's stated 1-sigma. A file that states none (a
    surveyed calibration) shares none of our priors: there the fit's whole covariance
    counts."""
    ext = evaluation.extrinsics
    selection = HypothesisSelection((), np.zeros(0, np.int64), -1, {},
                                    tuple(int(i) for i in evaluation.vehicle_track_ids),
                                    ext, 0)
    try:
        fit = refine.refine_extrinsics(ext, evaluation.recording, evaluation.tracked,
                                       selection, config)
    except InsufficientDataError as err:
        unfitted = (f'the radar could not be fitted on this recording alone '
                    f'({err.reason.rstrip(".")})')
        fell = _inlier_fall(evaluation)
        if fell is not None and fell[0] < _INLIER_COLLAPSE * fell[1]:
            # A fit from a calibration that misses the vehicle's box runs off as readily as
            # from a radar whose data are bad: a forty-seventh probe's mount turned 13 deg
            # (2.8-7.6 % inside against 70 %) was 'cannot tell', blamed on folded velocities,
            # where a 10 deg turn, fitted, was 'does not hold'.
            return Agreement('does not hold', (
                f'the vehicle\'s targets fall inside its box at the calibration in '
                f'{100 * fell[0]:.0f} % of cases against {100 * fell[1]:.0f} % when it was '
                f'calibrated, and {unfitted}: the radar has most likely moved (or this is '
                'another radar\'s recording, or vehicle.* do not describe this vehicle)')), \
                {}, None
        return Agreement('cannot tell', unfitted), {}, None
    fit = _refit_where_it_moved(fit, ext, evaluation, selection, config)
    d = fit.diagnostics
    own = quality.passes_covariance(fit)
    differences = _differences_in_calibration_axes(ext, fit.extrinsics)
    fit_sigmas = _fit_sigmas(own, ext)
    full_sigmas = _fit_sigmas(fit.covariance, ext)
    sigmas = {k: (math.hypot(fit_sigmas[k], stated[k]) if k in stated else full_sigmas[k])
              for k in differences}
    agreement = Agreement('holds', '', differences, sigmas, int(fit.n_passes),
                          float(fit.extrinsics.time_offset_s - ext.time_offset_s),
                          fit_sigmas=full_sigmas)
    if not _has_uncertainty(sigmas):
        return replace(agreement, verdict='cannot tell', reason=(
            'the fit on this recording alone has no uncertainty (fewer than two passes '
            'through the view?)')), d, fit.extrinsics
    z = agreement.z
    worst = max(z.values())
    named = _named_off(agreement)
    if fit.n_passes < AGREEMENT_MIN_PASSES:
        # two passes' scatter has one degree of freedom: an axis on which they agree by
        # chance claims hundredths of a degree (a 30 s drive: 0.02 deg of roll, 26 sigma
        # 'off' at the truth)
        return replace(agreement, verdict='cannot tell', reason=(
            f'the vehicle passed through the view {fit.n_passes} time'
            f'{"s" if fit.n_passes != 1 else ""} on this recording, and it takes '
            f'{AGREEMENT_MIN_PASSES} for the passes\' agreement to mean anything (as for '
            'calibrate)' + (f'; they put the radar {named} from the calibration: drive '
                            'more passes to judge that' if named else ''))), d, fit.extrinsics
    if worst > AGREEMENT_FAILS_SIGMA:
        verdict = 'does not hold'
        reason = (f'a fit on this recording alone puts the radar {named} from the '
                  'calibration, beyond both uncertainties: the radar moved since it was '
                  'calibrated, or the calibration is wrong (check that vehicle.* describe '
                  'this recording\'s vehicle, then calibrate again)')
    elif worst > AGREEMENT_HOLDS_SIGMA:
        verdict = 'doubtful'
        reason = (f'a fit on this recording alone puts the radar {named} from the '
                  'calibration, more than twice their uncertainty but not three times: '
                  'check with another drive')
    else:
        verdict = 'holds'
        unchecked = _unchecked(fit_sigmas, sigmas, stated)
        reason = (f'a fit on this recording alone ({fit.n_passes} passes) agrees with the '
                  f'calibration within {AGREEMENT_HOLDS_SIGMA:g} sigma on every axis '
                  f'(the worst {worst:.1f}); an altitude off by less than about '
                  f'{2 * sigmas["vertical_m"]:.1f} m would not show'
                  + (f'; this recording checks {unchecked} only loosely (its drives leave '
                     'that open): drive across the view to check it' if unchecked else ''))
        unseen = _unseen(sigmas)
        if unseen:
            # Agreement within 2 sigma of metres says nothing: a forty-fifth probe's radar
            # moved 1-3 m along its boresight 'held' (8 highway passes, all head-on and
            # tail-on: 6 m 1-sigma along). What is left to see it by is where the
            # vehicle's targets fall: at the calibration's pose they cannot miss its box
            # far more often than when it was calibrated (r_i 68 % -> 22, 11, 5 %), whatever
            # the reflection model (a wrong pose can score higher, never that much lower).
            verdict, reason = _unseen_verdict(evaluation, unseen, fit.n_passes)
    return replace(agreement, verdict=verdict, reason=reason), d, fit.extrinsics


#: A fit from the calibration under test that moved the radar this far [m, horizontally],
#: and this many times the 1-sigma its start's prior leaves along the move, is run again
#: from where it went (``_refit_where_it_moved``).
_REFIT_MOVED_M = 0.2
_REFIT_SIGMAS = 2.0


def _refit_where_it_moved(fit: Refinement, calibration: Extrinsics, evaluation: Evaluation,
                          selection: HypothesisSelection, config: CalibConfig) -> Refinement:
    """The fit run again from its own estimate, where it moved the radar
    ``_REFIT_MOVED_M`` or more from the calibration under test; as it was otherwise (or
    where the second fit fails).

    Why: the fit holds the horizontal position near its start by a prior (half a metre,
    ``refine_model._START_SIGMA_M``) for where the drives leave it open, and started at a
    calibration off by a metre it stops short (a seventy-sixth probe: 0.86 m of 1.0, 0.37
    of 0.5), with each pass's pull against that prior read as scatter between the passes:
    the 1-sigma it reported grew with the error under test (0.29, 0.43, 0.57 m for 0, 0.5
    and 1.0 m along the boresight), and a metre off 'held'. Started again where it went,
    the prior holds it there, not at the calibration under test."""
    step = (fit.extrinsics.translation_m - calibration.translation_m)[:2]
    moved = float(np.linalg.norm(step))
    if moved < _REFIT_MOVED_M:
        return fit
    # Only where the data, not the prior, decide the position along the move: along a
    # direction they leave open (drives along the boresight) the prior is what holds the
    # fit, and each refit from where the last one went slides it further (our simulator's
    # mid-block radar: a calibration 0.5 m off was found 1.08 m off, where the first fit
    # had 0.54). How much the prior decides is the start's term in the covariance (0.93 m
    # along there, 0.02 m on the probe's junction); the passes' scatter is no measure, as
    # it grew with the pull.
    direction = step / moved
    start_term = np.asarray(fit.diagnostics.get('covariance_start_term', np.zeros((7, 7))),
                            np.float64)[3:5, 3:5]
    sigma = math.sqrt(max(float(direction @ start_term @ direction), 0.0))
    if moved < _REFIT_SIGMAS * sigma:
        return fit
    try:
        return refine.refine_extrinsics(fit.extrinsics, evaluation.recording,
                                        evaluation.tracked, selection, config)
    except InsufficientDataError:
        return fit


#: A component this recording cannot check at all: the two fits' combined 1-sigma is at
#: least this [m, deg] (a move of twice it would still 'hold').
_UNSEEN = {'along_m': 1.0, 'across_m': 1.0, 'roll_deg': 2.0, 'pitch_deg': 2.0,
           'yaw_deg': 1.0}
#: Below this share of the calibration's own r_i, the vehicle's targets miss its box
#: (``_unseen_verdict``). calibrate's r_i counts only the targets its fit kept and reads
#: lower than evaluate's on the same recording, so a fall to half is not a drive's
#: other ranges or aspects.
_INLIER_FALL = 0.5


def _unseen(sigmas: Mapping[str, float]) -> str:
    """The components the combined 1-sigma leaves unchecked (``_UNSEEN``), in words."""
    return ', '.join(f'{_AXIS_WORDS[k]} ({_amount(k, sigmas[k])} 1-sigma)'
                     for k in _UNSEEN if sigmas.get(k, 0.0) >= _UNSEEN[k])


#: Below this share of the calibration's own r_i, with no fit of the recording alone, the
#: calibration does not hold (``_judged_fit``).
_INLIER_COLLAPSE = 0.25


def _inlier_fall(evaluation: Evaluation) -> tuple[float, float] | None:
    """(r_i on this recording at the calibration, r_i the calibration states), None where
    either is unknown."""
    stated = _number((evaluation.calibration.get('quality') or {}).get('inlier_ratio'))
    now = float(evaluation.paper.inlier_ratio)
    if stated is None or stated <= 0 or not math.isfinite(now):
        return None
    return now, stated


def _unseen_verdict(evaluation: Evaluation, unseen: str, n_passes: int) -> tuple[str, str]:
    """'doubtful' where the vehicle's targets fall inside its box less than
    ``_INLIER_FALL`` times as often as at calibration, else 'cannot tell'."""
    drive = ('drive across the view or turn through it (views of the vehicle\'s sides) to '
             'check it')
    fell = _inlier_fall(evaluation)
    if fell is not None and fell[0] < _INLIER_FALL * fell[1]:
        now, stated = fell
        return 'doubtful', (
            f'a fit on this recording alone ({n_passes} passes) cannot check {unseen}, '
            f'and the vehicle\'s targets fall inside its box at the calibration in '
            f'{100 * now:.0f} % of cases against {100 * stated:.0f} % when it was '
            'calibrated: the radar has probably moved along what this recording cannot '
            f'see (or vehicle.* do not describe this vehicle); {drive}')
    return 'cannot tell', (
        f'a fit on this recording alone ({n_passes} passes) agrees with the calibration, '
        f'but cannot check {unseen}: a move of twice that would not show; {drive}')


#: A component this recording checks only loosely: its own 1-sigma is this many times the
#: calibration's stated one, and at least the floor [m, deg].
_LOOSE_FACTOR = 3.0
_LOOSE_FLOOR = {'along_m': 0.15, 'across_m': 0.15, 'vertical_m': 1.0, 'roll_deg': 0.5,
                'pitch_deg': 0.5, 'yaw_deg': 0.2}


def _unchecked(fit_sigmas: Mapping[str, float], sigmas: Mapping[str, float],
               stated: Mapping[str, float]) -> str:
    """The components whose check here is loose, with the 1-sigma they are judged
    against, in words: this recording's own is ``_LOOSE_FACTOR`` times the calibration's,
    or the two together are half of what leaves it unseen (``_UNSEEN``; a calibration as
    loose as the check made the factor miss it)."""
    loose = [k for k, v in fit_sigmas.items()
             if v >= _LOOSE_FLOOR[k] and (v >= _LOOSE_FACTOR * stated.get(k, 0.0)
                                          or sigmas.get(k, 0.0) >= 0.5 * _UNSEEN.get(
                                              k, math.inf))]
    return ', '.join(f'{_AXIS_WORDS[k]} ({_amount(k, sigmas[k])} 1-sigma)' for k in loose)


_AXIS_WORDS = {'along_m': 'the position along the boresight',
               'across_m': 'the position across the boresight', 'vertical_m': 'the altitude',
               'roll_deg': 'the roll', 'pitch_deg': 'the pitch', 'yaw_deg': 'the yaw'}


def _amount(name: str, value: float) -> str:
    return f'{100 * value:.0f} cm' if name.endswith('_m') else f'{value:.2f} deg'


def _named_off(agreement: Agreement) -> str:
    """The components beyond ``AGREEMENT_HOLDS_SIGMA``, worst first, in words."""
    z = agreement.z
    off = sorted((k for k in z if z[k] > AGREEMENT_HOLDS_SIGMA), key=lambda k: -z[k])
    return ', '.join(f'{_component_text(k, agreement.differences[k])} ({z[k]:.1f} sigma)'
                     for k in off)


def _differences_in_calibration_axes(calibration: Extrinsics, fit: Extrinsics
                                     ) -> dict[str, float]:
    """The fit minus the calibration per ``AGREEMENT_COMPONENTS``, in the calibration's
    axes (``quality.boresight_axes``)."""
    axes = quality.boresight_axes(calibration.rotation)
    shift = axes @ (fit.translation_m - calibration.translation_m)
    turn = np.degrees(axes @ Rotation.from_matrix(
        fit.rotation @ calibration.rotation.T).as_rotvec())
    return dict(zip(AGREEMENT_COMPONENTS, (*map(float, shift), *map(float, turn))))


def _fit_sigmas(covariance: np.ndarray, calibration: Extrinsics) -> dict[str, float]:
    """The 1-sigma per ``AGREEMENT_COMPONENTS`` of a (7, 7) covariance (rotation vector as a
    left perturbation in the world, translation, clock) in the calibration's axes."""
    s = quality.uncertainty_from_covariance(covariance, calibration.rotation)
    return dict(zip(AGREEMENT_COMPONENTS, (s['along'], s['across'], s['vertical'],
                                           s['roll_deg'], s['pitch_deg'], s['yaw_deg'])))


def _stated_sigmas(calibration: Mapping[str, Any], *, same_vehicle: bool = False,
                   model_tilt_deg: float = 0.0) -> dict[str, float]:
    """The result file's 1-sigma per ``AGREEMENT_COMPONENTS`` (what it has of them); where
    this evaluation's vehicle box is the calibration's (``same_vehicle``) and the file has
    its passes' part (``quality.sigma_passes``), the roll's and pitch's from that and the
    reflection model's tilt (``model_tilt_deg``, 1-sigma, the drives' own share of it).

    Why: the models of the vehicle's reflection heights and their change with range tilt
    both fits of one vehicle alike, and the stated 1-sigma counts them in full: a
    seventy-sixth probe's 1 deg pitch error 'held' on 4 of 11 sites against 0.45-0.6 deg,
    where the passes agreed to 0.04-0.1. Not the altitude's, nor the position's: there the
    passes' part is the priors' (the reflection height holds the altitude to centimetres
    in each fit, and two drives' fits of one radar lay 5-6 cm apart, 3 of those sigma).
    With another vehicle the models part the two fits: the stated 1-sigma throughout."""
    q = calibration.get('quality') or {}
    sigma = q.get('sigma') or {}
    passes = q.get('sigma_passes') if same_vehicle else None

    def number(source: Mapping[str, Any], key: str) -> float | None:
        value = _number(source.get(key))
        return value if value is not None and value >= 0 else None

    out: dict[str, float] = {}
    for name, key in (('along_m', 'along_boresight_m'), ('across_m', 'across_boresight_m'),
                      ('vertical_m', 'vertical_m')):
        if (value := number(sigma, key)) is not None:
            out[name] = value
    rms = number(sigma, 'rotation_deg')
    for name in ('roll_deg', 'pitch_deg', 'yaw_deg'):
        # results before the per-axis figures: the RMS angle bounds each axis
        value = number(sigma, name)
        if value is None:
            value = rms
        if name != 'yaw_deg' and isinstance(passes, Mapping) and (
                own := number(passes, name)) is not None:
            value = math.hypot(own, model_tilt_deg) if value is None else min(
                value, math.hypot(own, model_tilt_deg))
        if value is not None:
            out[name] = value
    return out


def _component_text(name: str, value: float) -> str:
    if name.endswith('_m'):
        where = {'along_m': 'along its boresight', 'across_m': 'across its boresight',
                 'vertical_m': 'vertically'}[name]
        return f'{100 * value:+.0f} cm {where}'
    return f'{value:+.2f} deg in {name[:-4]}'


def _moved_during(diagnostics: Mapping[str, Any], recording: Recording) -> str | None:
    """The fit's own finding that the radar moved during this recording, as a sentence."""
    turn = diagnostics.get('mount_turn')
    if isinstance(turn, MountTurn):
        return mount_turn_text(turn, recording).rstrip('.')
    if 'halves_rotation_deg' in diagnostics:
        return (f'The first and the second half of this recording\'s passes disagree by '
                f'{float(diagnostics["halves_rotation_deg"]):.2f} deg and '
                f'{100 * float(diagnostics["halves_translation_m"]):.0f} cm, far beyond their '
                'uncertainty: the radar moved during it (a bumped or loose mount), or its '
                'clock drifted')
    return None


def _yaw_step_during(evaluation: Evaluation, config: CalibConfig, fitted: Extrinsics,
                     fitted_yaw_deg: float, tilt_sigma_deg: tuple[float, float] = (0.0, 0.0)
                     ) -> str | None:
    """A step in the yaw the passes' radial velocities give (``metrics.pass_yaw_offsets``,
    ``refine_covariance.yaw_step``), as a sentence, else None. The fit over the whole
    recording may miss it: it blends the mounts and its gate drops the targets of the
    passes the blend misplaces (a thirty-sixth probe's 3 deg knock: 'doubtful', 1.0 deg
    off). The yaws are taken against that fit (``fitted``, ``fitted_yaw_deg`` off the
    calibration), not the calibration: a calibration off in pitch turns each pass's yaw by
    another amount, as its view differs, and read as a step (a forty-first probe's radar
    re-aimed 0.8 deg in pitch before the drive: 'turned by -0.3 deg during it'). That
    fit's own roll and pitch errors (``tilt_sigma_deg``, 1-sigma) shift passes seen at
    other angles by other amounts: a step the two sides' views make of them is no turn."""
    rec = evaluation.recording
    passes = metrics.pass_yaw_offsets(rec, evaluation.target_index, fitted, config)
    yaw, weight, spans = passes.yaw_rad, passes.weight, passes.spans_ns
    k = refine_covariance.yaw_step(yaw, weight, config.hypotheses.min_passes,
                                   passes.tilt_shift, np.radians(tilt_sigma_deg),
                                   refine_covariance.YAW_STEP_TILT_Z)
    if k is None:
        return None
    before = fitted_yaw_deg + math.degrees(float(np.average(yaw[:k], weights=weight[:k])))
    after = fitted_yaw_deg + math.degrees(float(np.average(yaw[k:], weights=weight[k:])))
    t0 = int(rec.frame_stamps_ns[0])
    return (f'The radar\'s mount turned by {after - before:+.1f} deg in yaw between '
            f'{(spans[k - 1, 1] - t0) * 1e-9:.0f} s and {(spans[k, 0] - t0) * 1e-9:.0f} s '
            f'into the recording: its {k} vehicle pass{"es" if k != 1 else ""} before '
            f'that show the yaw {before:+.2f} deg from the calibration\'s, the '
            f'{yaw.size - k} after it {after:+.2f} deg (from their radial velocities, which '
            'depend on the rotation alone)')


#: A radar this far from every vehicle position of a recording sees none of it: a result
#: of another site (no radar sees a car at this range).
_OTHER_SITE_M = 2000.0


def _other_site(calibration: Mapping[str, Any], extrinsics: Extrinsics,
                recording: Recording) -> str | None:
    """Why the vehicle cannot be seen when the calibration is of another site: the radar
    kilometres from the drive (a probe's Sydney recording with an Ulm result read only
    'never seen ... wrong recording, vehicle parameters or clock offset?')."""
    drive = recording.vehicle.positions_m[:, :2]
    if drive.size == 0:
        return None
    distance = float(np.min(np.linalg.norm(drive - extrinsics.translation_m[:2], axis=1)))
    if not distance > _OTHER_SITE_M:
        return None
    if int(calibration['epsg']) != recording.frame.epsg:
        # a distance through another zone's projection means little that far away
        return (f': the result is in EPSG {calibration["epsg"]}, the recording in EPSG '
                f'{recording.frame.epsg}, a UTM zone apart: a result of another site?')
    return (f': the calibrated radar lies {distance / 1000:.1f} km from the nearest vehicle '
            'position of this recording: a result of another radar or site?')


def _azimuths_as_calibrated(recording: Recording, calibration: Mapping[str, Any]
                            ) -> Recording:
    """The recording with the azimuth error the calibration took off its targets
    (``quality.azimuth_bias``) taken off these too: the calibration holds for the radar's
    corrected azimuths, and judged on its raw ones a radar off by 0.66 deg at its edges
    read 'doubtful, 69 cm along the boresight' on its own recording."""
    bias = (calibration.get('quality') or {}).get('azimuth_bias')
    if not isinstance(bias, Mapping):
        return recording
    try:
        found = AzimuthBias(math.radians(float(bias['linear_deg'])),
                            math.radians(float(bias['cubic_deg'])),
                            math.radians(float(bias['half_width_deg'])),
                            float(bias.get('edge_deg', math.nan)),
                            float(bias.get('edge_sigma_deg', math.nan)))
    except (KeyError, TypeError, ValueError):
        return recording
    if not found.half_width_rad > 0.0:
        return recording
    return azimuth_corrected(recording, found)


def evaluate_recording(recording: Recording, calibration: Mapping[str, Any],
                       config: CalibConfig, *, truth: Mapping[str, Any] | None = None,
                       range_edges_m: Sequence[float] = DEFAULT_RANGE_EDGES_M,
                       agreement: bool = True) -> Evaluation:
    """Track the recording (stages 1-3) and evaluate the calibration on it
    (:func:`evaluate_tracked`), with the verdict of a fit on it alone
    (:func:`check_agreement`) unless ``agreement`` is false."""
    recording = _azimuths_as_calibrated(recording, calibration)
    fast = fast_vehicle_config(recording, config)
    if fast is not None:
        config = fast[0]
    tracked = track_targets(recording, config)
    recording, unfolded = _unfolded(recording, tracked, calibration, config)
    evaluation = evaluate_tracked(recording, tracked, calibration, config, truth=truth,
                                  range_edges_m=range_edges_m)
    if fast is not None:
        evaluation = replace(evaluation, notes=(*evaluation.notes, fast[1]))
    if unfolded is not None:
        evaluation = replace(evaluation, notes=(*evaluation.notes, unfolded))
    if not agreement:
        return evaluation
    return replace(evaluation, agreement=check_agreement(evaluation, config))


def _unfolded(recording: Recording, tracked: TrackedTargets, calibration: Mapping[str, Any],
              config: CalibConfig) -> tuple[Recording, str | None]:
    """The recording with the vehicle's radial velocities unfolded where the radar folds
    them (``core/velocity_folding.py``, judged at the calibration under test), and the note
    that says so; as it is, and None, where they do not fold.

    Why: ``calibrate`` unfolds them, and the fit that judges the calibration here followed
    folded ones away (a seventy-third probe's radar folding at +-10 m/s: 'cannot tell', the
    fit 23-34 m and 26-35 deg off, on recordings that calibrate to centimetres)."""
    extrinsics = calibration_extrinsics(calibration, recording.frame, config)
    folding = velocity_folding.detect_folding(extrinsics, recording, tracked.target_index,
                                              config)
    if folding is None:
        return recording, None
    recording, folding = velocity_folding.unfold_radial_velocities(
        recording, extrinsics, tracked.target_index, folding, config)
    return recording, (
        f'The radar\'s radial velocities fold over at +-{folding.period_mps / 2:.1f} m/s: near '
        f'the vehicle {folding.n_folded} of {folding.n_near} targets were off its motion by '
        f'that width, and {folding.n_unfolded} were unfolded by its known motion at the '
        'calibration before the fit that checks it')


# --- output -------------------------------------------------------------------------------

def _finite(value: float) -> float | None:
    return float(value) if math.isfinite(value) else None


def evaluation_dict(evaluation: Evaluation) -> dict[str, Any]:
    """The evaluation as plain JSON-ready types (NaN as null)."""
    p = evaluation.paper
    return {
        # which radar was evaluated (a bag of several: a nineteenth probe could not tell)
        'radar_frame': evaluation.calibration.get('radar_frame'),
        'inlier_ratio': _finite(p.inlier_ratio),
        'outlier_distance_m': _finite(p.outlier_distance_m),
        'closest_target_offset_m': _finite(p.closest_target_offset_m),
        'n_targets': p.n_targets,
        'n_outside': p.n_outside,
        'n_frames': p.n_frames,
        'tracks': {'total': evaluation.n_tracks,
                   'vehicle': [int(v) for v in evaluation.vehicle_track_ids]},
        'max_mean_offset_m': metrics.PAPER_MAX_MEAN_OFFSET_M,
        'time_offset_s': calibration_time_offset_s(evaluation.calibration),
        'duration_s': evaluation.recording.duration_s,
        'range_bins': [{
            'lo_m': b.lo_m, 'hi_m': _finite(b.hi_m), 'n_targets': b.n_targets,
            'inlier_ratio': _finite(b.inlier_ratio),
            'outlier_distance_m': _finite(b.outlier_distance_m),
            'n_frames': b.n_frames,
            'closest_target_offset_m': _finite(b.closest_target_offset_m),
        } for b in evaluation.range_bins],
        'moving_unlike_vehicle_fraction': evaluation.unlike_fraction,
        'notes': list(evaluation.notes),
        'without_unlike': (None if (a := evaluation.paper_alike) is None else {
            'inlier_ratio': _finite(a.inlier_ratio),
            'outlier_distance_m': _finite(a.outlier_distance_m),
            'closest_target_offset_m': _finite(a.closest_target_offset_m),
            'n_targets': a.n_targets}),
        'ground_truth_errors': (None if evaluation.errors is None
                                else {k: _finite(v) for k, v in evaluation.errors.items()}),
        'agreement': None if (g := evaluation.agreement) is None else {
            'verdict': g.verdict, 'reason': g.reason,
            'differences': {k: _finite(v) for k, v in g.differences.items()},
            'sigmas': {k: _finite(v) for k, v in g.sigmas.items()},
            'passes': g.n_passes, 'time_offset_s': _finite(g.time_offset_s),
            'moved_during_recording': g.moved is not None},
    }


def _fmt(value: float, scale: float = 1.0, digits: int = 2) -> str:
    return f'{scale * value:.{digits}f}' if math.isfinite(value) else '-'


def _unlike_lines(evaluation: Evaluation) -> list[str]:
    a = evaluation.paper_alike
    if a is None:
        return []
    return [f'  {100 * evaluation.unlike_fraction:.1f} % of these targets move unlike the '
            f'vehicle (radial velocity more than {metrics.MOTION_MISMATCH_MPS:g} m/s off its',
            '   own: other road users merged into its tracks, or its wheels); without them '
            f'r_i {_fmt(a.inlier_ratio, 100, 1)} %,',
            f'   delta_op {_fmt(a.outlier_distance_m)} m, delta_p '
            f'{_fmt(a.closest_target_offset_m)} m']


def _agreement_lines(agreement: Agreement | None) -> list[str]:
    if agreement is None:
        return []
    lines = ['', f'  verdict: {agreement.headline}: {agreement.reason}.']
    if agreement.differences:
        d, s = agreement.differences, agreement.sigmas
        lines += [
            '  a fit on this recording alone minus the calibration (1-sigma of the difference):',
            '    along {:+.1f} ({:.1f}) cm, across {:+.1f} ({:.1f}) cm, vertical {:+.1f} '
            '({:.1f}) cm'.format(*(100 * v for k in AGREEMENT_COMPONENTS[:3]
                                   for v in (d[k], s[k]))),
            '    roll {:+.3f} ({:.3f}) deg, pitch {:+.3f} ({:.3f}) deg, yaw {:+.3f} ({:.3f}) '
            'deg'.format(*(v for k in AGREEMENT_COMPONENTS[3:] for v in (d[k], s[k]))),
            f'    clocks {1000 * agreement.time_offset_s:+.1f} ms apart from the '
            f'calibration\'s offset here (not judged: each recording has its own)']
    return lines


def format_evaluation(evaluation: Evaluation) -> str:
    """The evaluation as a text table (what ``radar-calib evaluate`` prints)."""
    p = evaluation.paper
    rec = evaluation.recording
    lines = [
        f'evaluation of the calibration of radar frame '
        f'{evaluation.calibration.get("radar_frame", "?")!r} on {rec.duration_s:.0f} s of '
        f'recording: {evaluation.vehicle_track_ids.size}'
        f' of {evaluation.n_tracks} tracks associated with the calibration vehicle (mean '
        f'offset <= {metrics.PAPER_MAX_MEAN_OFFSET_M:g} m), {p.n_targets} targets in '
        f'{p.n_frames} frames',
        f'  r_i       {_fmt(p.inlier_ratio, 100, 1):>7} %   targets inside the vehicle box',
        f'  delta_op  {_fmt(p.outlier_distance_m):>7} m   mean distance of the '
        f'{p.n_outside} outside targets to the box',
        f'  delta_p   {_fmt(p.closest_target_offset_m):>7} m   closest target to the '
        'nearest box corner, mean over frames',
        # a seventh probe read these as a full check: 3 m of altitude left them unchanged,
        # and a radar placed 0.5 m too far along its boresight scored r_i 87 % against 67
        '  (bird\'s-eye figures, as the paper\'s: they do not see the altitude or the roll, '
        'and r_i alone',
        '   does not prove a calibration right: one that pushes the targets into the box '
        'scores higher;',
        '   read it with delta_op and delta_p. They count every target of the tracks within '
        '5 m of the',
        '   vehicle, as the paper\'s protocol does; calibrate\'s summary counts only the '
        'targets its',
        '   final fit kept, on and around the vehicle, and so reads lower on the same '
        'recording)',
        *_unlike_lines(evaluation),
        *(f'  note: {note}.' for note in evaluation.notes),
        '',
        f'  {"range [m]":<11}{"targets":>9}{"r_i [%]":>9}{"delta_op [m]":>14}'
        f'{"frames":>8}{"delta_p [m]":>13}',
    ]
    for b in evaluation.range_bins:
        label = (f'{b.lo_m:.0f}-{b.hi_m:.0f}' if math.isfinite(b.hi_m)
                 else f'>= {b.lo_m:.0f}')
        lines.append(f'  {label:<11}{b.n_targets:>9}{_fmt(b.inlier_ratio, 100, 1):>9}'
                     f'{_fmt(b.outlier_distance_m):>14}{b.n_frames:>8}'
                     f'{_fmt(b.closest_target_offset_m):>13}')
    lines += _agreement_lines(evaluation.agreement)
    e = evaluation.errors
    if e is not None:
        lines += ['', f'  against the ground truth: horizontal {100 * e["horizontal_m"]:.1f} cm '
                  f'(along the boresight {100 * e["along_boresight_m"]:+.1f}, across '
                  f'{100 * e["across_boresight_m"]:+.1f}), vertical '
                  f'{100 * e["vertical_m"]:.1f} cm, rotation {e["rotation_deg"]:.3f} deg '
                  f'(yaw {e["yaw_deg"]:+.3f} deg)'
                  + (f', clock offset {1000 * e["time_offset_s"]:+.1f} ms'
                     if 'time_offset_s' in e else '')]
    return '\n'.join(lines)
