"""A result in a notebook (`_repr_html_` of the Results of fluxcal.service.wiring.result): its table (the parameters with
standard errors, or the candidate effects), its verdict, the text the command line prints, its notes, and a plot of
the residual per channel against its noise floor where matplotlib is installed. Only formatting: the figures are the
result's own (its JSON, docs/contracts.md)."""

from __future__ import annotations

import base64
import html
from typing import Any

from .page import has_matplotlib, png, pyplot

#: rows of a result's table shown (the rest in to_dataframe())
MAX_ROWS = 40


def _cell(v: Any) -> str:
    if isinstance(v, float):
        return f"{v:.6g}"
    return html.escape("" if v is None else str(v))


def table_html(rows: list[dict[str, Any]]) -> str:
    """The rows as an HTML table (the first MAX_ROWS, the rest counted)."""
    if not rows:
        return ""
    keys = list(rows[0])
    body = "".join("<tr>" + "".join(f"<td>{_cell(r.get(k))}</td>" for k in keys) + "</tr>" for r in rows[:MAX_ROWS])
    more = (f"<p>... {len(rows) - MAX_ROWS} more rows: <code>to_dataframe()</code></p>" if len(rows) > MAX_ROWS
            else "")
    return ("<table><tr>" + "".join(f"<th>{html.escape(k)}</th>" for k in keys) + "</tr>" + body + "</table>" + more)


def channels_of(d: dict[str, Any]) -> list[tuple[str, float, float | None]]:
    """(channel, residual RMS, noise floor or None) of a result's JSON: diagnose's channels, or fit's sensors' scalar
    residuals."""
    if d.get("channels"):
        return [(c["name"], c["rms_nT"], c.get("noise_nT")) for c in d["channels"] if c.get("rms_nT") is not None]
    return [(f"{s['name']}.scalar", s["scalar_rms_nT"], None) for s in d.get("sensors", [])
            if s.get("scalar_rms_nT") is not None]


def residual_png(channels: list[tuple[str, float, float | None]]) -> bytes | None:
    """A bar chart of each channel's residual RMS beside its noise floor, or None without matplotlib or channels."""
    if not channels or not has_matplotlib():
        return None
    plt = pyplot("for the plot in a notebook")
    fig, ax = plt.subplots(figsize=(7.0, 2.8))
    xs = range(len(channels))
    ax.bar([x - 0.2 for x in xs], [c[1] for c in channels], 0.4, label="residual RMS")
    floors = [c[2] for c in channels]
    if any(f is not None for f in floors):
        ax.bar([x + 0.2 for x in xs], [f or 0.0 for f in floors], 0.4, label="noise floor", color="0.6")
    ax.set_xticks(list(xs), [c[0] for c in channels], rotation=30, ha="right", fontsize=8)
    ax.set_ylabel("nT")
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3, axis="y")
    data = png(fig)
    plt.close(fig)
    return data


def result_html(result: Any) -> str:
    """The HTML a notebook shows of a Result (module doc)."""
    d = result.as_dict()
    parts = [f"<p><b>fluxcal {html.escape(result.command)}</b> {html.escape(str(result.source))} "
             f"(exit status {result.status})</p>"]
    verdict = d.get("verdict") if isinstance(d.get("verdict"), dict) else None
    if verdict:
        what = f" by {verdict['effect']}" if verdict.get("effect") else ""
        parts.append(f"<p>verdict: <b>{html.escape(verdict['kind'] + what)}</b>"
                     + (f"; what is left: {html.escape(verdict['left'])}" if verdict.get("left") else "")
                     + (f"; what would explain it: {html.escape(verdict['advice'])}" if verdict.get("advice") else "")
                     + "</p>")
    parts.append(table_html(result.rows()))
    image = residual_png(channels_of(d))
    if image is not None:
        parts.append(f'<img alt="residual per channel" src="data:image/png;base64,{base64.b64encode(image).decode()}">')
    text = result.text()
    if text:
        parts.append(f"<details><summary>as the command line prints it</summary><pre>{html.escape(text)}</pre>"
                     f"</details>")
    if result.notes:
        parts.append("<ul>" + "".join(f"<li>{html.escape(n.level)}: {html.escape(n.text)}</li>" for n in result.notes)
                     + "</ul>")
    return "<div>" + "".join(parts) + "</div>"
