"""Foxglove: every channel of a fresh recording of `fluxcal run` decodes with mcap's reader (JSON channels
validated against their jsonschema, binary ones with fluxcal's decoders) and holds the right values; the live
bridge `fluxcal foxglove` serves the same channels to a client speaking Foxglove's WebSocket protocol."""

from __future__ import annotations

import asyncio
import json
import math
import re
import signal
import struct
import subprocess
import sys
import threading
import time
from pathlib import Path

import jsonschema
import numpy as np
import pytest
import websockets
from mcap.reader import make_reader
from test_service_e2e import PROBES, TOTAL_NT, free_port, stop, write_config

from fluxcal.drivers.errors import ConfigError
from fluxcal.service.io.foxglove_schemas import TENSOR_FIELDS, Products, path_safe
from fluxcal.service.io.recordings.reader import FluxcalDecoderFactory
from fluxcal.service.numerics.outputs import products
from fluxcal.service.wiring.commands.foxglove import parse_listen

pytestmark = pytest.mark.slow
UNIT = "e2e"
SUBPROTOCOLS = ["foxglove.sdk.v1", "foxglove.websocket.v1"]   # foxglove-sdk 0.30 speaks the first


def _config(tmp_path: Path, port: int, *, realtime: bool, record: bool) -> str:
    text = Path(write_config(tmp_path, port)).read_text()
    text = text.replace("realtime = false", f"realtime = {str(realtime).lower()}")
    text = text.replace("run_s = 40.0", "run_s = 30.0" if not realtime else "run_s = 600.0")
    mcap = f'[mcap]\nenabled = true\ndir = "{tmp_path / "rec"}"\n' if record else "[mcap]\nenabled = false\n"
    text = text[:text.index("[mcap]")] + mcap
    path = tmp_path / ("record.toml" if record else "live.toml")
    path.write_text(text)
    return str(path)


@pytest.fixture(scope="module")
def recorded(tmp_path_factory):
    """A fresh 30 s recording of the simulated 4-probe unit (faster than real time); its persisted calibration
    lets the live test start calibrated."""
    tmp = tmp_path_factory.mktemp("fox")
    cfg = _config(tmp, free_port(), realtime=False, record=True)
    out = subprocess.run([sys.executable, "-m", "fluxcal.service.wiring.cli", "run", "--config", cfg],
                         capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stdout + out.stderr
    (path,) = sorted((tmp / "rec").glob("*.mcap"))
    return tmp, path


def _read_all(path: Path) -> dict[str, list]:
    """topic -> [(schema, channel, message, decoded)] through mcap's indexed reader with fluxcal's decoders."""
    by_topic: dict[str, list] = {}
    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[FluxcalDecoderFactory()])
        summary = reader.get_summary()
        for ch in summary.channels.values():
            by_topic[ch.topic] = []
        for schema, channel, message, decoded in reader.iter_decoded_messages():
            by_topic[channel.topic].append((schema, channel, message, decoded))
    return by_topic


