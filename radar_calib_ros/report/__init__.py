"""``radar-calib report`` and ``calibrate --report``: PNG figures and one ``report.html``.

Two entry points, one page layout:

* :func:`report_recording` (``radar-calib report BAG --calibration result.yaml``) does not
  re-calibrate: a calibration run on a long recording takes minutes and would draw a
  different estimate from the file's. It tracks the recording (stages 1-3), evaluates the
  given calibration by the paper's protocol and fits the ground plane (cheap, independent of
  the calibration): the bird's-eye view of a test track, delta_op and delta_p over range,
  and the ground-plane fit.
* :func:`report_calibration` (``radar-calib calibrate BAG --report DIR``) reuses the
  ``CalibrationResult`` just computed and adds the figures only a calibration run has: the
  hypotheses, the residuals of the final refinement, the reflection profile and the
  radial-velocity residuals. Its evaluation figures are on the calibration recording
  itself (the paper's protocol wants a second recording: run ``report`` on one).
"""
from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from radar_calib_ros.config import CalibConfig
from radar_calib_ros.errors import InsufficientDataError
from radar_calib_ros.evaluate import (Evaluation, check_agreement, evaluate_tracked,
                                      track_targets)
from radar_calib_ros.recording import Recording
from radar_calib_ros.report import figures as fig
from radar_calib_ros.report.html import FigureEntry, write_html
from radar_calib_ros.types import F64, Extrinsics, GroundPlane, HypothesisSelection, Refinement

if TYPE_CHECKING:
    from radar_calib_ros.pipeline import CalibrationResult

__all__ = ['ReportFiles', 'report_calibration', 'report_recording', 'write_report']


REPORT_HTML = 'report.html'


@dataclass(frozen=True, slots=True)
class ReportFiles:
    """What a report wrote: the page and its figures (PNG, in page order)."""

    html: Path
    figures: tuple[Path, ...]
    evaluation: Evaluation | None


def _plane_points(recording: Recording, moving_index: np.ndarray, config: CalibConfig) -> F64:
    """The targets the ground plane is fitted to (as ``pipeline.run_calibration`` does)."""
    points = recording.targets.positions_m
    if config.ground.targets == 'moving':
        points = points[moving_index]
    return np.asarray(points, dtype=np.float64)


