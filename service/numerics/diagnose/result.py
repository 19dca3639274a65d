"""What a diagnosis finds, as data: each candidate effect and the diagnosis as a whole, JSON-ready.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from functools import cached_property
from typing import Any

import numpy as np

from fluxcal.service.numerics.engine import (
    FitResult,
    Parameter,
)
from fluxcal.service.numerics.jsonsafe import finite_or_none as _num
from fluxcal.service.numerics.jsonsafe import json_safe as _plain

P_SIGNIFICANT = 1e-3


GAIN_SIGMAS = 2.0


GAIN_TOLERANCE = 0.10


MIN_GAIN = 0.02            # "significant" is a gain worth having: the held-out MSE falls by at least 2 %


COLLINEAR_R2 = 0.90


ABSORBED = 0.01            # largest unexplained fraction of a candidate's regressors for "absorbed"


N_BLOCKS = 8


CANDIDATE_ITERATIONS = 4


Progress = Callable[[float, str], None]


@dataclass
class Candidate:
    """One catalogue effect tried on top of the model."""

    effect: str
    rms_nT: float                         # in-sample RMS over all channels with the effect added
    heldout_rms_nT: float                 # RMS of the blocks each predicted by the others
    significant: bool = False
    testable: bool = True
    reason: str | None = None             # why not testable, or a note
    refusal: str | None = None            # the verdict column's few words when a later check refused it
    gain: float = 0.0                     # held-out gain, fraction of the model's held-out weighted MSE
    log_ratio: float = 0.0                # mean over blocks of ln(MSE without / MSE with), held out
    log_ratio_se: float = 0.0             # its standard error from the block-to-block spread
    p_value: float = 1.0                  # nested-model F-test on all the data
    bic_delta: float = 0.0                # BIC with - BIC without (negative favours the effect)
    n_params: int = 0                     # parameters the data determine
    indistinguishable_from: list[str] = field(default_factory=list)
    separate_by: str | None = None
    block_log_ratio: np.ndarray | None = field(default=None, repr=False)
    fit: FitResult | None = field(default=None, repr=False)
    #: (C,) each channel's held-out RMS with the effect added, nT (None where it was not fitted)
    heldout_channels_nT: np.ndarray | None = field(default=None, repr=False)

    @cached_property
    def parameters(self) -> list[Parameter]:
        """The effect's own fitted parameters with their standard errors (none without a fit), worked out when first
        read: their errors under coloured noise are most of a candidate's cost, and only the checks of a significant
        candidate, or the output, read them."""
        return [] if self.fit is None else [p for p in self.fit.parameters() if p.term == self.effect]

    def refuse(self, refusal: str, reason: str) -> None:
        """Not significant after all, for a later check: the verdict column's few words and the whole reason."""
        self.significant, self.refusal, self.reason = False, refusal, reason

    def as_dict(self) -> dict[str, Any]:
        d: dict[str, Any] = {"effect": self.effect, "rms_nT": _num(self.rms_nT), "significant": self.significant,
                             "heldout_rms_nT": _num(self.heldout_rms_nT), "heldout_gain": _num(self.gain),
                             "heldout_log_ratio": _num(self.log_ratio),
                             "heldout_log_ratio_se": _num(self.log_ratio_se), "p_value": _num(self.p_value),
                             "bic_delta": _num(self.bic_delta), "n_params": self.n_params,
                             "testable": self.testable}
        if self.indistinguishable_from:
            d["indistinguishable_from"] = list(self.indistinguishable_from)
        if self.separate_by:
            d["separate_by"] = self.separate_by
        if self.reason:
            d["reason"] = self.reason
        if self.parameters:
            d["parameters"] = [{"name": p.name, "value": _num(p.value), "stderr": _num(p.stderr)}
                               for p in self.parameters]
        return d


@dataclass
class Diagnosis:
    """Everything `fluxcal diagnose` reports; `as_dict()` is the JSON of docs/contracts.md."""

    effects: list[str]
    model: str
    linear: str                           # "refit" or "fixed"
    reference: str                        # "ref_total", "config", "estimated" or "the site (WMM-2025)"
    rms_nT: float
    noise_nT: float
    channel_names: list[str]
    channel_rms_nT: np.ndarray
    channel_noise_nT: np.ndarray
    where: list[dict[str, Any]]
    candidates: list[Candidate]
    worst_segments: list[dict[str, Any]]
    n_samples: int
    duration_s: float
    heldout_rms_nT: float
    notes: list[str]
    fit: FitResult = field(repr=False)
    linear_refit_rms_nT: float | None = None
    linear_refit_refused: str | None = None     # why these data do not determine that refit (None: they do)
    parameters: list[Parameter] = field(default_factory=list)
    verdict: dict[str, Any] | None = None
    #: set when the samples diagnosed are every k-th of a longer recording: {"every", "n_used", "n_read", ...}
    thinned: dict[str, Any] | None = None
    #: the residual per axis in the probe, platform and Earth frames (frames.py)
    frames: list[dict[str, Any]] = field(default_factory=list)
    #: beyond the catalogue: what discovery tried and found (discover.Discovery), None where it did not run
    discovery: Any = None
    #: why the held-out test cannot judge these data and what recording would (weak.py), None where it can
    heldout_weak: dict[str, Any] | None = None

    @property
    def n_fitted(self) -> int | None:
        """The samples the residuals are taken over: away from the record's ends and its gaps in time, the rows every
        candidate's terms (lags, rates) are fitted on; None where that is every sample."""
        rows = getattr(getattr(self.fit, "problem", None), "rows", None)
        return None if rows is None or rows.size == self.n_samples else int(rows.size)

    @property
    def best(self) -> Candidate | None:
        """The first significant candidate, if any."""
        return next((c for c in self.candidates if c.significant), None)

    def as_dict(self) -> dict[str, Any]:
        d: dict[str, Any] = {
            "effects": list(self.effects),
            "rms_nT": _num(self.rms_nT),
            "noise_nT": _num(self.noise_nT),
            "channels": [{"name": n, "rms_nT": _num(r), "noise_nT": _num(s)}
                         for n, r, s in zip(self.channel_names, self.channel_rms_nT, self.channel_noise_nT)],
            "where": [{k: _num(v) if isinstance(v, float) else v for k, v in w.items()} for w in self.where],
            "candidates": [c.as_dict() for c in self.candidates],
            "worst_segments": self.worst_segments,
            "model": self.model,
            "linear": self.linear,
            "reference": self.reference,
            "n_samples": self.n_samples,
            "duration_s": _num(self.duration_s),
            "heldout_rms_nT": _num(self.heldout_rms_nT),
            "parameters": [{"name": p.name, "value": _num(p.value), "stderr": _num(p.stderr)}
                           for p in self.parameters],
            "notes": list(self.notes),
            "verdict": _plain(self.verdict),
        }
        if self.n_fitted is not None:
            d["n_fitted"] = self.n_fitted
        if self.linear_refit_rms_nT is not None:
            d["linear_refit_rms_nT"] = _num(self.linear_refit_rms_nT)
        if self.linear_refit_refused is not None:
            d["linear_refit_refused"] = self.linear_refit_refused
        if self.thinned is not None:
            d["thinned"] = _plain(self.thinned)
        d["frames"] = _plain(self.frames)
        if self.discovery is not None:
            d["discovery"] = self.discovery.as_dict()
        if self.heldout_weak is not None:
            d["heldout_weak"] = _plain(self.heldout_weak)
        return d


