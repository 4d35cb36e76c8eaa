"""``report.html``: one page with the result, the quality figures and the figures.

The page is self-contained and readable offline: no script, no remote style sheet or font,
every image embedded as a base64 data URI (and linked to its PNG file next to the page, so
the figures can also be opened at full size or reused).
"""
from __future__ import annotations

import base64
import html
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from radar_calib_ros.evaluate import AGREEMENT_COMPONENTS, Evaluation


@dataclass(frozen=True, slots=True)
class FigureEntry:
    """One figure of the page: its PNG (next to the page), a heading and a caption."""

    path: Path
    heading: str
    caption: str


_STYLE = """
body { font-family: sans-serif; max-width: 1100px; margin: 1em auto; padding: 0 1em;
       color: #222; line-height: 1.4; }
h1 { font-size: 1.5em; } h2 { font-size: 1.2em; margin-top: 1.6em; border-bottom: 1px solid #ccc; }
table { border-collapse: collapse; margin: 0.5em 0; }
td, th { border: 1px solid #ccc; padding: 2px 8px; text-align: right; }
td:first-child, th:first-child { text-align: left; }
figure { margin: 1em 0 2em 0; } figure img { max-width: 100%; border: 1px solid #ddd; }
figcaption { font-size: 0.9em; color: #444; }
.note { font-size: 0.9em; color: #555; }
.advice { background: #fff6e0; border-left: 4px solid #e0a000; padding: 0.4em 0.8em; }
"""


def _e(text: Any) -> str:
    return html.escape(str(text))


def _num(value: Any, fmt: str, scale: float = 1.0) -> str:
    if isinstance(value, bool) or not isinstance(value, (int, float)) \
            or not math.isfinite(value):
        return '-'
    return format(scale * value, fmt)


def _rows(rows: Sequence[tuple[str, str]]) -> str:
    return '<table>' + ''.join(f'<tr><td>{_e(k)}</td><td>{_e(v)}</td></tr>'
                               for k, v in rows) + '</table>'


def _result_section(calibration: Mapping[str, Any]) -> str:
    t = calibration.get('translation') or [math.nan] * 3
    rpy = calibration.get('rpy_deg') or [math.nan] * 3
    q = calibration.get('quaternion_xyzw') or [math.nan] * 4
    rows = [
        ('frames', f'{calibration.get("world_frame", "utm")} -> '
                   f'{calibration.get("radar_frame", "radar")} (EPSG:{calibration.get("epsg")})'),
        ('position E / N / altitude [m]', ' / '.join(_num(v, '.3f') for v in t)),
        ('latitude / longitude [deg]', f'{_num(calibration.get("latitude"), ".8f")} / '
                                       f'{_num(calibration.get("longitude"), ".8f")}'),
        ('roll / pitch / yaw [deg]', ' / '.join(_num(v, '.3f') for v in rpy)),
        ('quaternion x, y, z, w', ', '.join(_num(v, '.6f') for v in q)),
        ('boresight [deg from true north]', _num(calibration.get('boresight_azimuth_deg'),
                                                 '.2f')),
        ('computed', str(calibration.get('stamp', '-'))),
    ]
    return '<h2>Calibration</h2>' + _rows(rows)


def _quality_section(quality: Mapping[str, Any]) -> str:
    if not quality:
        return ''
    sigma = quality.get('sigma') or {}
    rows = [
        ('r_i (targets inside the vehicle box)', _num(quality.get('inlier_ratio'), '.1f', 100)
         + ' %'),
        ('delta_op (mean distance of outside targets) [m]',
         _num(quality.get('outlier_distance_m'), '.3f')),
        ('delta_p (closest target to the nearest corner) [m]',
         _num(quality.get('closest_target_offset_m'), '.3f')),
        ('passes / tracks used / hypotheses / correspondences',
         f'{quality.get("passes", "-")} / {quality.get("tracks_used", "-")} / '
         f'{quality.get("hypotheses", "-")} / {quality.get("correspondences", "-")}'),
        ('clock offset [ms]', _num(quality.get('time_offset_s'), '.1f', 1000)),
        ('1-sigma translation [m]', _num(sigma.get('translation_m'), '.3f')),
        ('1-sigma along / across the boresight [m]',
         f'{_num(sigma.get("along_boresight_m"), ".3f")} / '
         f'{_num(sigma.get("across_boresight_m"), ".3f")}'),
        ('1-sigma vertical [m]', _num(sigma.get('vertical_m'), '.3f')),
        ('1-sigma rotation [deg]', _num(sigma.get('rotation_deg'), '.3f')),
    ]
    out = ('<h2>Quality figures of the calibration run</h2><p class="note">On the '
           'calibration recording, over the accepted tracks.</p>' + _rows(rows))
    advice = quality.get('advice') or []
    if advice:
        out += '<div class="advice"><b>Advice</b><ul>' + ''.join(
            f'<li>{_e(a)}</li>' for a in advice) + '</ul></div>'
    return out


