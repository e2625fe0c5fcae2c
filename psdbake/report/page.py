"""index.html: one self-contained page (inline CSS, no scripts, no network), figures by
relative name. The page is ``_PAGE`` below; each ``$section`` is filled by a small function
that returns its lines, every one ending in a newline, so an empty section leaves no gap.
"""

from __future__ import annotations

import html
import math
import os
from collections.abc import Iterable
from string import Template

import numpy as np

from .. import __version__
from .figures import FAINT, leaf
from .prepare import ANGLE_FIGURE, Prepared, view_file
from .stats import METRICS, labels

_CSS = """
body{font-family:-apple-system,Segoe UI,Helvetica,Arial,sans-serif;max-width:1250px;margin:2em auto;padding:0 1em;
color:#222;line-height:1.45}
h1{font-size:1.6em;margin-bottom:.2em} h2{font-size:1.25em;margin-top:1.8em;border-bottom:1px solid #ddd}
table{border-collapse:collapse;font-size:.9em;margin:.6em 0} td,th{border:1px solid #ccc;padding:.25em .6em;text-align:right}
th{background:#f3f3f3} td.l,th.l{text-align:left} code{background:#f5f5f5;padding:0 .2em}
figure{margin:1.2em 0} figure img{max-width:100%;border:1px solid #ddd} figcaption{font-size:.92em;color:#333;max-width:1100px}
.note{color:#555;font-size:.9em} details{margin:.8em 0} summary{cursor:pointer;font-weight:600}
"""

_PAGE = Template("""\
<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8">
<meta name="generator" content="psdbake compare">
<title>psdbake compare: $name</title>
<style>$css</style></head><body>
<h1>Forward vs inverse PSD: $name</h1>
<p class="note">Written by psdbake $version <code>compare</code>. $intro</p>
<h2>Inputs</h2><table>
${inputs}</table>
<h2>Summary over the animation</h2>
<table><tr><th class="l">distance per vertex</th><th>largest</th><th>% of diagonal</th><th>at frame</th>\
<th>mean over frames of the mean over corrected vertices, % of diagonal</th></tr>
${summary}</table>
${turns}<h2>Does the correction turn with the joint?</h2>
<figure><img src="$angle_figure" alt="correction turn against the bone turn">
<figcaption>$angle_caption</figcaption></figure>
<h2>The mesh at chosen frames</h2>
<p>$views_intro</p>
${views}<h2>Per-frame statistics</h2>
<p class="note">$stats_note</p>
<details><summary>Table, one row per frame</summary><table><tr>$header</tr>
${rows}</table></details>
${credits}</body></html>
""")

_INTRO = (
    "At every frame the three results use the <em>same</em> RBF weights, so the only difference between forward and "
    "inverse PSD is the space in which the sculpted examples are interpolated: after skinning (posed space, forward) "
    "or before it (rest space, inverse, what psdbake writes as blend shapes)."
)

_ANGLE_CAPTION = Template(
    "The paper's Figure 3 analysis. The correction of a vertex is the vector <em>result \u2212 SSD</em>. "
    "<b>Left</b>: the angle between that vector at each frame and the same vector at the reference frame (thin "
    "vertical line: where the vertex's inverse-PSD correction is largest). The dashed line is the prediction for a "
    "correction that turns with the limb: the reference correction, carried rigidly by the bone with the "
    "vertex's largest skinning weight. The dotted line is that bone's own rotation angle since the reference "
    "frame; a vector turns by that full angle only when it is perpendicular to the rotation axis, so the dashed "
    "line never rises above it (a correction along the axis does not turn at all). <b>Right</b>: the same "
    "numbers, one point per frame, against the prediction; the diagonal is 'turns with the bone'. "
    "<b>Inverse PSD (red)</b> interpolates the examples in the rest pose and lets skinning pose the result, so "
    "its correction turns with the bone and its points lie near the diagonal (exactly on it for a vertex bound "
    "to one bone and driven by one example; blended skinning weights and examples whose rest-space "
    "corrections point different ways move it off). <b>Forward PSD (blue)</b> interpolates the sculpted "
    "deltas in posed space, so between and beyond the examples its correction keeps the direction it was "
    "sculpted in: it turns only as the weights blend examples sculpted in different directions, and it "
    "stays put where one example dominates while the limb moves on. Where blue sits below red, forward PSD "
    "pushes the surface in a direction the limb has already turned away from. Frames where a correction is "
    "under $faint of its largest are not drawn (a vanishing vector has no direction); the numbers are "
    "in stats.json under <code>vertex_turn</code>."
)

_VIEWS_INTRO = (
    "Each figure shows one frame in four panels, through one orthographic camera shared by every panel and "
    "every view (chosen to see as much of the corrected surface as possible). The first three panels are "
    "coloured by the correction |result \u2212 SSD| on one colour scale, the same in every view: SSD has no "
    "correction by definition (it is the reference); forward and inverse PSD correct by nearly the same amount "
    "(same weights, same examples) but not in the same direction, which the last panel shows as the distance "
    "between the two results, |inverse \u2212 forward|, on its own scale: zero at the example poses, where both "
    "reproduce the sculpts, and growing as the limb turns away from them. The shapes differ by a few percent "
    "of the mesh's size at most, so the colours, not the silhouettes, carry the comparison."
)

