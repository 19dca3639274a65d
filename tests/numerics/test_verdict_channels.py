"""The verdict per channel (issue 40): "explained" and "at the floor" only where no channel's residual stands above
signature.CHANNEL_FACTOR of its own floor both held out and in the fit; a channel left above is named with what it follows, discovery runs,
and no sentence says "down to the noise" beside it.

- worlds where a catalogue term takes part of an effect (a coil that saturates, a supply's exponential load: `column`
  takes their linear part), white and 1/f noise: "partly explained" naming the channels left, and discovery runs;
- worlds the catalogue explains fully (a heater coupled linearly, a hidden temperature effect under 1/f noise): the
  verdict and its effect as before, no channel above;
- on every one, the verdict, the per-channel table and where-it-fails agree (agree()).

A representative subset: bench/bench_discovery.py --part channels runs ten such worlds and counts."""

from __future__ import annotations

import numpy as np
import pytest
from shape_worlds import shape_world

from fluxcal.service.numerics.diagnose import diagnose, summary_text
from fluxcal.service.numerics.diagnose.fits import heldout
from fluxcal.service.numerics.diagnose.signature import CHANNEL_FACTOR, CHANNELS_SAID

#: the worlds: 6,500 samples at 20 Hz, the effect 1.5 times shape_worlds' size (bench/bench_shapes.py --part channels
#: runs ten such worlds of 8,000: "partly explained" with the channels named in 9, the tenth's `column` held out
#: loses). On 6,500 the channel furthest above stands at 1.36, 1.57 and 1.73 times its floor (held out and fitted)
#: against CHANNEL_FACTOR 1.15 (1.45, 1.56, 1.90 on 8,000); on 5,000 two of the three fell below it
N = 6500
SCALE = 1.5


def agree(d) -> None:
    """The verdict, the per-channel figures and where-it-fails tell one story (assertions)."""
    v = d.verdict
    text = summary_text(d)
    above = v.get("channels_above") or []
    best = d.best
    fit = best.fit if best is not None and best.fit is not None else d.fit
    held = heldout(fit).channel_rms_nT / d.channel_noise_nT
    fitted = fit.channels.rms_nT / d.channel_noise_nT
    if v["kind"] in ("explained", "at the floor"):
        assert not above and not np.any((held > CHANNEL_FACTOR * 1.001) & (fitted > CHANNEL_FACTOR * 1.001)), (
            held, fitted, text)
    else:
        assert "down to the noise" not in text, text
    for c in above:
        assert c["ratio"] > CHANNEL_FACTOR and c["rms_nT"] > CHANNEL_FACTOR * c["floor_nT"], c
    for c in above[:CHANNELS_SAID]:                     # the furthest named, the rest counted
        assert c["channel"] in v["left"], (c, v["left"])
        for follow in c["follows"]:                     # what it follows is what where-it-fails says of that channel
            assert follow["observable"] in v["left"], (follow, v["left"])
    if len(above) > CHANNELS_SAID:
        assert f"and {len(above) - CHANNELS_SAID} more channel" in v["left"], v["left"]
    if "down to the noise" in text:
        assert v["kind"] == "at the floor" and not above, text


@pytest.mark.slow
@pytest.mark.parametrize("kind, seed, pink", [("saturating coil", 1, 0.0), ("saturating coil", 4, 0.1),
                                              ("exponential supply", 2, 0.1)])
def test_a_channel_left_above_its_floor_is_named_and_discovery_runs(kind, seed, pink):
    data = shape_world(kind, seed, pink=pink, n=N, scale=SCALE)
    before = diagnose(data, discover=False)
    text = summary_text(before)
    v = before.verdict
    assert v["kind"] == "partly explained" and v["effect"] == "column", text
    assert v["channels_above"] and any(c["channel"].startswith({"saturating coil": "s1", "exponential supply": "s3"}
                                                               [kind]) or "-" in c["channel"]
                                       for c in v["channels_above"]), text
    assert "left above their own floor" in v["left"], v["left"]
    agree(before)
    after = diagnose(data)                                  # discovery runs by itself
    assert after.discovery is not None, summary_text(after)
    agree(after)


def heater_world(seed: int):
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).parent))
    from test_diagnose_beyond import heater_world as world

    return world(seed, coupled=True)


@pytest.mark.slow
def test_a_world_the_catalogue_explains_fully_is_explained_as_before():
    d = diagnose(heater_world(1))
    assert d.verdict["kind"] == "explained" and d.verdict["effect"] == "column", summary_text(d)
    assert d.verdict["channels_above"] == []
    agree(d)
