"""The advice never asks to log what the data carry (issue 30): every path that builds advice (signature.describe,
its time and follows branches, diagnose's wrappers: a weak held-out test, a gross stretch, discovery's sentence),
each with every combination of what the data carry (own or borrowed temperatures, logged columns, a scalar reference,
one probe or an array). Every request to log something goes through signature.LOG_ASKS, so a new path cannot ask
for a log unseen: the test also fails on any 'log ...' that is not one of those."""

from __future__ import annotations

import itertools
import re

import numpy as np
import pytest

from fluxcal.service.numerics.diagnose.signature import LOG_ASKS, Carried, describe

#: what each request asks for, and when the data carry it already
CARRIED_BY = {
    "temperature": lambda c: c.temperature,
    "reference": lambda c: c.reference or c.vector_reference,
    "second probe": lambda c: c.probes > 1 or c.reference,
    "phase": lambda c: False,            # the phase or speed of something no logged column follows
    "column": lambda c: False,           # something not logged yet (a current, a voltage)
}

CARRIED = [Carried(temperatures=t, borrowed=b, columns=cols, reference=ref, probes=p)
           for (t, b), cols, ref, p in itertools.product(
               [((), ()), (("s1", "s2", "s3"), ()), (("s1",), ("s2", "s3"))], [(), ("heater_A", "fan_hz")],
               [False, True], [1, 3])
           if not (p == 1 and b)]


def _sig(**kw):
    base = {"scalar_rms_nT": 3.0, "scalar_noise_nT": 1.0, "shared_fraction": None, "difference_rms_nT": 3.0,
            "difference_noise_nT": 1.0, "half_power_period_s": 30.0, "spectral_slope": None, "line_hz": None,
            "probe_share": None, "follows": [], "frames": None}
    base.update(kw)
    return base


def _follow(obs, strength=0.6, band=None):
    f = {"observable": obs, "channel": "s2.scalar", "strength": strength}
    if band:
        f["band"] = band
    return f


OBSERVABLES = ["temperature", "temperature rate", "temperature, delayed", "angular rate", "orientation", "heading",
               "field magnitude", "heater_A", "heater_A x field direction", "temperature x field direction"]

#: one signature per branch of describe (and of _time_advice and _follows_advice below it)
BRANCHES = {
    **{f"strong {o}": _sig(follows=[_follow(o)]) for o in OBSERVABLES},
    "line": _sig(line_hz=1.51),
    "common, no differences": _sig(shared_fraction=0.9, difference_rms_nT=1.0),
    "own flicker": _sig(shared_fraction=0.05, spectral_slope=-1.0, probe_share={"s1": 0.3, "s2": 0.35, "s3": 0.35}),
    "time, one probe's own": _sig(shared_fraction=0.1, follows=[_follow("time")],
                                  probe_share={"s1": 0.05, "s2": 0.9, "s3": 0.05}),
    "time, each probe's own": _sig(shared_fraction=0.1, follows=[_follow("time")],
                                   probe_share={"s1": 0.3, "s2": 0.35, "s3": 0.35}),
    "time, common": _sig(shared_fraction=0.9, follows=[_follow("time")]),
    "time, unknown share": _sig(follows=[_follow("time")]),
    "weak frequency": _sig(follows=[_follow("frequency", 0.3, band="1.2-2.57 Hz")]),
    **{f"weak {o}": _sig(follows=[_follow(o, 0.3)]) for o in OBSERVABLES},
    "nothing follows": _sig(),
}


def _asks(advice: str) -> list[str]:
    """The requests to log in a piece of advice; fails on a 'log' that is none of LOG_ASKS."""
    found = [k for k, phrase in LOG_ASKS.items() if phrase in advice]
    rest = advice
    for k in found:
        rest = rest.replace(LOG_ASKS[k], "")
    assert not re.search(r"\blog\b", rest), f"a request to log that is not in LOG_ASKS: {advice!r}"
    return found


@pytest.mark.parametrize("branch", sorted(BRANCHES))
def test_no_advice_asks_to_log_what_the_data_carry(branch):
    seen = set()
    for carried in CARRIED:
        _, advice = describe(dict(BRANCHES[branch]), carried)
        assert advice, (branch, carried)
        for k in _asks(advice):
            assert not CARRIED_BY[k](carried), f"{branch}: asks {LOG_ASKS[k]!r} of data carrying it: {carried}"
        if carried.temperature:
            assert "temperature the data do not carry" not in advice, (branch, advice)
        if carried.columns and branch in ("line", "weak frequency"):
            assert "heater_A, fan_hz" in advice, advice              # the logged columns that do not follow it
        seen.add(advice)
    assert seen


def test_the_issue_cases_are_told_what_the_data_carry():
    # a gradiometer whose differences follow temperature, both temperatures logged: no "log the temperatures"
    both = Carried(temperatures=("s1", "s2"), probes=2, reference=True)
    _, advice = describe(_sig(shared_fraction=0.1, follows=[_follow("time")],
                              probe_share={"s1": 0.5, "s2": 0.5}), both)
    assert "log the sensors' temperatures" not in advice and "temperature the logged one does not follow" in advice
    # a disturbance at the phase of a logged fan: not "log it"; the logged columns are named
    fan = Carried(columns=("fan_hz",), probes=1)
    _, advice = describe(_sig(follows=[_follow("frequency", 0.3, band="1.2-2.57 Hz")]), fan)
    assert "log it" not in advice and "fan_hz" in advice


