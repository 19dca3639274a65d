"""Corrected vectors as a ROS 2 bag (service/io/recordings/ros2_writer.py, service/wiring/ros2_sink.py): what the
live service and a replay correct is written as sensor_msgs/msg/MagneticField (tesla, header stamps, frame_id the
probe, covariance zero: unknown) into a rosbag2 directory that rosbags' reader and mcap-ros2-support's decoder read
back bit for bit."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("rosbags", reason="rosbags checks the bag: pip install 'fluxcal[ros2]'")

from fluxcal.drivers.errors import ConfigError
from fluxcal.service.io.recordings.reader import read_recording
from fluxcal.service.io.recordings.ros2_writer import Ros2BagWriter
from fluxcal.service.wiring.ros2_sink import Ros2BagSink, replay_ros2_sink

ROOT = Path(__file__).resolve().parents[2]

ORIGIN_NS = 1_750_000_000_000_000_000


def read_bag(path: Path) -> dict[str, list]:
    """Per topic: (bag timestamp, message) as rosbags reads them."""
    from rosbags.highlevel import AnyReader

    out: dict[str, list] = {}
    with AnyReader([path]) as r:
        for conn, ts, raw in r.messages():
            assert conn.msgtype == "sensor_msgs/msg/MagneticField"
            out.setdefault(conn.topic, []).append((ts, r.deserialize(raw, conn.msgtype)))
    return out


def test_replayed_corrected_vectors_read_back_by_rosbags(tmp_path):
    rec = read_recording("recordings/grad1-sim-30s.mcap")
    sink = Ros2BagSink.open(tmp_path / "out", unit="grad1", probe_names=rec.probe_names, raw=True,
                            stamp_origin_ns=ORIGIN_NS)
    for b in rec.raw_blocks:
        sink.on_raw(b)
    for b in rec.corrected_blocks:
        sink.on_corrected(b)
    sink.close()
    sink.close()                                                # twice: nothing more
    got = read_bag(tmp_path / "out")
    cor = rec.corrected
    assert set(got) == {f"/fluxcal/grad1/{p}/magnetic_field{r}" for p in ("s1", "s2") for r in ("", "_raw")}
    for k, p in enumerate(rec.probe_names):
        msgs = got[f"/fluxcal/grad1/{p}/magnetic_field"]
        assert len(msgs) == cor.n_samples
        stamps = np.array([m.header.stamp.sec * 1_000_000_000 + m.header.stamp.nanosec for _, m in msgs])
        np.testing.assert_array_equal(stamps, ORIGIN_NS + np.round(cor.t_s * 1e9).astype(np.int64))
        np.testing.assert_array_equal([ts for ts, _ in msgs], stamps)
        v = np.array([[m.magnetic_field.x, m.magnetic_field.y, m.magnetic_field.z] for _, m in msgs])
        np.testing.assert_array_equal(v, cor.corrected_nT[:, k] * 1e-9)
        assert {m.header.frame_id for _, m in msgs} == {p}
        assert all(not np.any(m.magnetic_field_covariance) for _, m in msgs)
        raw = got[f"/fluxcal/grad1/{p}/magnetic_field_raw"]
        assert len(raw) == rec.raw.n_samples
    # the same bag through mcap-ros2-support's decoder, and back into fluxcal as lab data
    pytest.importorskip("mcap_ros2")
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    with open(tmp_path / "out" / "out_0.mcap", "rb") as f:
        first = next(make_reader(f, decoder_factories=[DecoderFactory()]).iter_decoded_messages(
            topics=["/fluxcal/grad1/s2/magnetic_field"]))
    assert first[3].magnetic_field.z == cor.corrected_nT[0, 1, 2] * 1e-9
    from fluxcal.service.io.recordings.load import load_data
    from fluxcal.service.io.recordings.ros2 import Ros2Mapping

    lab = load_data(tmp_path / "out", mapping=Ros2Mapping(probes={"s1": "/fluxcal/grad1/s1/magnetic_field",
                                                                  "s2": "/fluxcal/grad1/s2/magnetic_field"}))
    np.testing.assert_allclose(lab.block.field_nT, cor.corrected_nT, rtol=1e-15)


def test_the_live_service_writes_a_bag(tmp_path):
    """A sink given to the daemon (as tests/wiring/test_sinks.py's counter): every corrected sample of the run in the bag."""
    from test_sinks import _run

    sink = replay_ros2_sink(tmp_path / "live_bag", _Cfg(), origin_unix_s=ORIGIN_NS / 1e9)
    _, rec = _run(tmp_path, [sink])
    got = read_bag(tmp_path / "live_bag")
    cor = rec.corrected
    for k, p in enumerate(("s1", "s2")):
        v = np.array([[m.magnetic_field.x, m.magnetic_field.y, m.magnetic_field.z]
                      for _, m in got[f"/fluxcal/grad1/{p}/magnetic_field"]])
        ok = np.isfinite(cor.corrected_nT[:, k]).all(axis=1)
        np.testing.assert_array_equal(v, cor.corrected_nT[ok, k] * 1e-9)
    assert sink.writer.skipped == int((~np.isfinite(cor.corrected_nT).all(axis=2)).sum())


class _Cfg:
    """The two fields of a configuration the sink takes (the test's service config names its unit grad1)."""

    class unit:
        name = "grad1"

    probe_names = ["s1", "s2"]


def test_bad_places_and_bad_vectors(tmp_path):
    (tmp_path / "full").mkdir()
    (tmp_path / "full" / "x").write_text("x")
    with pytest.raises(ConfigError, match="--ros2-out: .*full.*cannot write a ROS 2 bag there"):
        Ros2BagSink.open(tmp_path / "full", unit="u", probe_names=["s1"])
    from fluxcal.drivers.block import SampleBlock

    w = Ros2BagWriter(tmp_path / "b", unit="u", probe_names=["s1"])
    f = np.ones((4, 1, 3)) * 1000.0
    f[1, 0, 2] = np.nan
    w.write_raw(SampleBlock(t_s=np.arange(4.0), seq=np.arange(4), field_nT=f, temp_C=np.zeros((4, 1)),
                            flags=np.zeros(4, np.uint8)))
    w.close()
    assert w.skipped == 1 and w.status()["topics"] == {"/fluxcal/u/s1/magnetic_field_raw": 3}
    assert len(read_bag(tmp_path / "b")["/fluxcal/u/s1/magnetic_field_raw"]) == 3
    # the sink says at close what the bag holds and what it could not
    said: list[str] = []
    sink = Ros2BagSink.open(tmp_path / "c", unit="u", probe_names=["s1"], raw=True)
    sink.say = said.append
    sink.on_raw(SampleBlock(t_s=np.arange(4.0), seq=np.arange(4), field_nT=f, temp_C=np.zeros((4, 1)),
                            flags=np.zeros(4, np.uint8)))
    sink.close()
    assert said == [f"ROS 2 bag {tmp_path / 'c'}: 3 message(s) on 1 topic(s); 1 probe-sample(s) not written (a "
                    f"non-finite axis, or a stamp before the UNIX epoch: sensor_msgs has no place for either)"]


def test_the_configuration_turns_the_bag_on_and_replay_writes_one(tmp_path, capsys):
    """[ros2] enabled: the running service writes a bag of its own (stamps: UNIX time from the first block on);
    `replay --ros2-out DIR` writes the replay's corrected vectors, read back by rosbags."""
    import time

    from test_recording import service_config

    from fluxcal.service.wiring.cli import main
    from fluxcal.service.wiring.config import load_config
    from fluxcal.service.wiring.daemon import Daemon

    text = (Path(service_config(tmp_path, run_s=40, realtime=False)).read_text()
            .replace('transport = "pty"', 'transport = "direct"') + f'\n[ros2]\nenabled = true\ndir = "{tmp_path}/bags"\n')
    (tmp_path / "c.toml").write_text(text)
    before = time.time_ns()
    assert Daemon(load_config(tmp_path / "c.toml"), say=lambda m: None).run() == 0
    bags = sorted((tmp_path / "bags").iterdir())
    assert len(bags) == 1 and bags[0].name.startswith("grad1-")
    got = read_bag(bags[0])
    rec = read_recording(tmp_path / "rec")
    n = sum(b.n_samples for b in rec.corrected_blocks)
    assert n > 0 and all(len(got[f"/fluxcal/grad1/{p}/magnetic_field"]) == n for p in ("s1", "s2"))
    stamps = [m.header.stamp.sec for _, m in got["/fluxcal/grad1/s1/magnetic_field"]]
    assert before // 10**9 - 1 <= stamps[0] <= time.time() + 40        # UNIX seconds, not the unit's from 0
    # the replay of that run, through the command line
    capsys.readouterr()
    assert main(["replay", str(tmp_path / "rec"), "--ros2-out", str(tmp_path / "again")]) == 0
    assert "ROS 2 bag written to" in capsys.readouterr().out
    again = read_bag(tmp_path / "again")
    for p in ("s1", "s2"):
        live = np.array([[m.magnetic_field.x, m.magnetic_field.y, m.magnetic_field.z]
                         for _, m in got[f"/fluxcal/grad1/{p}/magnetic_field"]])
        replayed = np.array([[m.magnetic_field.x, m.magnetic_field.y, m.magnetic_field.z]
                             for _, m in again[f"/fluxcal/grad1/{p}/magnetic_field"]])
        np.testing.assert_array_equal(live, replayed)                # this machine's arithmetic: bit for bit


def test_replay_refuses_a_bag_it_cannot_write_before_any_work(tmp_path, capsys):
    """`replay --out o.mcap --ros2-out blocker/y` with blocker a file: exit 2 before anything is read or written (no
    o.mcap without a footer left behind)."""
    from fluxcal.service.wiring.cli import main

    (tmp_path / "blocker").write_text("a file")
    rc = main(["replay", str(ROOT / "recordings" / "grad1-sim-30s.mcap"), "--out", str(tmp_path / "o.mcap"),
               "--ros2-out", str(tmp_path / "blocker" / "y")])
    assert rc == 2
    assert "--ros2-out" in capsys.readouterr().err
    assert not (tmp_path / "o.mcap").exists()
