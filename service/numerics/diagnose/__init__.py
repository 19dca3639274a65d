"""Model against measurement: residual channels, where the model fails, and which effect is missing.

One pass (diagnostics.diagnose): the model as it stands; the candidates, each fitted beside it and
judged on held-out time blocks (fits.py); the verdict over them (verdict.py); where the model fails
(where.py). result.py holds what it finds, text.py says it on a terminal. Numerics only.
"""

from .diagnostics import diagnose
from .result import GAIN_SIGMAS, P_SIGNIFICANT, Candidate, Diagnosis
from .text import DECIDES, summary_text, verdict_lines, verdict_word
from .where import where_it_fails, worst_segments

__all__ = ["DECIDES", "Candidate", "Diagnosis", "GAIN_SIGMAS", "P_SIGNIFICANT", "diagnose", "summary_text", "where_it_fails",
           "verdict_lines", "verdict_word", "worst_segments"]