_STATS_NOTE = (
    'Also in <a href="stats.csv">stats.csv</a> and <a href="stats.json">stats.json</a> '
    "(which holds the series drawn in correction_angle.png under <code>vertex_turn</code>). "
    "Distances in scene units; <code>_rel</code> columns are fractions of the bounding-box diagonal; "
    "means are over the vertices with a corrective; angles are each driver's rotation away from the "
    "bind pose, in radians."
)

DEG = 180.0 / math.pi


def _e(text: object) -> str:
    return html.escape(str(text), quote=True)


def _pct(x: float) -> str:
    return f"{x * 100:.3g}%"


def _lines(items: Iterable[str]) -> str:
    return "".join(f"{item}\n" for item in items)


def render(rep: Prepared) -> str:
    """The whole page of a prepared report."""
    name = _e(os.path.basename(rep.label))
    return _PAGE.substitute(
        name=name, css=_CSS, version=_e(__version__), intro=_INTRO,
        inputs=_lines(_inputs(rep)), summary=_lines(_summary(rep)), turns=_lines(_turns(rep)),
        angle_figure=_e(ANGLE_FIGURE), angle_caption=_ANGLE_CAPTION.substitute(faint=f"{FAINT:.0%}"),
        views_intro=_VIEWS_INTRO, views=_lines(_views(rep)), stats_note=_STATS_NOTE,
        header="".join(f"<th>{_e(h)}</th>" for h in rep.table.header),
        rows=_lines("<tr>" + "".join(f"<td>{v:.4g}</td>" for v in row) + "</tr>" for row in rep.table.rows),
        credits=_lines(f'<p class="note">{_e(c)}</p>' for c in rep.credits),
    )


def _inputs(rep: Prepared) -> list[str]:
    """The Inputs table: what was compared and with which fit settings."""
    comparison, m = rep.comparison, rep.mesh
    fit = comparison.fit
    mfit = next(f for f in fit.meshes if f.mesh == m.mesh)
    s, d = fit.settings, mfit.driver_data
    rows = [
        ("asset", rep.label), ("examples", ", ".join(fit.example_files)), ("animation", comparison.anim),
        ("mesh", f"{m.mesh} ({m.ssd.shape[1]} points, {len(m.corrected)} with a corrective, "
                 f"bounding-box diagonal {m.diagonal:.4g})"),
        ("frames", f"{m.times[0]:g}..{m.times[-1]:g} ({len(m.times)} frames)"),
        ("drivers", ", ".join(leaf(j) for j in mfit.drivers)),
        ("examples fitted", ", ".join(ex.label for ex in mfit.examples)),
        ("RBF", f"kernel {d.kernel}, sigma {d.sigma:.4g} rad, degree {d.degree}, smoothing {d.smoothing:g}"
                + ("" if s.rest_example else ", no rest example")),
        ("deformers", ", ".join(s.deformers) or "none"),
    ]
    if len(comparison.meshes) > 1:
        others = [o.mesh for o in comparison.meshes if o.mesh != m.mesh]
        rows.append(("other meshes", ", ".join(others) + " (choose with --mesh)"))
    return [f'<tr><th class="l">{_e(k)}</th><td class="l">{_e(v)}</td></tr>' for k, v in rows]


def _summary(rep: Prepared) -> list[str]:
    """One row per distance: its largest value over the animation, and its typical size."""
    out = []
    for key, name in METRICS:
        dist = rep.stats.metric(key)
        i = int(np.argmax(dist.max))
        out.append(f'<tr><td class="l">{_e(name)}</td><td>{dist.max[i]:.4g}</td><td>{_pct(dist.max_rel[i])}</td>'
                   f"<td>{rep.mesh.times[i]:g}</td><td>{_pct(float(dist.mean_rel.mean()))}</td></tr>")
    return out


def _turns(rep: Prepared) -> list[str]:
    """One paragraph per chosen vertex: how far its correction turns, in words."""
    out = []
    for turn in rep.turns:
        top = {k: turn.peak(k) * DEG for k in ("inverse", "forward", "carried_turn", "joint_turn")}
        out.append(
            f"<p>Vertex {turn.vertex} ({_e(turn.why)}): from frame {turn.reference_time:g} its correction turns "
            f"by up to <b>{top['inverse']:.1f}°</b> with inverse PSD and <b>{top['forward']:.1f}°</b> with forward PSD. "
            f"Carried rigidly by the bone that moves the vertex most ({_e(leaf(turn.joint))}, which rotates by up to "
            f"{top['joint_turn']:.1f}°), the frame-{turn.reference_time:g} correction would turn by up to "
            f"{top['carried_turn']:.1f}°.</p>"
        )
    return out


def _views(rep: Prepared) -> list[str]:
    """One figure per chosen frame, captioned with the example weights there."""
    m, rel = rep.mesh, rep.stats.inverse_forward.max_rel
    _, examples = labels(rep.comparison, m)
    out = []
    for t in rep.view_frames:
        i = int(np.argmin(np.abs(m.times - t)))
        weights = ", ".join(f"{_e(e)} {w:.2f}" for e, w in zip(examples, m.weights[i], strict=True))
        out.append(f'<figure><img src="{_e(view_file(t))}" alt="SSD, forward and inverse PSD at frame {t:g}">'
                   f"<figcaption>Frame {t:g}: example weights {weights}; |inverse \u2212 forward| up to "
                   f"{_pct(rel[i])} of the diagonal (largest over the animation: {_pct(rel.max())}).</figcaption></figure>")
    return out