def test_every_channel_of_a_fresh_recording_decodes_with_the_right_values(recorded):
    _, path = recorded
    msgs = _read_all(path)
    t = f"/fluxcal/{UNIT}"
    assert set(msgs) == {f"{t}/{s}" for s in ("raw", "corrected", "vectors", "diff", "tensor", "error", "params",
                                              "calibration", "events", "health")}
    for topic, items in msgs.items():
        assert items, f"{topic}: no message"
        for schema, channel, message, decoded in items:
            if channel.message_encoding == "json":
                assert schema.encoding == "jsonschema"
                jsonschema.validate(json.loads(message.data), json.loads(schema.data))
                assert decoded == json.loads(message.data)
            else:
                assert channel.message_encoding in ("fluxcal.raw.v1", "fluxcal.corrected.v1")
                assert decoded.n_samples > 0
    corrected = [d for *_, d in msgs[f"{t}/corrected"]]
    t_s = np.concatenate([c.t_s for c in corrected])
    cal_id = np.concatenate([np.full(c.n_samples, c.cal_id) for c in corrected])
    field = np.concatenate([c.corrected_nT for c in corrected])
    names = [p[0] for p in PROBES]

    def window(m: dict) -> np.ndarray:
        """The samples of the message's 0.1 s interval and calibration, chosen independently of the decimator."""
        rows = (np.floor(t_s / 0.1 + 1e-9) == math.floor(m["t_s"] / 0.1 + 1e-9)) & (cal_id == m["cal_id"])
        assert rows.sum() == m["n"]
        return field[rows]

    diffs = [d for *_, d in msgs[f"{t}/diff"]]
    assert len(diffs) > 100 and all(d["reference"] == "s1" for d in diffs)
    for d in diffs[::7]:
        w = window(d)
        delta = w[:, 1:] - w[:, :1]
        for k, name in enumerate(names[1:]):
            got = [d[name][a] for a in "xyz"]
            assert np.allclose(got, delta[:, k].mean(axis=0), rtol=0, atol=1e-9), (name, got)
            assert d[name]["magnitude"] == pytest.approx(np.linalg.norm(delta[:, k], axis=1).mean(), abs=1e-9)
    for v in [d for *_, d in msgs[f"{t}/vectors"]][::11]:
        w = window(v)
        assert v["s3"]["z"] == pytest.approx(w[:, 2, 2].mean(), abs=1e-9)
        assert abs(v["center"]["total"] - TOTAL_NT) < 5.0
    tensors = [d for *_, d in msgs[f"{t}/tensor"]]
    assert len(tensors) == len(diffs)
    for g in tensors[::7]:
        w = window(g)
        pos = np.array([p[1] for p in PROBES], float)
        want = products(np.zeros(len(w)), np.zeros(len(w), np.int64), w, pos, 0).tensor_nT_m.mean(axis=0)
        assert np.allclose([g[f] for f in TENSOR_FIELDS], want.ravel(), atol=1e-9)
        assert abs(g["trace"]) < 0.05                    # div B = 0: a source-free (uniform) simulated field
        assert max(abs(g[f]) for f in TENSOR_FIELDS) < 10.0          # noise only: no gradient in the simulation
    errors = [d for *_, d in msgs[f"{t}/error"]]
    assert errors and all(set(e["rms_nT"]) == {f"{n}.scalar" for n in names} for e in errors)
    assert all(e["rms"] == {path_safe(k): v for k, v in e["rms_nT"].items()} for e in errors)
    assert np.median([e["rms"]["s1_scalar"] for e in errors]) < 2.0          # noise 0.5 nT per axis
    params = [d for *_, d in msgs[f"{t}/params"]]
    calibrations = [d for *_, d in msgs[f"{t}/calibration"]]
    assert len(params) == len(calibrations) and params[-1]["usable"] and params[-1]["kind"] == "calibration"
    last = params[-1]
    assert 0 < last["coverage"] <= 1 and last["condition"] > 0 and len(last["gate_rms_nT"]) == 4
    for probe, (name, _, off, *_r) in zip(last["probes"], PROBES):
        assert probe["name"] == name and np.allclose(probe["offset_nT"], off, atol=3.0)
        assert all(0 < se < 1.0 for se in probe["offset_se_nT"]) and len(probe["matrix"]) == 9
        assert len(probe["matrix_se"]) == 9


def test_products_combine_block_errors_as_rms_over_the_interval():
    p = Products(["a", "b"])
    assert p.error({"a.scalar": 3.0}, t_s=0.00, seq=0, n=10) == []
    assert p.error({"a.scalar": 4.0, "b-a.x": 1.0}, t_s=0.05, seq=10, n=30) == []
    ((stream, msg),) = p.error({"a.scalar": 1.0}, t_s=0.10, seq=40, n=10)        # a new interval ends the first
    assert stream == "error" and msg["n"] == 40 and msg["seq"] == 0 and msg["t_s"] == 0.0
    assert msg["rms_nT"]["a.scalar"] == pytest.approx(math.sqrt((10 * 9 + 30 * 16) / 40))
    assert msg["rms"] == {"a_scalar": msg["rms_nT"]["a.scalar"], "b_minus_a_x": 1.0}
    assert [s for s, _ in p.flush()] == ["error"]


def test_listen_is_parsed_strictly():
    assert parse_listen("127.0.0.1:0") == ("127.0.0.1", 0)
    for bad in ("8765", "127.0.0.1", "127.0.0.1:99999", "ws://x:1"):
        with pytest.raises(ConfigError, match="--listen"):
            parse_listen(bad)


class _Lines:
    """A subprocess's stderr, read on a thread, so the test can wait for a line."""

    def __init__(self, stream) -> None:
        self.lines: list[str] = []
        threading.Thread(target=lambda: [self.lines.append(ln) for ln in stream], daemon=True).start()

    def wait(self, pattern: str, timeout: float) -> re.Match:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            for ln in list(self.lines):
                m = re.search(pattern, ln)
                if m:
                    return m
            time.sleep(0.05)
        raise AssertionError(f"no line matching {pattern!r} in {timeout} s: {''.join(self.lines)}")


