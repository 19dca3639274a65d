"""The data's scale said: data whose size is implausible for nT (µT, counts), and a given total field far off the
data's scale (fluxcal.service.numerics.field_scale), for fit and for the input preparation of diagnose
(prepare.effect_input)."""

from __future__ import annotations

from typing import Any, Sequence

import numpy as np


def field_scale_notes(said: Any, source: str, field_nT: Any, probe_names: Sequence[str], *, centres_nT: Any = None,
                      total_nT: Any = None, total_source: str = "") -> list[str]:
    """Data whose size is implausible for nT (µT, counts), and a given total field far off the data's scale, said
    (the latter loudly) whatever the output format; returns them, loud first, for the result's warnings."""
    from fluxcal.service.numerics.field_scale import field_scale_warnings

    if total_nT is not None and not isinstance(total_nT, (int, float)):
        finite = np.asarray(total_nT, dtype=np.float64)
        finite = finite[np.isfinite(finite)]
        total_nT = float(np.median(finite)) if finite.size else None     # a ref_total column
    warnings, loud = field_scale_warnings(field_nT, probe_names, centres_nT, total_nT, total_source)
    for w in warnings:
        said("field-scale", f"{source}: {w}")
    for w in loud:
        said("field-scale", f"{source}: {w}", level="loud")
    return loud + warnings


def data_scale_notes(said: Any, prep: Any, data: Any, judged: Sequence[Any]) -> list[str]:
    """field_scale_notes of the prepared `data` (a LabData) as fit, diagnose and inspect say them: the data's size about
    the determinacy gate's centres (`judged`), against the total field fit takes, named in total_words; nothing until
    the gate takes every probe (of samples that determine nothing, a sphere through 6 of them gave two sizes and a
    unit guessed from each: fit, refused first, said neither)."""
    from fluxcal.service.wiring.fitting import gate_centres, total_field

    if not all(j.determined for j in judged):
        return []

    total = total_field(data, prep.total_nT)
    return field_scale_notes(said, prep.source, data.block.field_nT, data.probe_names, centres_nT=gate_centres(judged),
                             total_nT=None if total.source == "estimated" else total.values,
                             total_source=total_words(prep, total.source))


def total_words(prep: Any, source: str) -> str:
    """The total field fit takes, in the words fit, diagnose and inspect say it with: the site or the track (the
    prepared data's `total_source`), the configuration, the ref_total column; `source`: total_field's."""
    if prep.site is not None or prep.track is not None:
        return prep.total_source
    return {"config": prep.origin or "configured", "ref_total": "the ref_total column"}.get(source, source)


__all__ = ["data_scale_notes", "field_scale_notes", "total_words"]