def test_a_band_is_no_cause_where_the_probe_turns_at_its_rates_or_a_logged_column_follows():
    """A residual band where the field the probe reads varies most is at the rates it turns: a misfit of its direction,
    not something turning near it (a hand-turned board's gyros logged, it was asked to log the phase of what turns);
    a logged column the residual follows nearly as well is named first (a servo's magnet, 45 % through the field's
    direction beside a band at 48 %); a band that holds little of the turning and no column is a disturbance."""
    gyros = Carried(columns=("gyro_x", "gyro_y", "gyro_z"), probes=1)
    band = {**_follow("frequency", 0.31, band="0.0933-0.186 Hz"), "band_hz": [0.0933, 0.186]}
    _, advice = describe(_sig(follows=[{**band, "turning_share": 0.32}]), gyros)
    assert advice.startswith("a misfit at the rates the probe turns (0.0933-0.186 Hz holds 32 % of the turning")
    assert _asks(advice) == [], advice
    _, advice = describe(_sig(follows=[{**band, "turning_share": 0.05}]), gyros)
    assert advice.startswith("a narrow-band disturbance at 0.0933-0.186 Hz")
    servo = Carried(columns=("servo_deg", "gyro_x"), probes=1)
    for strength, named in ((0.45, True), (0.2, False)):
        follows = [{**band, "strength": 0.48, "turning_share": 0.25}, _follow("servo_deg x field direction", strength)]
        _, advice = describe(_sig(follows=follows), servo)
        assert advice.startswith("a coupling of servo_deg seen through the field's direction") == named, advice


def test_the_turning_share_is_of_the_fields_direction_not_of_a_disturbance_at_a_still_probe():
    """A still probe's field varies only by what disturbs it: a pump's 1.5 Hz was 0.94 of the raw field's variation
    and would have been read as the probe turning (review). The share is of the turning of the field's direction,
    and nothing where it turns by less than TURN_MIN_RAD in the band."""
    from fluxcal.service.numerics.diagnose.where import TURN_MIN_RAD, TURNING_SHARE, band_share

    dt = 0.02
    t = np.arange(6000) * dt
    still = np.tile([20_000.0, 5_000.0, 45_000.0], (t.size, 1))
    still[:, 0] += 40.0 * np.sin(2 * np.pi * 1.5 * t)                       # a pump's field, 40 nT at 1.5 Hz
    assert band_share(still, dt, (1.0, 2.0)) == 0.0
    a = 2 * np.pi * 0.12 * t                                                # turned about z at 0.12 Hz
    turned = 48_000.0 * np.column_stack([0.6 * np.cos(a), 0.6 * np.sin(a), np.full(t.size, 0.8)])
    share = band_share(turned, dt, (0.09, 0.19))
    assert share > 0.95 and share >= TURNING_SHARE and TURN_MIN_RAD < 0.6
    assert band_share(turned + still - still.mean(0), dt, (1.0, 2.0)) < 0.01     # turning, with the pump elsewhere


def test_the_wrappers_of_diagnose_ask_for_no_log():
    from types import SimpleNamespace

    from fluxcal.service.numerics.diagnose.diagnostics import _weak_advice
    from fluxcal.service.numerics.diagnose.stretch import stretch_advice

    weak = {"reason": "the blocks are separate turns", "advice": "a recording that repeats its motion would decide"}
    cand = SimpleNamespace(testable=True, fit=object(), n_params=3, p_value=1e-9, bic_delta=-50.0, effect="column",
                           rms_nT=244.3)
    for advice in (_weak_advice(weak, [cand], None), _weak_advice(weak, [], "something"),
                   stretch_advice({"t_start_s": 1.0, "t_end_s": 2.0, "ratio": 4.0}, None)):
        assert _asks(advice) == [], advice
    assert "column explains most" in _weak_advice(weak, [cand], None)


def test_a_catalogue_term_asks_for_a_log_only_where_the_data_lack_it():
    import numpy as np

    from fluxcal.service.numerics.effects import Ambient, Column
    from fluxcal.service.numerics.effects.base import EffectData

    n = 200
    data = EffectData(t_s=np.arange(n) * 0.1, raw_nT=np.ones((n, 2, 3)), temp_C=np.full((n, 2), np.nan),
                      probe_names=["s1", "s2"], ref_total_nT=np.full(n, 5e4),
                      extras={"heater_A": np.sin(np.arange(n))})
    assert Column().why_unavailable(data) is None                 # its 'log the heater currents' is not said
    assert "follows the ambient field already" in Ambient().why_unavailable(data)   # nor ambient's 'log a reference'
    data.extras.clear()                                           # no column: column asks for one, not for ref_total
    why = Column().why_unavailable(data)
    assert "log the heater or motor currents" in why and "reference" not in why, why