async def _foxglove_client(url: str, topics: list[str], want: int, timeout: float) -> tuple[dict, dict, dict]:
    """Speak the Foxglove WebSocket protocol: serverInfo, advertise, subscribe, binary message data (opcode 1:
    u32 subscription id, u64 log time, payload). Returns (serverInfo, channels by topic, messages by topic)."""
    async with websockets.connect(url, subprotocols=SUBPROTOCOLS, open_timeout=10) as ws:
        assert ws.subprotocol in SUBPROTOCOLS
        info = json.loads(await asyncio.wait_for(ws.recv(), timeout))
        assert info["op"] == "serverInfo"
        channels: dict[str, dict] = {}
        got: dict[str, list] = {t: [] for t in topics}
        by_sub: dict[int, str] = {}
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline and (len(by_sub) < len(topics) or min(map(len, got.values())) < want):
            try:
                frame = await asyncio.wait_for(ws.recv(), max(0.1, deadline - time.monotonic()))
            except asyncio.TimeoutError:
                break
            if isinstance(frame, str):
                m = json.loads(frame)
                if m["op"] == "advertise":
                    channels.update({c["topic"]: c for c in m["channels"]})
                    new = [t for t in topics if t in channels and t not in by_sub.values()]
                    subs = [{"id": len(by_sub) + i + 1, "channelId": channels[t]["id"]} for i, t in enumerate(new)]
                    by_sub.update({s["id"]: t for s, t in zip(subs, new)})
                    if subs:
                        await ws.send(json.dumps({"op": "subscribe", "subscriptions": subs}))
                continue
            op, sub_id, log_ns = struct.unpack_from("<BIQ", frame, 0)
            if op == 1 and sub_id in by_sub:
                got[by_sub[sub_id]].append((log_ns, json.loads(frame[13:])))
        return info, channels, got


def test_live_bridge_serves_the_products_to_a_foxglove_protocol_client(recorded):
    tmp, _ = recorded
    port = free_port()
    cfg = _config(tmp, port, realtime=True, record=False)
    bridge = subprocess.Popen([sys.executable, "-m", "fluxcal.service.wiring.cli", "foxglove", "--connect",
                               f"tcp/127.0.0.1:{port}", "--unit", UNIT, "--listen", "127.0.0.1:0", "--seconds", "90"],
                              stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    service = None
    try:
        err = _Lines(bridge.stderr)
        url = err.wait(r"(ws://127\.0\.0\.1:\d+)", 20).group(1)
        err.wait(r"cannot reach tcp/127\.0\.0\.1:%d" % port, 20)          # started before the unit: it says so
        service = subprocess.Popen([sys.executable, "-m", "fluxcal.service.wiring.cli", "run", "--config", cfg],
                                   stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        err.wait(r"serving fluxcal/e2e", 30)
        topics = [f"/fluxcal/{UNIT}/{s}" for s in ("diff", "tensor", "error", "vectors")]
        info, channels, got = asyncio.run(_foxglove_client(url, topics, want=5, timeout=40))
        bridge.send_signal(signal.SIGTERM)
        assert bridge.wait(timeout=20) == 0
        err.wait(r"stopped: \d+ messages sent", 5)
    finally:
        if bridge.poll() is None:
            bridge.kill()
            bridge.wait()
        log = stop(service) if service is not None else ""
    assert info["name"] == "fluxcal"
    for t in topics:
        assert channels[t]["encoding"] == "json" and channels[t]["schemaEncoding"] == "jsonschema", t
        assert len(got[t]) >= 5, (t, {k: len(v) for k, v in got.items()}, log)
        schema = json.loads(channels[t]["schema"])
        for _, m in got[t]:
            jsonschema.validate(m, schema)
        times = [ns for ns, _ in got[t]]
        assert times == sorted(times) and abs(times[-1] / 1e9 - time.time()) < 120     # unit time on the wall clock
    names = [p[0] for p in PROBES]
    for _, d in got[f"/fluxcal/{UNIT}/diff"]:
        assert d["reference"] == "s1" and d["n"] > 0
        for n in names[1:]:
            v = [d[n][a] for a in ("x", "y", "z", "magnitude")]
            assert np.all(np.isfinite(v)) and d[n]["magnitude"] < 20.0      # noise of a calibrated, uniform field
    for _, g in got[f"/fluxcal/{UNIT}/tensor"]:
        assert np.all(np.isfinite([g[f] for f in TENSOR_FIELDS])) and abs(g["trace"]) < 0.05
    for _, v in got[f"/fluxcal/{UNIT}/vectors"]:
        assert all(abs(v[n]["total"] - TOTAL_NT) < 20.0 for n in names), v
    for _, e in got[f"/fluxcal/{UNIT}/error"]:
        assert set(e["rms_nT"]) == {f"{n}.scalar" for n in names}
        assert all(0 <= x < 5.0 for x in e["rms"].values())
