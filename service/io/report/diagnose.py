"""The HTML report of `fluxcal diagnose --report DIR`: one self-contained page with PNG plots.

DIR/index.html embeds every plot (base64 PNG) so the page alone can be mailed or archived; the PNG
files are written beside it too. matplotlib is optional for fluxcal and imported only here, only
when a report is asked for; without it `write_report` raises a FluxcalError that says how to install it.

Plots: the residual against its strongest observables before and after the best candidate effect,
the error per channel before and after, the residual over time, the candidate table, and the
calibration section (report/calibration.py) when one is given.
"""

from __future__ import annotations

import html
from pathlib import Path

import numpy as np

from fluxcal.service.numerics.calib.sky import CalibrationSection
from fluxcal.service.numerics.diagnose import DECIDES, Diagnosis, verdict_lines, verdict_word
from fluxcal.service.numerics.diagnose.text import discovery_lines, gain_text, reference_words

from .calibration import section_figures, section_html
from .page import CSS, NO_MATPLOTLIB, has_matplotlib, images, png, pyplot, write_page

MAX_POINTS = 6000


def _observable_axis(d: Diagnosis, channel: str, observable: str) -> tuple[np.ndarray, str] | None:
    """A one-dimensional axis to plot a residual against: the observable itself or its main direction."""
    fit = d.fit
    pr = fit.problem
    data = pr.data
    rows = pr.rows
    c = fit.channels.names.index(channel)
    kind, kk = pr.channel_probe(c)
    k = 0 if kind == "diff" else kk
    if observable == "time":
        return data.t_s[rows], "time (s)"
    if observable == "temperature" and data.has_temperature():
        return data.temperature(kk)[rows], f"temperature of {data.probe_names[kk]} (degC)"
    if observable == "angular rate":
        s1, r1 = data.smooth(0)[rows], data.rate(0)[rows]
        omega = np.linalg.norm(np.cross(s1, r1), axis=1) / np.sum(s1 ** 2, axis=1)
        return np.degrees(omega), "angular rate (deg/s)"
    if observable in ("orientation", "heading"):
        u = fit.ev.nhat[k]
        return np.degrees(np.arctan2(u[:, 1], u[:, 0])), f"field heading in {data.probe_names[k]}'s frame (deg)"
    if observable == "field magnitude" and data.ref_total_nT is not None:
        return data.ref_total_nT[rows], "reference total field (nT)"
    if observable in data.extras:
        return data.extras[observable][rows], observable
    return None


def _spectrum_groups(names: list[str]) -> list[tuple[str, list[int]]]:
    """The channels in panels of at most a few lines: the scalar channels together, each probe's differences to
    probe 1 together (3 probes: 3 panels of 3)."""
    groups: dict[str, list[int]] = {}
    for c, name in enumerate(names):
        key = "scalar residuals" if name.endswith(".scalar") else name.rsplit(".", 1)[0]
        groups.setdefault(key, []).append(c)
    return list(groups.items())


