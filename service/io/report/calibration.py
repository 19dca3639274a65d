"""The calibration section of the HTML reports (`fit --report`, `diagnose --report`), and the page of
`fit --report DIR` itself.

It draws what fluxcal.service.numerics.calib.sky computed, nothing more: per probe the field directions the
data visited on an equal-area (Mollweide) map of the sensor frame with the unvisited directions
circled, and the scalar residual |B_cal| − F binned over the same map; then the parameter table
(calib.param_table) with standard errors and warnings. Without matplotlib the fit's page still has
the text and tables, and says that the plots need it.
"""

from __future__ import annotations

import html
from pathlib import Path

import numpy as np

from fluxcal.service.numerics.calib.sky import CalibrationSection, ProbeSky

from .page import CSS, NO_MATPLOTLIB, Figure, has_matplotlib, images, png, pyplot, write_page

_AXES = {"+x": (0.0, 0.0), "-x": (180.0, 0.0), "+y": (90.0, 0.0), "-y": (-90.0, 0.0), "+z": (0.0, 90.0),
         "-z": (0.0, -90.0)}
_FRAME = "sensor frame: azimuth from +x towards +y, elevation towards +z"


def _safe(name: str) -> str:
    return "".join(c if c.isalnum() or c in "-_" else "_" for c in name)


def _mollweide(plt, title: str):
    fig = plt.figure(figsize=(7.5, 4.2))
    ax = fig.add_subplot(projection="mollweide")
    ax.grid(alpha=0.3)
    ax.set_title(title, fontsize=10, pad=14)
    ax.tick_params(labelsize=7)
    for label, (az, el) in _AXES.items():
        x = np.radians(az if label != "-x" else 179.0)    # −x sits on the map's edge: drawn just inside
        ax.plot(x, np.radians(el), "k+", ms=8)
        ax.annotate(label, (x, np.radians(el)), textcoords="offset points", xytext=(4, 4), fontsize=8)
    return fig, ax


def _outline(ax, az_el_deg: np.ndarray, **kw) -> None:
    """A circle on the map as dots (a line would cross the map where it wraps at ±180°)."""
    ax.plot(np.radians(az_el_deg[:, 0]), np.radians(az_el_deg[:, 1]), ".", ms=1.5, **kw)


def coverage_figure(plt, p: ProbeSky) -> Figure:
    fig, ax = _mollweide(plt, f"{p.name}: field directions visited ({p.n_samples} samples; "
                              f"{p.coverage_fraction:.0%} of the 26 direction bins)")
    ax.plot(np.radians(p.azimuth_deg), np.radians(p.elevation_deg), ".", ms=1.5, color="tab:blue", alpha=0.4)
    for u in p.unvisited:
        _outline(ax, u.outline_deg, color="tab:red")
        az, el = np.degrees(np.arctan2(u.direction[1], u.direction[0])), np.degrees(np.arcsin(u.direction[2]))
        ax.annotate(f"not visited: {u.label}", (np.radians(az), np.radians(el)), color="tab:red", fontsize=8,
                    ha="center", va="center", fontweight="bold")
    plt.tight_layout()
    data = png(fig)
    plt.close(fig)
    missing = f"; circled in red: no sample within {p.unvisited[0].radius_deg:.0f}°" if p.unvisited else ""
    return (f"coverage_{_safe(p.name)}.png", f"{p.name}: the field direction of every sample ({_FRAME}){missing}",
            data)


def residual_figure(plt, p: ProbeSky) -> Figure:
    r = p.residual
    fig, ax = _mollweide(plt, f"{p.name}: mean scalar residual |B_cal| − F by field direction")
    lim = r.colour_limit_nT
    cmap = plt.get_cmap("RdBu_r").copy()
    mesh = ax.pcolormesh(np.radians(r.az_edges_deg), np.radians(r.el_edges_deg),
                         np.ma.masked_invalid(r.mean_nT), cmap=cmap, vmin=-lim, vmax=lim, shading="flat")
    fig.colorbar(mesh, ax=ax, orientation="horizontal", fraction=0.05, pad=0.08, label="mean residual (nT)")
    w = r.worst()
    if w is not None:
        ax.plot(np.radians(w["azimuth_deg"]), np.radians(w["elevation_deg"]), "ko", mfc="none", ms=10)
    data = png(fig)
    plt.close(fig)
    return (f"residual_{_safe(p.name)}.png", f"{p.name}: the scalar residual per sample averaged in equal-area "
            f"bins ({_FRAME}); white: no samples; circled: the largest mean", data)


