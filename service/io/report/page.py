"""What every HTML report shares: matplotlib behind a guard, a figure as PNG bytes, the page's style,
embedded images, and writing DIR/index.html with its PNGs so the page appears complete or not at all.
"""

from __future__ import annotations

import base64
import html
import io
from pathlib import Path

from fluxcal.drivers.errors import FluxcalError
from fluxcal.drivers.outputs import refuse_linked_folder, replacing

#: (file name, caption, PNG bytes)
Figure = tuple[str, str, bytes]

CSS = """body { font-family: sans-serif; max-width: 60em; margin: 2em auto; color: #222; }
table { border-collapse: collapse; margin: 1em 0; font-size: 0.9em; }
td, th { border: 1px solid #bbb; padding: 0.2em 0.6em; text-align: left; }
td.num { text-align: right; font-variant-numeric: tabular-nums; }
td.warn { color: #a40000; font-weight: bold; }
p.warn { color: #a40000; }
figure { margin: 1.5em 0; } img { max-width: 100%; } figcaption { font-size: 0.85em; color: #555; }
pre { white-space: pre-wrap; overflow-wrap: anywhere; }"""

NO_MATPLOTLIB = ("the HTML report needs matplotlib, which is not installed: pip install matplotlib "
                 "(or the project's [plots] extra)")


def pyplot(purpose: str = "or run diagnose without --report"):
    """matplotlib.pyplot on the file-only backend; FluxcalError saying how to install it if missing."""
    try:
        import matplotlib
    except ImportError:
        raise FluxcalError(f"{NO_MATPLOTLIB}, {purpose}") from None
    matplotlib.use("Agg")                       # files only, never a window
    import matplotlib.pyplot as plt

    return plt


def has_matplotlib() -> bool:
    try:
        import matplotlib  # noqa: F401
    except ImportError:
        return False
    return True


def png(fig) -> bytes:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=96, bbox_inches="tight")
    return buf.getvalue()


def images(figs: list[Figure]) -> str:
    """The figures embedded (base64 PNG) with their captions."""
    return "".join(
        f'<figure><img alt="{html.escape(cap)}" src="data:image/png;base64,{base64.b64encode(data).decode()}">'
        f"<figcaption>{html.escape(cap)}</figcaption></figure>" for _, cap, data in figs)


def write_page(out_dir: str | Path, page: str, figs: list[Figure]) -> Path:
    """DIR/index.html and the PNG files beside it; index.html replaced in one step. DIR is made if missing, in a
    folder that must exist (the commands check it first: commands/notes.check_output_folder)."""
    out = Path(out_dir)
    refuse_linked_folder(out, "report")
    try:
        out.mkdir(exist_ok=True)
        for name, _, data in figs:                   # each replaced whole, never written through a link
            with replacing(out / name) as f:
                f.write(data)
        with replacing(out / "index.html", "w") as f:
            f.write(page)
    except OSError as e:
        raise FluxcalError(f"{out}: cannot write the report: {e.strerror or e}") from None
    return out / "index.html"


__all__ = ["Figure", "CSS", "NO_MATPLOTLIB", "pyplot", "has_matplotlib", "png", "images", "write_page"]