def _evaluation_section(evaluation: Evaluation, source: str) -> str:
    p = evaluation.paper
    head = (f'<h2>Evaluation (the paper\'s protocol)</h2><p class="note">{_e(source)} '
            f'{evaluation.vehicle_track_ids.size} of {evaluation.n_tracks} tracks associated '
            'with the calibration vehicle by synchronised time (mean offset at most 5 m), '
            f'merged: {p.n_targets} targets in {p.n_frames} frames.</p>')
    rows = [('r_i (targets inside the vehicle box)', _num(p.inlier_ratio, '.1f', 100) + ' %'),
            ('delta_op [m]', _num(p.outlier_distance_m, '.3f')),
            ('delta_p [m]', _num(p.closest_target_offset_m, '.3f'))]
    table = ['<table><tr><th>range [m]</th><th>targets</th><th>r_i [%]</th>'
             '<th>delta_op [m]</th><th>frames</th><th>delta_p [m]</th></tr>']
    for b in evaluation.range_bins:
        label = (f'{b.lo_m:.0f}-{b.hi_m:.0f}' if math.isfinite(b.hi_m)
                 else f'&ge; {b.lo_m:.0f}')
        table.append(f'<tr><td>{label}</td><td>{b.n_targets}</td>'
                     f'<td>{_num(b.inlier_ratio, ".1f", 100)}</td>'
                     f'<td>{_num(b.outlier_distance_m, ".3f")}</td><td>{b.n_frames}</td>'
                     f'<td>{_num(b.closest_target_offset_m, ".3f")}</td></tr>')
    table.append('</table>')
    for note in evaluation.notes:
        head += f'<p class="note">Note: {_e(note)}.</p>'
    out = head + _rows(rows) + ''.join(table) + _agreement_section(evaluation)
    e = evaluation.errors
    if e is not None:
        rows = [('horizontal [cm]', _num(e.get('horizontal_m'), '.1f', 100)),
                ('  along / across the boresight [cm]',
                 f'{_num(e.get("along_boresight_m"), "+.1f", 100)} / '
                 f'{_num(e.get("across_boresight_m"), "+.1f", 100)}'),
                ('vertical [cm]', _num(e.get('vertical_m'), '.1f', 100)),
                ('rotation [deg]', _num(e.get('rotation_deg'), '.3f')),
                ('yaw [deg]', _num(e.get('yaw_deg'), '+.3f'))]
        if 'time_offset_s' in e:
            rows.append(('clock offset [ms]', _num(e['time_offset_s'], '+.1f', 1000)))
        out += ('<h2>Against the ground truth</h2><p class="note">The bag directory carries '
                "the simulator's ground_truth.json.</p>" + _rows(rows))
    return out


def _agreement_section(evaluation: Evaluation) -> str:
    g = evaluation.agreement
    if g is None:
        return ''
    out = f'<h2>Verdict: {_e(g.headline)}</h2><p class="note">{_e(g.reason)}.</p>'
    if not g.differences:
        return out
    units = {'_m': ('cm', 100, '+.1f'), '_deg': ('deg', 1, '+.3f')}
    rows = []
    for k in AGREEMENT_COMPONENTS:
        unit, scale, fmt = units['_m' if k.endswith('_m') else '_deg']
        label = k.rsplit('_', 1)[0]
        rows.append((f'{label} [{unit}]: fit here minus calibration (1-sigma)',
                     f'{_num(g.differences[k], fmt, scale)} '
                     f'({_num(g.sigmas[k], fmt.lstrip("+"), scale)})'))
    return out + _rows(rows)


def _figure_html(entry: FigureEntry) -> str:
    data = base64.b64encode(entry.path.read_bytes()).decode('ascii')
    name = _e(entry.path.name)
    return (f'<figure id="{name}"><h3>{_e(entry.heading)}</h3>'
            f'<img src="data:image/png;base64,{data}" alt="{name}">'
            f'<figcaption>{_e(entry.caption)} (<a href="{name}">{name}</a>)</figcaption>'
            '</figure>')


def write_html(path: str | Path, *, title: str, calibration: Mapping[str, Any],
               evaluation: Evaluation | None, evaluation_source: str,
               figures: Sequence[FigureEntry], notes: Sequence[str] = ()) -> Path:
    """Write ``report.html``.

    Parameters
    ----------
    path : str or Path
        The page; the figures' PNGs should sit in the same directory (they are linked by
        name and embedded).
    title : str
    calibration : mapping
        The result's mapping (contract layout), with its ``quality``.
    evaluation : Evaluation or None
    evaluation_source : str
        One sentence saying on which recording the evaluation ran.
    figures : sequence of FigureEntry
    notes : sequence of str
        Sentences shown under the title (e.g. which figures need ``calibrate --report``).
    """
    path = Path(path)
    parts = [f'<!DOCTYPE html><html lang="en"><head><meta charset="utf-8">'
             f'<title>{_e(title)}</title><style>{_STYLE}</style></head><body>',
             f'<h1>{_e(title)}</h1>']
    parts += [f'<p class="note">{_e(n)}</p>' for n in notes]
    if figures:
        parts.append('<p>Figures: ' + ', '.join(
            f'<a href="#{_e(f.path.name)}">{_e(f.heading)}</a>' for f in figures) + '</p>')
    parts.append(_result_section(calibration))
    parts.append(_quality_section(calibration.get('quality') or {}))
    if evaluation is not None:
        parts.append(_evaluation_section(evaluation, evaluation_source))
    parts.append('<h2>Figures</h2>')
    parts += [_figure_html(f) for f in figures]
    parts.append('</body></html>\n')
    path.write_text('\n'.join(parts), encoding='utf-8')
    return path