def _spectrum_figure(plt, d: Diagnosis) -> tuple[str, str, bytes] | None:
    """The spectrum of every channel's residual against its white noise floor, one panel per group of channels,
    drawn from the numbers `where` names its bands from (numerics.diagnose.where.excess_spectrum: the periodogram
    in log-spaced bins), each band it names shaded in its channel's colour."""
    from fluxcal.service.numerics.diagnose.where import excess_spectrum
    from fluxcal.service.numerics.effects.timebase import sample_grid

    ch = d.fit.channels
    if ch.values.shape[0] < 256:
        return None
    dt = sample_grid(ch.t_s)[1]                # the interval where_it_fails took its bands on
    bands = {w["channel"]: w for w in d.where if w["observable"] == "frequency" and w.get("band_hz")}
    groups = _spectrum_groups(list(ch.names))
    cols = 1 if len(groups) == 1 else 2
    rows = -(-len(groups) // cols)
    fig, axes = plt.subplots(rows, cols, figsize=(7.5, 2.9 * rows), squeeze=False, sharex=True)
    sig = (d.verdict or {}).get("signature") or {}
    for ax, (title, members) in zip(axes.ravel(), groups):
        for c in members:
            name = ch.names[c]
            ex = excess_spectrum(ch.values[:, c], dt, float(d.channel_noise_nT[c]))
            line, = ax.loglog(ex.freq_hz, np.sqrt(ex.density), lw=0.8, label=name)
            ax.axhline(np.sqrt(ex.floor), color=line.get_color(), ls=":", lw=0.8)
            w = bands.get(name)
            if w is not None:
                ax.axvspan(*w["band_hz"], color=line.get_color(), alpha=0.15,
                           label=f"{w['band']} ({100 * w['strength']:.0f} %)")
        if sig.get("line_hz"):
            ax.axvline(sig["line_hz"], color="k", ls="--", lw=0.8, label=f"line at {sig['line_hz']:.2f} Hz")
        ax.set_title(title, fontsize=9)
        ax.set_ylabel("residual (nT/√Hz)", fontsize=8)
        ax.tick_params(labelsize=7)
        ax.legend(fontsize=6, ncol=2)
    for ax in axes.ravel()[len(groups):]:
        ax.set_visible(False)
    for ax in axes[-1]:
        ax.set_xlabel("frequency (Hz)", fontsize=8)
    fig.tight_layout()
    data = png(fig)
    plt.close(fig)
    return ("spectrum.png", f"Spectrum of the residual of each of the {len(ch.names)} channels, the model's before any "
            f"candidate (the periodogram averaged in log-spaced bins; dotted: its white noise floor; shaded: the band "
            f"'Where the model fails' names for that channel, and the share of its variance above the floor there)",
            data)


def _frames_figure(plt, d: Diagnosis) -> tuple[str, str, bytes] | None:
    """Each difference vector's RMS per axis in the platform, probe and Earth frames: which axis carries it,
    and (with the share fixed in the platform in the title) whether it stands still or turns with the platform."""
    diffs = [e for e in d.frames if e["kind"] == "difference"]
    if not diffs:
        return None
    fig, axes = plt.subplots(1, len(diffs), figsize=(min(7.5, 2.6 * len(diffs) + 1.0), 3.0), squeeze=False)
    for ax, e in zip(axes[0], diffs):
        frames = [f for f in ("platform", "probe", "earth") if f in e and "rms_nT" in e[f]]
        xs = np.arange(3)
        w = 0.8 / len(frames)
        for i, f in enumerate(frames):
            ax.bar(xs + (i - (len(frames) - 1) / 2) * w, list(e[f]["rms_nT"].values()), w, label=f)
        ax.set_xticks(xs, ["x / N", "y / E", "z / D"] if "earth" in frames else ["x", "y", "z"], fontsize=8)
        share = e["platform"]["fixed_share"]
        ax.set_title(f"{e['channels']}" + ("" if share is None else f" ({100 * share:.0f} % fixed)"), fontsize=8)
        ax.set_ylabel("RMS (nT)")
        ax.grid(alpha=0.3, axis="y")
    axes[0][0].legend(fontsize=7)
    data = png(fig)
    plt.close(fig)
    return ("frames.png", "Each difference vector's RMS per axis in the platform, probe and Earth frames "
            "(in brackets: the share of its excess a vector fixed in the platform explains)", data)


def _frames_table(d: Diagnosis) -> str:
    rows = []
    for e in d.frames:
        for f in ("platform", "probe", "earth"):
            fr = e.get(f)
            if fr is None:
                continue
            share = fr.get("fixed_share")
            axes = fr.get("rms_nT") or {}
            rows.append(f"<tr><td>{html.escape(e['channels'])}</td><td>{f}</td>"
                        f"<td>{'-' if share is None else f'{100 * share:.0f} %'}</td>"
                        f"<td>{html.escape(', '.join(f'{k} {v:.3f}' for k, v in axes.items()) or '-')}</td></tr>")
    if not rows:
        return ""
    return ("<h2>Per axis, in each frame</h2><p>The share of the residual's excess over its floor that one vector fixed "
            "in the platform frame explains (an offset error or a field the platform carries stands still there; a "
            "field of the site turns with the platform), and the RMS per axis in each frame.</p>"
            "<table><tr><th>channels</th><th>frame</th><th>fixed in the platform</th><th>RMS per axis (nT)</th></tr>"
            + "".join(rows) + "</table>")


def _figures(d: Diagnosis) -> list[tuple[str, str, bytes]]:
    """(file name, caption, PNG bytes) of every plot."""
    plt = pyplot()
    m = d.fit.channels.values.shape[0]
    sel = np.arange(0, m, max(1, m // MAX_POINTS))       # at most about MAX_POINTS points per series
    figs = [f for f in (_spectrum_figure(plt, d), _frames_figure(plt, d)) if f is not None]
    figs += _where_figures(plt, d, sel)
    figs.append(_channels_figure(plt, d))
    figs.append(_time_figure(plt, d, sel))
    candidates = _candidates_figure(plt, d)
    if candidates is not None:
        figs.append(candidates)
    return figs + _shape_figures(plt, d)


def _shape_figures(plt, d: Diagnosis) -> list[tuple[str, str, bytes]]:
    """Each law discovery found: the partial residual against its observable (the residual with the law's field added
    back, along its direction, in bins with their standard errors) and the law's field with its band of two standard
    errors, per probe (shape_reading.partial_residual)."""
    found = getattr(d, "discovery", None)
    figs = []
    for j, g in enumerate(g for g in (found.groups if found is not None and found.claimed else [])
                          if g.parts.get("partial")):
        fig, ax = plt.subplots(figsize=(7.5, 3.8))
        for k, part in enumerate(g.parts["partial"]):
            colour = f"C{k}"
            ax.errorbar(part["x"], part["mean_nT"], yerr=part["stderr_nT"], fmt="o", ms=3, color=colour,
                        label=f"{part['probe']}: residual + the law's field, along it")
            law = np.asarray(part["law_nT"])
            band = np.asarray(part["band_nT"])
            ax.plot(part["grid"], law, "-", color=colour, label=f"{part['probe']}: {g.parts['law']} found")
            ax.fill_between(part["grid"], law - band, law + band, color=colour, alpha=0.2)
        unit = g.group.feature.unit
        ax.set_xlabel(f"{g.group.feature.observable}" + (f" ({unit})" if unit and unit != g.group.feature.observable
                                                          else ""))
        ax.set_ylabel("field along the law's direction (nT)")
        ax.set_title(f"{g.group.feature.observable}: {g.parts['law']} (band: 2 standard errors)")
        ax.legend(loc="best", fontsize=8)
        ax.grid(alpha=0.3)
        figs.append((f"shape_{j + 1}.png", f"What discovery found of {g.group.feature.observable}: the partial "
                     f"residual against it, and the {g.parts['law']} with its band", png(fig)))
        plt.close(fig)
    return figs


def _where_picks(d: Diagnosis, most: int = 3) -> list[dict]:
    """The strongest (channel, observable) pairs of `d.where`, each once, frequency bands left out: at most `most`."""
    seen: set[tuple[str, str]] = set()
    picks = []
    for w in d.where:
        key = (w["channel"], w["observable"])
        if w["observable"] == "frequency" or key in seen:
            continue
        seen.add(key)
        picks.append(w)
        if len(picks) == most:
            break
    return picks


def _where_figures(plt, d: Diagnosis, sel: np.ndarray) -> list[tuple[str, str, bytes]]:
    """The residual of a channel against each of its strongest observables, before and after the best candidate
    (the samples `sel`)."""
    best = d.best
    after_vals = best.fit.channels.values if best is not None else None
    before_vals = d.fit.channels.values
    figs = []
    for i, w in enumerate(_where_picks(d)):
        axis = _observable_axis(d, w["channel"], w["observable"])
        if axis is None:
            continue
        x, label = axis
        c = d.channel_names.index(w["channel"])
        fig, ax = plt.subplots(figsize=(7.5, 3.6))
        ax.plot(x[sel], before_vals[sel, c], ".", ms=2, alpha=0.5, label=f"before: {d.model}")
        if after_vals is not None:
            ax.plot(x[sel], after_vals[sel, c], ".", ms=2, alpha=0.5, label=f"after: + {best.effect}")
        ax.set_xlabel(label)
        ax.set_ylabel(f"{w['channel']} residual (nT)")
        ax.set_title(f"{w['channel']} against {w['observable']} (explains {100 * w['strength']:.0f}% of the residual)")
        ax.legend(loc="best", markerscale=5, fontsize=8)
        ax.grid(alpha=0.3)
        figs.append((f"where_{i + 1}.png", f"Residual of {w['channel']} against {w['observable']}, "
                     f"before and after adding the best candidate", png(fig)))
        plt.close(fig)
    return figs


def _channels_figure(plt, d: Diagnosis) -> tuple[str, str, bytes]:
    """The RMS of each channel before and after what explains it (the best candidate, discovery's finding), against
    its noise floor (log scale)."""
    from matplotlib.ticker import ScalarFormatter

    best, found = d.best, getattr(d, "discovery", None)
    names = d.channel_names
    fig, ax = plt.subplots(figsize=(7.5, 3.4))
    xs = np.arange(len(names))
    wbar = 0.28
    ax.bar(xs - wbar, d.channel_rms_nT, wbar, label="before")
    # after: what explains it, the catalogue's best and what discovery found beside it (the plot drew "before" alone
    # where discovery explained the data)
    after = None
    if found is not None and found.claimed and found.fit is not None:
        after = (found.fit.channels.rms_nT, "after + what discovery found" if best is None else
                 f"after + {best.effect} and what discovery found")
    elif best is not None:
        after = (best.fit.channels.rms_nT, f"after + {best.effect}")
    if after is not None and len(after[0]) == len(names):
        ax.bar(xs, after[0], wbar, label=after[1])
    else:
        after = None
    ax.bar(xs + wbar, d.channel_noise_nT, wbar, label="noise floor", color="0.6")
    ax.set_xticks(xs, names, rotation=30, ha="right", fontsize=8)
    ax.set_ylabel("RMS (nT)")
    ax.set_yscale("log")
    ax.yaxis.set_major_formatter(ScalarFormatter())
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3, axis="y")
    data = png(fig)
    plt.close(fig)
    return ("channels.png", "Error per channel before and after, against the noise floor" if after is not None else
            "Error per channel, against the noise floor", data)


def _time_figure(plt, d: Diagnosis, sel: np.ndarray) -> tuple[str, str, bytes]:
    """The residual's RMS over the channels along time, before and after the best candidate (the samples `sel`),
    the worst segments shaded."""
    best = d.best
    t = d.fit.channels.t_s
    before_vals = d.fit.channels.values
    fig, ax = plt.subplots(figsize=(7.5, 3.4))
    ax.plot(t[sel], np.sqrt(np.mean(before_vals[sel] ** 2, axis=1)), lw=0.6, label="before")
    if best is not None:
        after_vals = best.fit.channels.values
        ax.plot(t[sel], np.sqrt(np.mean(after_vals[sel] ** 2, axis=1)), lw=0.6, label=f"after + {best.effect}")
    for s in d.worst_segments:
        ax.axvspan(s["t_start_s"], s["t_end_s"], color="red", alpha=0.08)
    ax.set_xlabel("time (s)")
    ax.set_ylabel("RMS over channels (nT)")
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3)
    data = png(fig)
    plt.close(fig)
    return ("time.png", "Residual over time (worst segments shaded)", data)


def _candidates_figure(plt, d: Diagnosis) -> tuple[str, str, bytes] | None:
    """The held-out RMS of each testable candidate (green: significant) against the model's and the noise floor;
    None when no candidate could be tested."""
    testable = [c for c in d.candidates if c.testable]
    if not testable:
        return None
    fig, ax = plt.subplots(figsize=(7.5, 3.2))
    ys = np.arange(len(testable))
    ax.barh(ys, [c.heldout_rms_nT for c in testable],
            color=["tab:green" if c.significant else "tab:gray" for c in testable])
    ax.axvline(d.heldout_rms_nT, color="k", lw=1, label="model now (held-out)")
    ax.axvline(d.noise_nT, color="tab:red", lw=1, ls="--", label="noise floor")
    ax.set_yticks(ys, [c.effect for c in testable])
    ax.invert_yaxis()
    ax.set_xlabel("held-out RMS with the effect added (nT)")
    ax.legend(fontsize=8)
    data = png(fig)
    plt.close(fig)
    return ("candidates.png", "Held-out RMS of each candidate (green: significant)", data)


def _table(d: Diagnosis) -> str:
    head = ("<tr><th>effect</th><th>RMS if added (nT)</th><th>held-out RMS (nT)</th><th>held-out gain</th>"
            "<th>p-value</th><th>&Delta;BIC</th><th>verdict</th><th>note</th></tr>")
    rows = []
    for c in d.candidates:
        note = ""
        if c.indistinguishable_from:
            note = f"indistinguishable from {', '.join(c.indistinguishable_from)}: {c.separate_by}"
        elif c.reason:
            note = c.reason
        if c.testable:
            weak = d.heldout_weak
            t = c.log_ratio / c.log_ratio_se if c.log_ratio_se > 0 else float("inf")
            gain = html.escape(gain_text(c.gain, weak).strip()) + ("" if weak or c.gain < -1.0 else f" (t = {t:.1f})")
            cells = [c.effect, f"{c.rms_nT:.3f}", f"{c.heldout_rms_nT:.3f}", gain, f"{c.p_value:.2g}",
                     f"{c.bic_delta:.1f}",
                     "<b>SIGNIFICANT</b>" if c.significant else html.escape(verdict_word(c, weak)), html.escape(note)]
        else:
            cells = [c.effect, "-", "-", "-", "-", "-", "not testable", html.escape(note)]
        rows.append("<tr>" + "".join(f"<td>{x}</td>" for x in cells) + "</tr>")
    return ("<p>" + html.escape(" ".join(DECIDES.split())) + "</p><table>" + head + "".join(rows) + "</table>")


def _discovery(d: Diagnosis) -> str:
    """Beyond the catalogue: what discovery tried and found, as the terminal says it, and how to write it as an effect
    of your own (diagnose --write-effect)."""
    lines = discovery_lines(d)
    if not lines:
        return ""
    found = getattr(d, "discovery", None)
    write = ("<p>Write it as an effect of your own: <code>fluxcal diagnose DATA --write-effect FILE.py</code>, then "
             "<code>--effects FILE.py:Discovered</code> (docs/tutorial-discover.md).</p>"
             if found is not None and found.claimed else "")
    return ("<h2>Beyond the catalogue</h2><pre>" + html.escape("\n".join(ln.strip() for ln in lines if ln.strip()))
            + "</pre>" + write)


def render_html(d: Diagnosis, figs: list[tuple[str, str, bytes]], title: str,
                calibration: CalibrationSection | None = None, calibration_figs: list | None = None,
                note: str = "") -> str:
    ch_rows = "".join(f"<tr><td>{html.escape(n)}</td><td>{r:.3f}</td><td>{s:.3f}</td></tr>"
                      for n, r, s in zip(d.channel_names, d.channel_rms_nT, d.channel_noise_nT))
    where_rows = "".join(
        f"<tr><td>{html.escape(w['channel'])}</td><td>{html.escape(w['observable'])}"
        f"{' (' + html.escape(w['band']) + ')' if w.get('band') else ''}</td><td>{w['strength']:.2f}</td></tr>"
        for w in d.where[:12])
    verdict = "<br>".join(html.escape(line.strip()) for line in verdict_lines(d))
    notes = "".join(f"<li>{html.escape(n)}</li>" for n in d.notes)
    cal = section_html(calibration, calibration_figs or [], note) if calibration is not None else ""
    return f"""<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8"><title>{html.escape(title)}</title>
<style>
{CSS}
</style></head><body>
<h1>{html.escape(title)}</h1>
<p>Model: <b>{html.escape(d.model)}</b> (linear part {d.linear}; total field {html.escape(reference_words(d.reference))});
{d.n_samples} samples over {d.duration_s:.1f} s.</p>
<p>Residual RMS <b>{d.rms_nT:.3f} nT</b> against a noise floor of {d.noise_nT:.3f} nT;
held-out {d.heldout_rms_nT:.3f} nT.</p>
<h2>Verdict</h2>
<p>{verdict}</p>
<h2>Candidate effects</h2>
<p>Each effect is fitted in addition to the model and judged on {len(d.fit.problem.blocks)} contiguous time
blocks, each predicted by the fit to the others.</p>
{_table(d)}
{_discovery(d)}
<h2>Channels</h2>
<table><tr><th>channel</th><th>RMS (nT)</th><th>noise (nT)</th></tr>{ch_rows}</table>
<h2>Where the model fails</h2>
<table><tr><th>channel</th><th>observable</th><th>explained variance</th></tr>{where_rows}</table>
{_frames_table(d)}
<h2>Plots</h2>
{images(figs) if figs else f"<p>{html.escape(note)}</p>"}
{cal}
{'<h2>Notes</h2><ul>' + notes + '</ul>' if notes else ''}
</body></html>
"""


def write_report(d: Diagnosis, out_dir: str | Path, title: str = "fluxcal diagnose",
                 calibration: CalibrationSection | None = None) -> Path:
    """Write DIR/index.html and the PNG plots, with the calibration section when one is given; the page
    appears complete or not at all. Without matplotlib the page has the text and tables and says that the
    plots need it (`NO_MATPLOTLIB`)."""
    note = ""
    if has_matplotlib():
        figs = _figures(d)
        cal_figs = section_figures(pyplot(), calibration) if calibration is not None else []
    else:
        figs, cal_figs, note = [], [], f"No plots: {NO_MATPLOTLIB}."
    return write_page(out_dir, render_html(d, figs, title, calibration, cal_figs, note), figs + cal_figs)


__all__ = ["write_report", "render_html"]
