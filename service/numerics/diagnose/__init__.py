"""Model against measurement: residual channels, where the model fails, and which effect is missing.

One pass: candidates (what could be missing), fits (each candidate on held-out time blocks), verdict
(what is significant, what is left). Numerics only.
"""

from .diagnostics import Diagnosis, diagnose, summary_text  # noqa: F401
