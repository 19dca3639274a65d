"""The unit's sample rate: the estimator's durations (window_s, check_every_s, update_every_s) are counted
in samples at it. A serial unit's frames carry a clock but the service must know the rate before the
first frame, so the configuration states it; the daemon checks it against the unit clock once."""

from __future__ import annotations

import numpy as np
import pytest

from drivers.block import SampleBlock
from drivers.errors import ConfigError
from service.config import config_from_dict
from service.daemon import Daemon, build_pipeline


def serial_config(**source) -> dict:
    return {"unit": {"name": "u", "n_probes": 2},
            "source": {"kind": "serial", "port": "/dev/ttyUSB0", "n_probes": 2, **source},
            "estimator": {"window_s": 30.0, "check_every_s": 5.0, "update_every_s": 0.5}}


def test_a_serial_configuration_without_the_rate_names_the_key():
    with pytest.raises(ConfigError) as e:
        config_from_dict(serial_config(), "unit.toml")
    assert str(e.value).startswith("unit.toml: source.rate_hz: missing")
    with pytest.raises(ConfigError, match=r"source\.rate_hz: -5\.0"):
        config_from_dict(serial_config(rate_hz=-5.0), "unit.toml")
    with pytest.raises(ConfigError, match=r"source\.rate_hz: missing"):
        config_from_dict({"unit": {"n_probes": 1}, "source": {"kind": "replay", "path": "x.mcap"}}, "r.toml")


def test_a_rate_that_differs_from_the_simulated_units_is_refused():
    raw = {"unit": {"n_probes": 1}, "source": {"kind": "serial", "port": "/dev/pts/9", "n_probes": 1, "rate_hz": 500.0},
           "sim": {"rate_hz": 200.0, "probes": [{"position_m": [0.0, 0.0, 0.0]}]}}
    with pytest.raises(ConfigError, match=r"source\.rate_hz: 500\.0 differs from sim\.rate_hz = 200\.0"):
        config_from_dict(raw, "x.toml")


@pytest.mark.parametrize("rate", [200.0, 1000.0])
def test_the_estimators_durations_are_counted_at_the_configured_rate(rate):
    pl = build_pipeline(config_from_dict(serial_config(rate_hz=rate)))
    assert pl.ring.capacity == int(30.0 * rate)                  # window_s
    assert pl.chunk == int(round(0.5 * rate))                    # update_every_s
    assert pl.check_every_chunks * pl.chunk == int(round(5.0 * rate))   # check_every_s


def unit_blocks(rate_hz: float, seconds: float, block_n: int = 8, seq0: int = 100) -> list[SampleBlock]:
    n = int(seconds * rate_hz)
    seq = np.arange(seq0, seq0 + n, dtype=np.int64)
    t = (seq - seq0) / rate_hz + 12.5                        # the unit clock, any origin
    field = np.zeros((n, 2, 3))
    return [SampleBlock(t_s=t[a:a + block_n], seq=seq[a:a + block_n], field_nT=field[a:a + block_n],
                        temp_C=np.full((min(block_n, n - a), 2), 20.0), flags=np.zeros(min(block_n, n - a), np.uint8))
            for a in range(0, n, block_n)]


@pytest.mark.parametrize("actual, configured, said", [(1000.0, 200.0, True), (200.0, 200.0, False),
                                                      (201.0, 200.0, False), (190.0, 200.0, True)])
def test_the_daemon_says_once_when_the_unit_clock_disagrees_with_the_rate(actual, configured, said):
    messages: list[str] = []
    d = Daemon(config_from_dict(serial_config(rate_hz=configured)), say=messages.append)
    for b in unit_blocks(actual, 12.0):
        if not d.rate_checked:
            d._check_rate(b)
    assert d.rate_checked
    assert len(messages) == int(said)
    if said:
        assert f"shows {actual:.4g} samples/s" in messages[0]
        assert f"set rate_hz = {actual:.4g}" in messages[0]


def test_the_rate_check_starts_again_after_the_unit_restarts():
    """A unit that restarts (seq and clock from zero) before the check ends is measured afresh, not
    across the restart."""
    messages: list[str] = []
    d = Daemon(config_from_dict(serial_config(rate_hz=500.0)), say=messages.append)
    for b in unit_blocks(500.0, 3.0, seq0=40000):
        d._check_rate(b)
    assert not d.rate_checked
    for b in unit_blocks(500.0, 6.0, seq0=0):
        if not d.rate_checked:
            d._check_rate(b)
    assert d.rate_checked and messages == []
