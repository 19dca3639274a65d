"""The unit's sample rate: the estimator's durations (window_s, check_every_s, update_every_s) are counted
in samples at it. A serial unit's frames carry a clock but the service must know the rate before the
first frame, so the configuration states it; the daemon checks it against the unit clock once."""

from __future__ import annotations

import numpy as np
import pytest

from fluxcal.drivers.block import SampleBlock
from fluxcal.drivers.errors import ConfigError
from fluxcal.service.wiring.config import config_from_dict
from fluxcal.service.wiring.daemon import Daemon, build_pipeline

#: what this file tests besides what it imports (tests/index.py: every module findable from its test)
COVERS = ("fluxcal.service.wiring.input",)


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


def test_a_sim_section_gives_the_rate_only_when_it_states_it():
    raw = {"unit": {"n_probes": 1}, "source": {"kind": "serial", "port": "/dev/pts/9", "n_probes": 1},
           "sim": {"probes": [{"position_m": [0.0, 0.0, 0.0]}]}}
    with pytest.raises(ConfigError, match=r"source\.rate_hz: missing"):
        config_from_dict(raw)
    raw["sim"]["rate_hz"] = 50.0
    assert config_from_dict(raw).rate_hz == 50.0


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
            d._rate.check(b)
    assert d.rate_checked
    assert len(messages) == int(said)
    if said:
        assert f"shows {actual:g} samples/s but source.rate_hz = {configured:g}" in messages[0]
        # a window configured in seconds lasts configured / actual of them
        assert f"last {configured / actual:.3g} x the seconds configured" in messages[0]
        assert messages[0].endswith(f"set source.rate_hz = {actual:g}")


def shifted(blocks: list[SampleBlock], dseq: int, dt: float) -> list[SampleBlock]:
    return [SampleBlock(t_s=b.t_s + dt, seq=b.seq + dseq, field_nT=b.field_nT, temp_C=b.temp_C, flags=b.flags)
            for b in blocks]


@pytest.mark.parametrize("dseq, dt", [(-40000, -30.0),          # the unit restarted: seq and clock from zero
                                      (70000 * 3, 70.0),        # an outage in which the 16-bit seq wrapped 3x
                                      (65536, 0.0),             # a restart the unwrapper took for a wrap
                                      (5, 4000.0)])             # a clock that jumped
def test_gaps_between_blocks_never_enter_the_rate(dseq, dt):
    """Only spans inside blocks are counted: whatever happened between two blocks (cable pulled, unit
    restarted, counters wrapped) the rate seen is the unit's."""
    messages: list[str] = []
    d = Daemon(config_from_dict(serial_config(rate_hz=500.0)), say=messages.append)
    for b in unit_blocks(500.0, 3.0, seq0=40000):
        d._rate.check(b)
    assert not d.rate_checked
    for b in shifted(unit_blocks(500.0, 3.0, seq0=40000 + 1500), dseq, 3.0 + dt):
        if not d.rate_checked:
            d._rate.check(b)
    assert d.rate_checked and messages == []


def test_a_clock_without_values_does_not_use_up_the_check():
    d = Daemon(config_from_dict(serial_config(rate_hz=500.0)), say=print)
    for b in unit_blocks(500.0, 10.0):
        d._rate.check(SampleBlock(t_s=np.full(b.n_samples, np.nan), seq=b.seq, field_nT=b.field_nT,
                                  temp_C=b.temp_C, flags=b.flags))
    assert not d.rate_checked


def test_can_has_no_unit_clock_to_check():
    raw = {"unit": {"n_probes": 1}, "source": {"kind": "can", "interface": "virtual", "channel": "x", "n_probes": 1,
                                               "rate_hz": 100.0}}
    assert Daemon(config_from_dict(raw)).rate_checked


def test_a_recording_from_before_the_rate_key_replays_as_its_live_run_did(tmp_path, capsys):
    """A serial run recorded before source.rate_hz existed was processed at 200 Hz: replay says so and
    does the same, so its output is still the live run's."""
    import json

    from fluxcal.drivers.sim.config import load_sim_config
    from fluxcal.drivers.sim.source import SimSource
    from fluxcal.service.io.recordings.reader import concat_corrected, read_recording
    from fluxcal.service.io.recordings.writer import McapLogger
    from fluxcal.service.wiring.cli import main

    src = SimSource(load_sim_config({"duration_s": 20.0, "rate_hz": 200.0, "motion": {"kind": "tumble", "rate_deg_s": 40.0},
                                     "probes": [{}, {"offset_nT": [30, 0, 0]}]}),
                    realtime=False)
    blocks = []
    while not src.exhausted:
        b = src.read(0.1)
        if b is not None:
            blocks.append(b)
    raw = serial_config()                                      # no rate_hz: as stored before the key existed
    raw["estimator"] = {"min_samples": 500, "check_every_s": 2.0, "window_s": 10.0, "gate_coverage": 0.1}
    log = McapLogger(tmp_path / "rec", unit="u", metadata={"config": json.dumps(raw), "probe_names": '["s1", "s2"]'})
    for b in blocks:
        log.write_raw(b)
    log.close()
    rec_file = next((tmp_path / "rec").glob("*.mcap"))
    assert main(["replay", str(rec_file), "--out", str(tmp_path / "out.mcap")]) == 0
    assert "names no source.rate_hz" in capsys.readouterr().err
    replayed = read_recording(tmp_path / "out.mcap").corrected_blocks
    pl = build_pipeline(config_from_dict(serial_config(rate_hz=200.0) | {"estimator": raw["estimator"]}))
    whole = SampleBlock.concat(blocks)
    parts = [whole.slice(a, a + 50) for a in range(0, whole.n_samples, 50)]
    live = [o.corrected for o in (pl.process(b) for b in parts) if o.corrected is not None]
    assert replayed and live
    got, want = concat_corrected(replayed), concat_corrected(live)
    assert np.array_equal(got.seq, want.seq) and np.array_equal(got.corrected_nT, want.corrected_nT, equal_nan=True)


@pytest.mark.parametrize("speed", [1.0, 4.0])
def test_a_simulated_unit_paced_by_the_wall_clock_runs_at_its_speed(speed):
    # [sim] speed: seconds of the unit's time per second of the wall clock (a demo or a test at 3x); the samples
    # are the same ones, only their pace changes
    import time

    from fluxcal.drivers.sim.config import load_sim_config
    from fluxcal.drivers.sim.source import SimSource

    cfg = {"duration_s": 0.0, "rate_hz": 500.0, "realtime": True, "speed": speed, "probes": [{}]}
    src = SimSource(load_sim_config(cfg))
    got, t0 = [], time.monotonic()
    while time.monotonic() - t0 < 1.0:
        b = src.read(0.05)
        if b is not None:
            got.append(b)
    wall = time.monotonic() - t0
    n = sum(b.n_samples for b in got)
    assert 0.8 * 500 * speed * wall < n < 1.1 * 500 * speed * wall + 50, (n, wall)
    fast = SimSource(load_sim_config({**cfg, "realtime": False}), realtime=False)
    parts = []
    while sum(len(p) for p in parts) < n:
        parts.append(fast.read(0.1).field_nT)
    want = np.concatenate(parts)[:n]
    np.testing.assert_array_equal(np.concatenate([b.field_nT for b in got]), want)
