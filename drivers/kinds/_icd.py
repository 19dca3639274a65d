"""The counters of the ICD's samples, whatever bus carries them (serial frames, CAN frames): gaps in the unit's
counter, saturation, temperatures, and values no probe gives. Shared by the serial and CAN declarations."""

from __future__ import annotations

from ..declare import Counted


def icd_samples(intact: str, flags: str = "") -> tuple[Counted, ...]:
    """intact: how a sample that arrived whole is said on this bus ("with a good CRC"); flags: what the bus says of
    the ICD's flags byte, when it carries none."""
    return (
        Counted("seq_gaps", "gaps in the unit's sample counter"),
        Counted("samples_missed", "samples lost inside those gaps", fault="gaps", label="samples missed",
                what="{n:,} sample(s) missed in gaps of the unit's counter", beside=(("seq_gaps", "{n:,} gap(s)"),)),
        Counted("saturated_axes", "axis readings at an ADC rail, made NaN", fault="saturated", label="saturation",
                what="{n:,} saturated axis reading(s), NaN"),
        Counted("temp_invalid", "samples the unit flagged temperature-invalid (temperature NaN)" + flags,
                fault="temp_invalid",
                label="temperature invalid", what="{n:,} sample(s) flagged temperature-invalid"),
        Counted("implausible_samples", f"samples {intact} but values no probe gives (FLAG_IMPLAUSIBLE): kept, kept "
                                       f"out of the estimator", fault="implausible", label="implausible values",
                what=f"{{n:,}} sample(s) {intact} but values no probe gives, kept out of the estimator",
                beside=(("reserved_flags", "reserved flag bits {n:,}"),
                        ("beyond_full_scale", "axes beyond full scale {n:,}"),
                        ("zero_vectors", "zero vectors {n:,}"),
                        ("temp_out_of_range", "temperatures out of range {n:,}"))),
        Counted("reserved_flags", "... of which: frames with flag bits the ICD says are 0" + flags),
        Counted("beyond_full_scale", "... axes beyond the configured full scale (not at a rail)"),
        Counted("zero_vectors", "... probe vectors exactly (0, 0, 0)"),
        Counted("temp_out_of_range", "... probe temperatures outside the configured range (not flagged invalid)"),
    )


def picked(counted: tuple[Counted, ...], *names: str) -> tuple[Counted, ...]:
    """Those of `counted` named, in that order (a kind that has some of the ICD's sample counters)."""
    by = {c.name: c for c in counted}
    return tuple(by[n] for n in names)