def write_report(out_dir: str | Path, *, title: str, calibration: Mapping[str, Any],
                 config: CalibConfig, evaluation: Evaluation | None,
                 evaluation_source: str = '', plane_points_m: F64 | None = None,
                 ground: GroundPlane | None = None, selection: HypothesisSelection | None = None,
                 final: Extrinsics | None = None, refinement: Refinement | None = None,
                 notes: tuple[str, ...] = ()) -> ReportFiles:
    """Draw every figure the inputs allow, save them as PNG and write ``report.html``.

    Parameters
    ----------
    out_dir : str or Path
        Created if missing; existing figures of the same names are replaced.
    title : str
    calibration : mapping
        The result's mapping (contract layout).
    config : CalibConfig
    evaluation : Evaluation or None
        Gives the bird's-eye view, delta_op and delta_p figures.
    evaluation_source : str
        One sentence for the page: on which recording the evaluation ran.
    plane_points_m, ground : optional
        The ground plane's targets (sensor frame) and fit.
    selection, final : optional
        The hypotheses and the final estimate.
    refinement : Refinement or None
        Residual, reflection-profile and radial-velocity figures.
    notes : tuple of str
        Sentences under the page title.

    Returns
    -------
    ReportFiles
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    entries: list[FigureEntry] = []

    def add(name: str, figure: Any, heading: str, caption: str) -> None:
        if figure is None:
            return
        path = out / name
        fig.save_figure(figure, path)
        entries.append(FigureEntry(path, heading, caption))

    if evaluation is not None:
        add('bev_track.png', fig.figure_bev_track(evaluation, config),
            "Bird's-eye view of a test track",
            'One pass of the calibration vehicle: its boxes over time and the target clusters '
            'of its associated tracks, coloured by time (black early, yellow late; convex '
            'hulls for clusters of three or more targets), with the estimated sensor '
            "position (cyan cross), on UTM axes. The paper's Fig. 4.")
        add('outlier_distance.png', fig.figure_outlier_distance(evaluation),
            'delta_op over range',
            'Distance of the targets outside the vehicle box to the box, over their '
            "distance from the sensor (the paper's Fig. 2), and r_i per range bin.")
        add('closest_offset.png', fig.figure_closest_offset(evaluation, config.vehicle),
            'delta_p over range',
            'Per frame, the distance between the target closest to the sensor and the '
            "vehicle corner nearest the sensor, over that corner's range, with the "
            '"max error" reference: the distance from a corner to the vehicle\'s centre '
            "(the paper's Fig. 3). It grows with range at the right calibration too (a "
            'probe: 0.6 m at 30 m, 1.5 m at 115 m, from fewer returns and the angular '
            'noise); a rotation error adds range times the angle, 1.7 m per 100 m and '
            'degree. On a second recording the verdict judges the rotation directly.')
    if plane_points_m is not None and ground is not None:
        add('ground_plane.png', fig.figure_ground_plane(plane_points_m, ground, config),
            'Ground-plane fit',
            'Moving targets in the sensor frame from above, from the side and from the '
            'front; in blue those dense enough (the density threshold) and within the '
            'robust gate, which the plane was fitted to; the fitted plane in red. Its '
            "tilt gives the sensor's roll and pitch.")
    if selection is not None and final is not None:
        add('hypotheses.png', fig.figure_hypotheses(selection, final), 'Hypotheses',
            'The sensor position of every per-track hypothesis relative to the final '
            'estimate, clustered by translation (DBSCAN); the accepted cluster in red; '
            'right, the mean pairwise rotation angle within each cluster.')
    add('refinement_residuals.png', fig.figure_refinement_residuals(refinement),
        'Residuals of the final refinement',
        'Position residuals (target minus the estimated reflection profile, in the world) '
        'along and across the line of sight and vertically, over range and azimuth, with '
        'binned medians. A systematic rotation error shows as a slope.')
    add('reflection_profile.png', fig.figure_reflection_profile(refinement, config.vehicle),
        'Reflection profile',
        'Where on the calibration vehicle its targets lie on average, as a function of '
        'the aspect angle (which side faces the radar), estimated jointly with the '
        'calibration; the targets in the vehicle frame behind it and the vehicle box.')
    add('velocity_residuals.png', fig.figure_velocity_residuals(refinement),
        'Radial-velocity residuals',
        "Predicted minus measured radial velocity of the vehicle's targets under the final "
        'calibration: distribution, over range and over aspect angle. Rotation and clock '
        'offset errors would shift them systematically; wheels widen the tails.')
    html = write_html(out / REPORT_HTML, title=title, calibration=calibration,
                      evaluation=evaluation, evaluation_source=evaluation_source,
                      figures=entries, notes=notes)
    return ReportFiles(html, tuple(e.path for e in entries), evaluation)


def report_recording(out_dir: str | Path, recording: Recording, calibration: Mapping[str, Any],
                     config: CalibConfig, *, truth: Mapping[str, Any] | None = None,
                     source: str = '') -> ReportFiles:
    """Report of a calibration file on a recording, without re-calibrating.

    Raises
    ------
    InsufficientDataError
        The calibration vehicle is never seen under this calibration.
    """
    from radar_calib_ros.core import ground_plane
    tracked = track_targets(recording, config)
    evaluation = evaluate_tracked(recording, tracked, calibration, config, truth=truth)
    # the verdict of a fit on this recording alone, as ``evaluate`` gives it
    evaluation = replace(evaluation, agreement=check_agreement(evaluation, config))
    points = _plane_points(recording, tracked.target_index, config)
    ground = ground_plane.fit_ground_plane(points, config.ground) if len(points) >= 3 else None
    return write_report(
        out_dir, title=f'Radar calibration report{": " + source if source else ""}',
        calibration=calibration, config=config, evaluation=evaluation,
        evaluation_source=f'On the recording {source}.' if source else '',
        plane_points_m=points, ground=ground,
        notes=('Evaluation of a calibration file on a recording, without re-calibrating. '
               'The hypotheses, refinement residuals, reflection profile and radial-velocity '
               'figures come from a calibration run: radar-calib calibrate BAG --report DIR.',))


def report_calibration(out_dir: str | Path, result: CalibrationResult, config: CalibConfig,
                       *, calibration: Mapping[str, Any] | None = None,
                       truth: Mapping[str, Any] | None = None, source: str = '') -> ReportFiles:
    """Report of a calibration run, reusing its ``CalibrationResult`` (nothing recomputed
    but the metrics)."""
    calibration = dict(calibration if calibration is not None else result.calibration(config))
    notes = ['The evaluation figures are on the calibration recording itself; for the '
             "paper's protocol run radar-calib report on a second recording."]
    evaluation: Evaluation | None
    try:
        evaluation = evaluate_tracked(result.recording, result.tracked, calibration, config,
                                      truth=truth)
    except InsufficientDataError as err:
        evaluation = None
        notes.append(f'No evaluation figures: {err}.')
    if result.refinement is None:
        notes.append('The final refinement did not run (refine.final is false): no residual, '
                     'reflection-profile or radial-velocity figure.')
    return write_report(
        out_dir, title=f'Radar calibration report{": " + source if source else ""}',
        calibration=calibration, config=config, evaluation=evaluation,
        evaluation_source=f'On the calibration recording {source}.' if source
        else 'On the calibration recording.',
        plane_points_m=_plane_points(result.recording, result.tracked.target_index, config),
        ground=result.ground, selection=result.selection, final=result.extrinsics,
        refinement=result.refinement, notes=tuple(notes))
