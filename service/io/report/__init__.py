"""The HTML reports: `fluxcal diagnose --report DIR` (diagnose.py) and `fluxcal fit --report DIR`
(calibration.py, whose calibration section the diagnose page carries too); page.py holds what both share.
matplotlib is optional and imported only when a report is drawn."""

from .calibration import write_calibration_report
from .diagnose import render_html, write_report

__all__ = ["write_report", "render_html", "write_calibration_report"]
