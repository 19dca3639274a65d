"""ROS 2 bags as lab data (service/io/recordings/ros2.py): bags written by the ecosystem's own libraries
(mcap-ros2-support's writer, rosbags' writer in sqlite3 and MCAP storage) with two MagneticField topics, an Imu and
two Temperature topics give the same LabData as the same samples through the lab CSV, and `fit` and `diagnose` the
same numbers (to 1e-9 relative); topics are chosen by options; streams at different instants are matched as
numerics/merge.py says (never borrowed); `fluxcal inspect` lists the mapping."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

pytest.importorskip("mcap_ros2", reason="the ROS 2 reader's optional package: pip install 'fluxcal[ros2]'")
pytest.importorskip("rosbags", reason="the ROS 2 reader's optional package: pip install 'fluxcal[ros2]'")

from fluxcal.drivers.errors import DataError
from fluxcal.drivers.sim import Unit, load_sim_config
from fluxcal.service.io.recordings.inspect import inspect_file
from fluxcal.service.io.recordings.load import load_data
from fluxcal.service.io.recordings.ros2 import Ros2Mapping
from fluxcal.service.numerics.merge import (
    Q_NED_FROM_ENU,
    euler_from_quaternion,
    ned_from_enu_quaternion,
    quaternion_from_euler,
    quaternion_product,
)
from fluxcal.service.wiring import cli

#: what this file tests besides what it imports (tests/index.py: every module findable from its test)
COVERS = ("fluxcal.service.io.recordings.inspect",)

MAG, IMU, TEMP, NAV = ("sensor_msgs/msg/MagneticField", "sensor_msgs/msg/Imu", "sensor_msgs/msg/Temperature",
                       "sensor_msgs/msg/NavSatFix")
T0_NS = 1_760_000_000_123_456_789          # 2025-10-09: UNIX stamps
RATE = 50.0


def _typestore():
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS2_HUMBLE)


def simulated(n: int = 3000, seed: int = 3) -> dict:
    """Two probes tumbling with a temperature ramp: the samples, their attitude and their ROS stamps."""
    rng = np.random.default_rng(seed)
    probes = [{"position_m": [0.2 * k, 0.0, 0.0], "scale": (1 + 0.02 * rng.standard_normal(3)).tolist(),
               "nonorth_deg": rng.uniform(-2, 2, 3).tolist(), "misalign_deg": rng.uniform(-3, 3, 3).tolist(),
               "offset_nT": rng.uniform(-400, 400, 3).tolist(), "noise_nT": 0.8} for k in range(2)]
    cfg = load_sim_config({"seed": seed, "rate_hz": RATE, "duration_s": n / RATE,
                           "field": {"total_nT": 50500.0, "inclination_deg": 64.0, "declination_deg": 2.0},
                           "motion": {"kind": "tumble", "rate_deg_s": 30.0, "tumble_period_s": 7.0},
                           "temperature": {"start_C": 18.0, "ramp_C_per_h": 60.0, "amplitude_C": 3.0,
                                           "period_s": 20.0},
                           "probes": probes})
    s = Unit(cfg).digitise(0, cfg.n_samples)
    b = s.to_block()
    r = s.world.attitude
    heel = np.degrees(np.arctan2(r[:, 2, 1], r[:, 2, 2]))
    pitch = np.degrees(-np.arcsin(np.clip(r[:, 2, 0], -1, 1)))
    azimuth = np.degrees(np.arctan2(r[:, 1, 0], r[:, 0, 0]))
    ns = T0_NS + np.round(b.t_s * 1e9).astype(np.int64)
    return {"ns": ns, "t": (ns - ns[0]) / 1e9, "field": b.field_nT, "temp": b.temp_C,
            "euler": np.column_stack([heel, pitch, azimuth])}


def enu_quaternions(euler: np.ndarray) -> np.ndarray:
    """The ROS orientation (platform -> ENU) of fluxcal's platform -> NED Euler angles."""
    q_ned = quaternion_from_euler(euler[:, 0], euler[:, 1], euler[:, 2])
    conj = Q_NED_FROM_ENU * np.array([1.0, -1.0, -1.0, -1.0])
    return quaternion_product(conj, q_ned)