def section_figures(plt, section: CalibrationSection) -> list[Figure]:
    """Every plot of the section, two per probe."""
    figs: list[Figure] = []
    for p in section.probes:
        figs.append(coverage_figure(plt, p))
        figs.append(residual_figure(plt, p))
    return figs


def _num(x: float | None, fmt: str) -> str:
    return "n/a" if x is None or not np.isfinite(x) else format(x, fmt)


def parameter_table(section: CalibrationSection) -> str:
    head = ("<tr><th>probe / effect</th><th>parameter</th><th>value</th><th>standard error</th><th>unit</th>"
            "<th>warning / note</th></tr>")
    rows = []
    for r in section.rows:
        flag = (f'<td class="warn">{html.escape(r.warning)}</td>' if r.warning
                else f"<td>{html.escape(r.note)}</td>")
        rows.append(f"<tr><td>{html.escape(r.owner)}</td><td>{html.escape(r.name)}</td>"
                    f'<td class="num">{_num(r.value, ".6g")}</td><td class="num">{_num(r.se, ".2g")}</td>'
                    f"<td>{html.escape(r.unit)}</td>{flag}</tr>")
    return "<table>" + head + "".join(rows) + "</table>"


def _probe_text(p: ProbeSky, radius_deg: float) -> str:
    advice = p.coverage_advice[:1].upper() + p.coverage_advice[1:]
    lines = [f"<h3>{html.escape(p.name)}</h3>",
             f"<p>Coverage: <b>{p.coverage_fraction:.0%}</b> of the 26 direction bins about the fitted offset were "
             f"seen ({p.n_samples} samples)." + (f" {html.escape(advice)}." if advice else "") + "</p>"]
    if p.unvisited:
        lines += [f'<p class="warn">{html.escape(u.sentence())}.</p>' for u in p.unvisited]
    else:
        lines.append(f"<p>Every one of the 26 named directions (axes, edges, corners) has a sample within "
                     f"{radius_deg:.0f}° of it.</p>")
    w = p.residual.worst()
    rms = f"Scalar residual RMS {p.residual_rms_nT:.3f} nT"
    if w is not None:
        rms += (f"; the largest mean over a direction bin is {w['mean_nT']:+.3f} nT near {w['near']} "
                f"(azimuth {w['azimuth_deg']:.0f}°, elevation {w['elevation_deg']:.0f}°, {w['count']} samples, "
                f"RMS {w['rms_nT']:.3f} nT there; the mean is {w['t']:.1f} standard errors from 0)")
    lines.append(f"<p>{html.escape(rms)}.</p>")
    return "\n".join(lines)


def section_html(section: CalibrationSection, figs: list[Figure], plots_note: str = "") -> str:
    """The section as HTML: per probe its text and two maps, then the parameter table and the warnings."""
    by_name = {name: (name, cap, data) for name, cap, data in figs}
    parts = ["<h2>Calibration</h2>", f"<p><b>{html.escape(section.heading)}</b>: "
             f"{html.escape(section.description)}</p>"]
    if plots_note:
        parts.append(f'<p class="warn">{html.escape(plots_note)}</p>')
    for p in section.probes:
        parts.append(_probe_text(p, section.radius_deg))
        mine = [by_name[n] for n in (f"coverage_{_safe(p.name)}.png", f"residual_{_safe(p.name)}.png") if n in by_name]
        parts.append(images(mine))
    parts += ["<h3>Parameters</h3>", "<p>Standard errors as the fit gives them (n/a: none); a warning where the "
              "data leave a parameter undetermined.</p>", parameter_table(section)]
    if section.warnings:
        parts.append("<h3>Warnings of the fit</h3><ul>" +
                     "".join(f"<li>{html.escape(w)}</li>" for w in section.warnings) + "</ul>")
    return "\n".join(parts)


def write_calibration_report(section: CalibrationSection, out_dir: str | Path, title: str = "fluxcal fit",
                             summary: str = "") -> tuple[Path, str]:
    """DIR/index.html (and its PNGs) of the calibration alone. Returns the page and a note ("" when the
    plots are there; else that they need matplotlib: the text and tables are written regardless)."""
    note = ""
    figs: list[Figure] = []
    if has_matplotlib():
        figs = section_figures(pyplot(), section)
    else:
        note = f"No plots: {NO_MATPLOTLIB}."
    page = f"""<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8"><title>{html.escape(title)}</title>
<style>
{CSS}
</style></head><body>
<h1>{html.escape(title)}</h1>
{f"<p>{html.escape(summary)}</p>" if summary else ""}
{section_html(section, figs, note)}
</body></html>
"""
    return write_page(out_dir, page, figs), note


__all__ = ["section_figures", "section_html", "parameter_table", "write_calibration_report"]