def write_csv(path, d: dict) -> None:
    cols = ["t"] + [f"s{k + 1}_{a}" for k in range(2) for a in "xyz"] + ["s1_temp", "s2_temp", "heel_deg",
                                                                          "pitch_deg", "azimuth_deg"]
    rows = np.column_stack([d["t"], d["field"].reshape(len(d["t"]), 6), d["temp"], d["euler"]])
    np.savetxt(path, rows, delimiter=",", header=",".join(cols), comments="", fmt="%.17g")


def _msgs(d: dict):
    """(topic, type, ns, message as a dict) in time order: the data as ROS 2 messages."""
    q = enu_quaternions(d["euler"])
    zero9 = [0.0] * 9
    for i, ns in enumerate(d["ns"].tolist()):
        stamp = {"sec": ns // 1_000_000_000, "nanosec": ns % 1_000_000_000}
        for k in range(2):
            f = d["field"][i, k] * 1e-9
            yield (f"/mag{k + 1}/field", MAG, ns, {"header": {"stamp": stamp, "frame_id": "base_link"},
                   "magnetic_field": {"x": f[0], "y": f[1], "z": f[2]}, "magnetic_field_covariance": zero9})
            yield (f"/mag{k + 1}/temperature", TEMP, ns, {"header": {"stamp": stamp, "frame_id": "base_link"},
                   "temperature": float(d["temp"][i, k]), "variance": 0.0})
        w, x, y, z = q[i]
        yield ("/imu/data", IMU, ns, {"header": {"stamp": stamp, "frame_id": "base_link"},
               "orientation": {"w": w, "x": x, "y": y, "z": z}, "orientation_covariance": zero9,
               "angular_velocity": {"x": 0.0, "y": 0.0, "z": 0.0}, "angular_velocity_covariance": zero9,
               "linear_acceleration": {"x": 0.0, "y": 0.0, "z": 9.8}, "linear_acceleration_covariance": zero9})


def write_mcap_ros2(path, messages) -> None:
    """With mcap-ros2-support's own writer (the message definitions as rosbag2's MCAP storage writes them)."""
    from mcap_ros2.writer import Writer

    ts = _typestore()
    with open(path, "wb") as f:
        w = Writer(f)
        schemas = {}
        for topic, kind, ns, msg in messages:
            if kind not in schemas:
                schemas[kind] = w.register_msgdef(kind, ts.generate_msgdef(kind, ros_version=2)[0])
            w.write_message(topic, schemas[kind], msg, log_time=ns)
        w.finish()


def _rosbags_msg(ts, kind: str, m: dict):
    """A rosbags message object of a message given as nested dicts."""
    from rosbags.typesys.stores.ros2_humble import builtin_interfaces__msg__Time as Time
    from rosbags.typesys.stores.ros2_humble import geometry_msgs__msg__Quaternion as Quat
    from rosbags.typesys.stores.ros2_humble import geometry_msgs__msg__Vector3 as Vec
    from rosbags.typesys.stores.ros2_humble import std_msgs__msg__Header as Header

    h = Header(stamp=Time(**m["header"]["stamp"]), frame_id=m["header"]["frame_id"])
    cls = ts.types[kind]
    if kind == MAG:
        return cls(header=h, magnetic_field=Vec(**m["magnetic_field"]),
                   magnetic_field_covariance=np.zeros(9))
    if kind == TEMP:
        return cls(header=h, temperature=m["temperature"], variance=0.0)
    if kind == NAV:
        from rosbags.typesys.stores.ros2_humble import sensor_msgs__msg__NavSatStatus as Status
        return cls(header=h, status=Status(status=m["status"], service=1), latitude=m["latitude"],
                   longitude=m["longitude"], altitude=m["altitude"], position_covariance=np.zeros(9),
                   position_covariance_type=0)
    z = Vec(x=0.0, y=0.0, z=0.0)
    return cls(header=h, orientation=Quat(**m["orientation"]), orientation_covariance=np.zeros(9),
               angular_velocity=z, angular_velocity_covariance=np.zeros(9), linear_acceleration=z,
               linear_acceleration_covariance=np.zeros(9))


def write_rosbag2(path, messages, storage: str = "sqlite3") -> None:
    """With rosbags' own writer: a rosbag2 directory (metadata.yaml and a .db3 or .mcap)."""
    from rosbags.rosbag2 import StoragePlugin, Writer

    ts = _typestore()
    plugin = StoragePlugin.SQLITE3 if storage == "sqlite3" else StoragePlugin.MCAP
    with Writer(path, version=9, storage_plugin=plugin) as w:
        conns = {}
        for topic, kind, ns, msg in messages:
            if topic not in conns:
                conns[topic] = w.add_connection(topic, kind, typestore=ts)
            w.write(conns[topic], ns, ts.serialize_cdr(_rosbags_msg(ts, kind, msg), kind))


@pytest.fixture(scope="module")
def same_data(tmp_path_factory):
    d = simulated()
    root = tmp_path_factory.mktemp("ros2")
    write_csv(root / "same.csv", d)
    # the same data as the bag carries them, in the CSV's units: tesla x 1e9, the Imu's quaternion as fluxcal's Euler
    # angles (that conversion is checked against the simulator's own angles above, to 1e-9 of a turn)
    exact = dict(d, field=(d["field"] * 1e-9) * 1e9,
                 euler=euler_from_quaternion(ned_from_enu_quaternion(enu_quaternions(d["euler"]))))
    write_csv(root / "exact.csv", exact)
    msgs = list(_msgs(d))
    write_mcap_ros2(root / "same.mcap", msgs)
    write_rosbag2(root / "same_db3", msgs, "sqlite3")
    write_rosbag2(root / "same_mcapbag", msgs, "mcap")
    return root, d


def assert_same_lab(a, b) -> None:
    assert a.probe_names == b.probe_names
    assert a.block.n_samples == b.block.n_samples
    np.testing.assert_array_equal(a.block.t_s, b.block.t_s)
    np.testing.assert_allclose(a.block.field_nT, b.block.field_nT, rtol=1e-12, atol=0)
    np.testing.assert_array_equal(a.block.temp_C, b.block.temp_C)
    assert set(a.block.extras) == set(b.block.extras)
    for k in a.block.extras:                # angles through a quaternion and back: 1e-9 of a full turn
        np.testing.assert_allclose(a.block.extras[k], b.block.extras[k], rtol=0, atol=360 * 1e-9, err_msg=k)


@pytest.mark.parametrize("bag", ["same.mcap", "same_db3", "same_db3/same_db3.db3", "same_mcapbag"])
def test_bag_gives_the_csvs_lab_data(same_data, bag):
    root, d = same_data
    csv = load_data(root / "same.csv")
    lab = load_data(root / bag)
    assert_same_lab(lab, csv)
    assert lab.warnings == []
    assert float(lab.metadata["t0_unix_s"]) == pytest.approx(T0_NS / 1e9, abs=1e-6)
    src = json.loads(lab.metadata["sources"])
    assert src == {"s1": "/mag1/field", "s2": "/mag2/field", "s1_temp": "/mag1/temperature",
                   "s2_temp": "/mag2/temperature", "heel_deg": "/imu/data", "pitch_deg": "/imu/data",
                   "azimuth_deg": "/imu/data"}


def _numbers(obj, path=""):
    """Every number in a JSON document, by its path."""
    if isinstance(obj, dict):
        for k, v in obj.items():
            yield from _numbers(v, f"{path}.{k}")
    elif isinstance(obj, list):
        for i, v in enumerate(obj):
            yield from _numbers(v, f"{path}[{i}]")
    elif isinstance(obj, (int, float)) and not isinstance(obj, bool):
        yield path, float(obj)


def _same_numbers(a: dict, b: dict) -> int:
    na, nb = dict(_numbers(a)), dict(_numbers(b))
    assert set(na) == set(nb)
    for k in na:
        x, y = na[k], nb[k]
        if math.isnan(x):
            assert math.isnan(y), k
        else:
            assert y == pytest.approx(x, rel=1e-9, abs=1e-9 * max(1.0, abs(x))), k
    return len(na)


@pytest.mark.parametrize("command", [["fit", "--align", "regression"], ["diagnose", "--max-samples", "0"]])
def test_fit_and_diagnose_of_a_bag_are_the_csvs(same_data, capsys, command):
    root, _ = same_data
    np.testing.assert_array_equal(load_data(root / "exact.csv").block.field_nT, load_data(root / "same.mcap")
                                  .block.field_nT)
    out = {}
    for name in ("exact.csv", "same.mcap"):
        capsys.readouterr()
        assert cli.main([command[0], str(root / name), "--json", *command[1:]]) == 0
        out[name] = json.loads(capsys.readouterr().out)
    assert _same_numbers(out["exact.csv"], out["same.mcap"]) > 50


def test_topics_chosen_by_options(same_data):
    root, _ = same_data
    lab = load_data(root / "same.mcap", mapping=Ros2Mapping(probes={"s1": "/mag2/field"}, imu=None,
                                                             temperatures={}))
    csv = load_data(root / "same.csv")
    assert lab.probe_names == ["s1"]
    np.testing.assert_allclose(lab.block.field_nT[:, 0], csv.block.field_nT[:, 1], rtol=1e-12)
    assert np.isnan(lab.block.temp_C).all() and lab.block.extras == {}
    assert any("s1: no temperature stream" in n and "never another probe's" in n for n in lab.notes)
    with pytest.raises(DataError, match=r"probes.s1: '/nope' is not a topic of the bag \(its "
                                        r"sensor_msgs/msg/MagneticField topics: /mag1/field, /mag2/field\)"):
        load_data(root / "same.mcap", mapping=Ros2Mapping(probes={"s1": "/nope"}))
    with pytest.raises(DataError, match="'/imu/data' carries sensor_msgs/msg/Imu, not"):
        load_data(root / "same.mcap", mapping=Ros2Mapping(probes={"s1": "/imu/data"}))


def test_inspect_lists_topics_and_mapping(same_data, capsys):
    root, _ = same_data
    i = inspect_file(root / "same.mcap")                      # the streams, then the one reading fit and diagnose use
    by = {s.name: s for s in i.streams}
    assert by["/mag1/field"].maps_to.startswith("probe s1") and by["/mag2/field"].maps_to.startswith("probe s2")
    assert by["/mag2/temperature"].maps_to == "s2_temp"
    assert by["/imu/data"].maps_to.startswith("heel_deg, pitch_deg, azimuth_deg")
    assert all(s.count == 3000 and s.rate_hz == pytest.approx(RATE, rel=1e-9) for s in i.streams)
    assert i.probes == ["s1", "s2"] and i.duration_s == pytest.approx(2999 / RATE, rel=1e-9)
    assert cli.main(["inspect", str(root / "same_db3")]) == 0
    text = capsys.readouterr().out
    assert "ROS 2 bag (rosbag2 directory)" in text and "/mag1/temperature" in text and "s1_temp" in text
    assert cli.main(["inspect", str(root / "same.mcap"), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["probes"] == ["s1", "s2"]


def test_streams_at_other_instants_are_matched_never_borrowed(tmp_path):
    """A second magnetometer at 2/3 the rate and 3 ms late, a GPS at 5 Hz starting late, a temperature with a hole:
    probes matched one to one within half an interval, the GPS interpolated and the rows before its first fix left
    out and said, the temperature NaN across its hole, the stamps-less messages on their log time."""
    n = 600
    ns1 = T0_NS + np.arange(n) * 20_000_000                       # 50 Hz
    ns2 = T0_NS + 3_000_000 + np.arange(0, n * 3 // 2, 1) * 30_000_000 // 1    # 33.3 Hz, 3 ms late
    ns2 = ns2[ns2 <= ns1[-1] + 5_000_000]
    nsg = T0_NS + 2_000_000_000 + np.arange(0, 50) * 200_000_000  # 5 Hz from 2 s to 11.8 s
    nst = np.concatenate([ns1[:200], ns1[300:]])                   # a 2 s hole
    msgs = []

    def stamp(ns):
        return {"sec": int(ns) // 1_000_000_000, "nanosec": int(ns) % 1_000_000_000}

    for i, ns in enumerate(ns1):
        msgs.append(("/a/mag", MAG, int(ns), {"header": {"stamp": stamp(ns), "frame_id": "a"},
                     "magnetic_field": {"x": 2e-5 + i * 1e-12, "y": 0.0, "z": 4e-5},
                     "magnetic_field_covariance": [0.0] * 9}))
    for i, ns in enumerate(ns2):
        msgs.append(("/b/mag", MAG, int(ns), {"header": {"stamp": stamp(0), "frame_id": "b"},    # no stamp
                     "magnetic_field": {"x": 1e-5, "y": i * 1e-12, "z": 4e-5},
                     "magnetic_field_covariance": [0.0] * 9}))
    for i, ns in enumerate(nsg):
        msgs.append(("/gps/fix", NAV, int(ns), {"header": {"stamp": stamp(ns), "frame_id": "gps"},
                     "status": {"status": 0, "service": 1}, "latitude": 48.0 + i * 1e-4, "longitude": 11.0,
                     "altitude": 500.0 + i, "position_covariance": [0.0] * 9, "position_covariance_type": 0}))
    for ns in nst:
        msgs.append(("/a/temperature", TEMP, int(ns), {"header": {"stamp": stamp(ns), "frame_id": "a"},
                     "temperature": 20.0, "variance": 0.0}))
    msgs.sort(key=lambda m: m[2])
    write_mcap_ros2(tmp_path / "mixed.mcap", msgs)
    lab = load_data(tmp_path / "mixed.mcap")
    b = lab.block
    # the time base: /b/mag's instants (fewer samples); /a/mag's nearest within 15 ms, one to one
    t_b = (ns2 - T0_NS) / 1e9
    t_a = (ns1 - T0_NS) / 1e9
    kept = (t_b >= 2.0) & (t_b <= 11.8)                            # inside the GPS's span
    assert b.n_samples == int(kept.sum())
    np.testing.assert_allclose(b.t_s, t_b[kept] - t_b[kept][0], atol=1e-9)
    ia = np.rint((b.field_nT[:, 0, 0] - 20000.0) * 1e3).astype(int)   # the /a sample's index, in its x
    assert np.all(np.abs(t_a[ia] - t_b[kept]) <= 0.010 + 1e-9)
    assert np.unique(ia).size == ia.size                           # none used twice
    np.testing.assert_allclose(b.field_nT[:, 1, 1], np.flatnonzero(kept) * 1e-3, atol=1e-6)
    # GPS linear between its samples
    lat = 48.0 + (t_b[kept] - 2.0) / 0.2 * 1e-4
    np.testing.assert_allclose(b.extras["lat_deg"], lat, atol=1e-9)
    np.testing.assert_allclose(b.extras["alt_m"], 500.0 + (t_b[kept] - 2.0) / 0.2, atol=1e-6)
    # the temperature: NaN inside its hole (4-6 s) only
    hole = (b.t_s + t_b[kept][0] > t_a[199]) & (b.t_s + t_b[kept][0] < t_a[300])
    assert np.isnan(b.temp_C[hole, 0]).all() and (b.temp_C[~hole, 0] == 20.0).all()
    assert np.isnan(b.temp_C[:, 1]).all()
    said = " ".join(lab.warnings)
    assert "/b/mag: " in said and "without a header stamp: their log time taken" in said
    assert f"no value at {int((t_b < 2.0).sum()) + int((t_b > 11.8).sum())} rows" in said
    assert "never extrapolated" in said
    assert "s1_temp (/a/temperature (Temperature)): no temperature at" in said
    assert any("time base: the instants of s2" in n for n in lab.notes)


def test_a_bag_without_magnetometer_is_refused(tmp_path):
    d = simulated(n=20)
    msgs = [m for m in _msgs(d) if m[1] != MAG]
    write_mcap_ros2(tmp_path / "nomag.mcap", msgs)
    with pytest.raises(DataError, match="no sensor_msgs/msg/MagneticField topic in the bag"):
        load_data(tmp_path / "nomag.mcap")
    (tmp_path / "lone.db3").write_bytes(b"SQLite format 3\x00")
    with pytest.raises(DataError, match="without the metadata.yaml of its bag beside it"):
        load_data(tmp_path / "lone.db3")


def test_a_damaged_bag_is_said_in_one_line_never_a_traceback(tmp_path, capsys):
    """A bag cut anywhere in its first 64 bytes or its last 400 (the summary, the footer), or with one byte flipped
    anywhere (a chunk's zstd data, a message definition, a log time, the summary): `inspect` and `fit` read it or say
    what is wrong in one last line, with exit status 2, never a traceback from mcap, zstd or the CDR decoder; every
    cut is refused in a line naming the file. (Before: struct.error, ZstdError, KeyError, OverflowError,
    AttributeError and the message-definition parser's errors escaped in 137 of the 622 runs over flipped bags.)"""
    d = simulated(n=20)
    write_mcap_ros2(tmp_path / "bag.mcap", list(_msgs(d)))
    data = (tmp_path / "bag.mcap").read_bytes()
    cases = {f"cut{n}": data[:n] for n in [*range(64), *range(len(data) - 400, len(data))]}
    for i in range(0, len(data), 23):
        flipped = bytearray(data)
        flipped[i] ^= 0x5A
        cases[f"flip{i}"] = bytes(flipped)
    refused = {"inspect": 0, "fit": 0}
    for name, blob in cases.items():
        path = tmp_path / f"{name}.mcap"
        path.write_bytes(blob)
        for command in ("inspect", "fit"):
            rc = cli.main([command, str(path)], install_signals=False)
            err = capsys.readouterr().err
            assert rc in (0, 2) and "Traceback" not in err, (name, command, err)
            if rc == 2:
                refused[command] += 1
                last = err.strip().splitlines()[-1]        # notes of what was read may come before
                assert last.startswith(f"fluxcal {command}: "), (name, command, err)
                assert str(path) in last or not name.startswith("cut"), (name, command, err)
            else:
                assert name.startswith("flip"), (name, command, err)
        path.unlink()
    cuts = sum(name.startswith("cut") for name in cases)
    assert refused["inspect"] > cuts and refused["fit"] > cuts      # every cut, and some flips


def test_fluxcal_recordings_are_not_taken_for_bags():
    from fluxcal.service.io.recordings.formats import detect_format

    assert detect_format("recordings/grad1-sim-30s.mcap") == "fluxcal"


def test_topics_chosen_on_the_command_line(same_data, capsys):
    """--topics NAME=TOPIC,..: the same choice from the command line, and a refusal that names the option."""
    from fluxcal.service.wiring.cli import main

    root, _ = same_data
    capsys.readouterr()
    assert main(["fit", str(root / "same.mcap"), "--topics", "s1=/mag2/field,imu=none", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    alone = load_data(root / "same.mcap", mapping=Ros2Mapping(probes={"s1": "/mag2/field"}, imu=None))
    assert [s["name"] for s in out["sensors"]] == ["s1"] and alone.probe_names == ["s1"]
    # inspect takes the same option (it was refused there while fit took it) and lists what fit took
    assert main(["inspect", str(root / "same.mcap"), "--topics", "s1=/mag2/field,imu=none", "--json"]) == 0
    seen = json.loads(capsys.readouterr().out)
    assert seen["probes"] == ["s1"] and seen["samples"] == alone.block.n_samples
    assert seen["verdict"] == out["determinacy"]
    by = {s["name"]: s for s in seen["streams"]}
    assert by["/mag2/field"]["maps_to"].startswith("probe s1") and not by["/mag1/field"]["maps_to"]
    assert main(["fit", str(root / "same.csv"), "--topics", "s1=/mag2/field"]) == 2
    assert "--topics: " in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["fit", str(root / "same.mcap"), "--topics", "s1"])
