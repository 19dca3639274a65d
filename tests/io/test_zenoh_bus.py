"""The Zenoh bus on loopback: blocks arrive decoded and equal, BLOCK streams lose nothing in a burst,
state and commands round-trip through the service's own thread, and a router in the middle relays all
of it (the multi-host layout). Free ports, no multicast, every session closed in `finally`."""

from __future__ import annotations

import json
import socket
import threading
import time
from contextlib import ExitStack
from typing import Any

import numpy as np
import pytest

from fluxcal.drivers.block import SampleBlock
from fluxcal.drivers.config import load_section
from fluxcal.drivers.errors import ConfigError, DataError
from fluxcal.service.io.bus import (
    BusClient,
    BusError,
    Keys,
    ServiceBus,
    ZenohConfig,
    decode_series,
    discover_units,
    encode_series,
    make_zenoh_config,
    open_session,
)
from fluxcal.service.numerics.outputs import CorrectedBlock

#: what this file tests besides what it imports (tests/index.py: every module findable from its test)
COVERS = ("fluxcal.service.io.bus.desk", "fluxcal.service.io.bus.sender")


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def peer_cfg() -> tuple[ZenohConfig, str]:
    ep = f"tcp/127.0.0.1:{free_port()}"
    cfg = ZenohConfig(mode="peer", listen=[ep])
    cfg.validate("zenoh")
    return cfg, ep


def wait_until(cond, timeout: float = 5.0, what: str = "condition") -> None:
    deadline = time.monotonic() + timeout
    while not cond():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out waiting for {what}")
        time.sleep(0.005)


def make_block(n: int, p: int, seq0: int = 0, seed: int = 0) -> SampleBlock:
    rng = np.random.default_rng(seed)
    field = rng.normal(0.0, 30000.0, (n, p, 3))
    field[0, 0, 1] = np.nan                               # a saturated axis travels as NaN
    temp = rng.normal(22.0, 1.0, (n, p))
    temp[-1, -1] = np.nan
    return SampleBlock(t_s=(seq0 + np.arange(n)) / 200.0, seq=seq0 + np.arange(n, dtype=np.int64),
                       field_nT=field, temp_C=temp, flags=rng.integers(0, 8, n).astype(np.uint8),
                       extras={"ref_total": rng.normal(52500.0, 1.0, n)})


def make_corrected(block: SampleBlock, cal_id: int = 4, tensor: bool = True) -> CorrectedBlock:
    c = block.field_nT * 1.01 + 3.0
    n = block.n_samples
    tens = np.arange(n * 9, dtype=float).reshape(n, 3, 3) / 7.0 if tensor else None
    return CorrectedBlock(t_s=block.t_s, seq=block.seq, corrected_nT=c, diff_nT=c[:, 1:] - c[:, :1],
                          tensor_nT_m=tens, center_nT=c.mean(axis=1), cal_id=cal_id)


def assert_blocks_equal(a: Any, b: Any) -> None:
    for name in ("t_s", "seq", "field_nT", "temp_C", "flags", "corrected_nT", "diff_nT", "tensor_nT_m", "center_nT"):
        if hasattr(a, name):
            x, y = getattr(a, name), getattr(b, name)
            if x is None:
                assert y is None, name
            else:
                np.testing.assert_array_equal(x, y, err_msg=name)      # bit for bit, NaN where NaN
                assert x.dtype == y.dtype, name


def collect(client: BusClient, n: int, timeout: float = 10.0) -> list:
    out = []
    deadline = time.monotonic() + timeout
    while len(out) < n and time.monotonic() < deadline:
        m = client.recv(timeout=0.2)
        if m is not None:
            out.append(m)
    return out


class FakeDaemon:
    """The service's thread: drains commands, answers them, serves state queries on the way."""

    def __init__(self, bus: ServiceBus, answer: dict | None = None, decide=None) -> None:
        # decide(cmd) -> the answer for that command, when it is not always the same
        self.bus, self.answer, self.decide = bus, answer or {"ok": True}, decide
        self.seen: list[tuple[int, str, str, str]] = []
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self.run, daemon=True)
        self.thread.start()

    def run(self) -> None:
        while not self.stop.is_set():
            cmd = self.bus.next_command(timeout=0.02)
            if cmd is not None:
                self.seen.append((cmd.id, cmd.name, cmd.payload, threading.current_thread().name))
                cmd.reply(self.decide(cmd) if self.decide else {**self.answer, "applied": cmd.name})

    def close(self) -> None:
        self.stop.set()
        self.thread.join(2.0)


@pytest.fixture
def stack():
    with ExitStack() as s:
        yield s


# --- configuration ------------------------------------------------------------------------------

def test_config_defaults_bind_loopback_only_and_no_multicast():
    cfg = load_section(ZenohConfig, {}, "zenoh")
    assert cfg.mode == "peer" and cfg.listen == ["tcp/127.0.0.1:7447"] and cfg.connect == []
    assert cfg.multicast_scouting is False and cfg.per_probe is True
    z = make_zenoh_config(cfg)
    assert json.loads(z.get_json("mode")) == "peer"
    assert json.loads(z.get_json("listen/endpoints")) == ["tcp/127.0.0.1:7447"]
    assert json.loads(z.get_json("scouting/multicast/enabled")) is False
    client = load_section(ZenohConfig, {"mode": "client", "connect": ["tcp/10.0.0.5:7447"]}, "zenoh")
    assert client.listen == []                    # the peer's default listen is not a client's
    assert json.loads(make_zenoh_config(client).get_json("connect/endpoints")) == ["tcp/10.0.0.5:7447"]


@pytest.mark.parametrize("table, message", [
    ({"listne": []}, "zenoh.listne: unknown key (allowed: mode, listen, connect"),
    ({"mode": "server"}, "zenoh.mode: 'server' is not allowed (allowed: 'peer', 'client', 'router')"),
    ({"listen": ["127.0.0.1:7447"]}, "zenoh.listen[0]: '127.0.0.1:7447' is not a Zenoh endpoint"),
    ({"connect": ["tcp/host"]}, "zenoh.connect[0]: 'tcp/host' needs host:port"),
    ({"connect": ["tcp/host:70000"]}, "needs host:port with a port 0..65535"),
    ({"mode": "client"}, "zenoh.connect: a client needs at least one endpoint"),
    ({"mode": "client", "listen": ["tcp/127.0.0.1:1"], "connect": ["tcp/127.0.0.1:2"]},
     "zenoh.listen: ['tcp/127.0.0.1:1'] is not allowed with mode 'client'"),
    ({"listen": []}, "zenoh.listen: nothing to listen on and nothing to connect to"),
    ({"tls": {"root_ca": "no-such-ca.pem"}}, "zenoh.tls.cert: required with TLS"),
    ({"tls": {"certificate": "x"}}, "zenoh.tls.certificate: unknown key (allowed: root_ca, cert, key, mutual"),
    ({"access": {"readers": ["dash"]}}, "zenoh.access: access control names peers by their client certificate"),
    ({"access": {"commanders": [""]}}, "zenoh.access.commanders[0]: '' is not allowed"),
    ({"multicast_scouting": "yes"}, "zenoh.multicast_scouting: expected true or false, got 'yes'"),
])
def test_config_errors_name_key_value_and_what_is_allowed(table, message):
    with pytest.raises(ConfigError) as e:
        load_section(ZenohConfig, table, "zenoh")
    assert message in str(e.value)


def test_service_config_reads_the_zenoh_section():
    from fluxcal.service.wiring.config import config_from_dict

    cfg = config_from_dict({"zenoh": {"mode": "peer", "listen": ["tcp/127.0.0.1:7999"]}}, "x.toml")
    assert isinstance(cfg.zenoh, ZenohConfig) and cfg.zenoh.listen == ["tcp/127.0.0.1:7999"]
    with pytest.raises(ConfigError, match=r"x.toml: zenoh.mode: 'hub' is not allowed"):
        config_from_dict({"zenoh": {"mode": "hub"}}, "x.toml")


def test_unit_and_probe_names_must_be_key_segments():
    assert Keys("grad_1-a").stream("raw") == "fluxcal/grad_1-a/raw"
    for bad in ("a/b", "*", "", "x y"):
        with pytest.raises(ConfigError, match="unit name"):
            Keys(bad)


def test_open_failures_are_bus_errors_that_say_what_to_do(stack):
    cfg, ep = peer_cfg()
    stack.enter_context(ServiceBus(cfg, "u1"))
    with pytest.raises(BusError, match=r"^zenoh\.listen: \['tcp/127\.0\.0\.1:\d+'\]: the port is already in use "
                                       r"\(another fluxcal, or another program, listens there\): choose another port"):
        ServiceBus(ZenohConfig(listen=[ep]), "u2")
    with pytest.raises(BusError, match="is the service .* running and listening there"):
        BusClient(ZenohConfig.client(f"tcp/127.0.0.1:{free_port()}"), "u1")


# --- encodings ----------------------------------------------------------------------------------

def test_series_encoding_round_trip_and_malformed_payloads():
    vals = np.random.default_rng(1).normal(size=(5, 1, 3))
    s = decode_series(encode_series(np.arange(5) * 0.1, np.arange(5) + 9, vals, 12))
    np.testing.assert_array_equal(s.values, vals)
    assert s.seq.tolist() == list(range(9, 14)) and s.cal_id == 12
    payload = encode_series(np.arange(5) * 0.1, np.arange(5), vals, 1)
    for bad in (payload[:-1], payload + b"\0", b"FXS2" + payload[4:], b""):
        with pytest.raises(DataError, match="series"):
            decode_series(bad)
    with pytest.raises(ValueError, match=r"expected t_s and seq of shape \(5,\)"):
        encode_series(np.arange(4), np.arange(5), vals, 1)


# --- publish / subscribe ------------------------------------------------------------------------

def test_blocks_arrive_decoded_and_equal_in_a_client_session(stack):
    cfg, ep = peer_cfg()
    bus = stack.enter_context(ServiceBus(cfg, "grad1", probe_names=["s1", "s2", "s3", "s4"]))
    streams = ["raw", "corrected", "diff", "tensor", "corrected/s3"]
    client = stack.enter_context(BusClient(ZenohConfig.client(ep), "grad1", streams=streams))
    wait_until(lambda: all(bus.has_subscribers(s) for s in streams), what="subscribers")
    block = make_block(20, 4, seq0=1000)
    cor = make_corrected(block)
    bus.publish_raw(block)
    bus.publish_corrected(cor)
    got = {m.stream: m for m in collect(client, 5)}
    assert sorted(got) == sorted(streams)
    assert got["raw"].key == "fluxcal/grad1/raw"
    assert_blocks_equal(block, got["raw"].value)
    np.testing.assert_array_equal(got["raw"].value.extras["ref_total"], block.extras["ref_total"])
    assert_blocks_equal(cor, got["corrected"].value)
    assert got["corrected"].value.cal_id == 4
    np.testing.assert_array_equal(got["diff"].value.values, cor.diff_nT)
    np.testing.assert_array_equal(got["diff"].value.seq, block.seq)
    np.testing.assert_array_equal(got["tensor"].value.values, cor.tensor_nT_m)
    one = got["corrected/s3"].value
    assert got["corrected/s3"].key == "fluxcal/grad1/corrected/s3"
    np.testing.assert_array_equal(one.corrected_nT[:, 0], cor.corrected_nT[:, 2])
    assert one.n_probes == 1 and one.diff_nT is None
    assert client.stats["decode_errors"] == 0


def test_json_streams_carry_null_for_nan_and_the_unit(stack):
    cfg, ep = peer_cfg()
    bus = stack.enter_context(ServiceBus(cfg, "u1"))
    client = stack.enter_context(BusClient(ZenohConfig.client(ep), "u1", streams=["calibration", "health", "error"]))
    wait_until(lambda: bus.has_subscribers("error"), what="subscriber")
    bus.publish_calibration({"kind": "command", "seq": 40, "t_s": float("nan"),
                             "state": {"usable": True, "gate": {"coverage": np.float64(0.8)}}})
    bus.publish_health({"frames_accepted": np.int64(1234), "crc_failures": 2})
    bus.publish_error({"s1.scalar": 0.71, "s2-s1.x": float("inf")}, seq=40, t_s=0.2)
    got = {m.stream: m.value for m in collect(client, 3)}
    assert got["calibration"]["t_s"] is None and got["calibration"]["state"]["gate"]["coverage"] == 0.8
    assert got["calibration"]["unit"] == "u1"
    assert got["health"]["counters"] == {"frames_accepted": 1234, "crc_failures": 2}
    assert got["health"]["bus"]["published_calibration"] == 1
    assert got["error"]["rms_nT"] == {"s1.scalar": 0.71, "s2-s1.x": None} and got["error"]["seq"] == 40


def test_a_burst_of_block_streams_loses_nothing_even_through_a_small_receive_queue(stack):
    cfg, ep = peer_cfg()
    bus = stack.enter_context(ServiceBus(cfg, "u1", per_probe=False))
    # capacity 8: the burst must be held back (BLOCK), not dropped
    client = stack.enter_context(BusClient(ZenohConfig.client(ep), "u1", streams=["raw", "corrected"], capacity=8))
    wait_until(lambda: bus.has_subscribers("raw") and bus.has_subscribers("corrected"), what="subscribers")
    n_msgs, n = 2000, 5
    got: list = []
    reader = threading.Thread(target=lambda: got.extend(collect(client, 2 * n_msgs, timeout=30.0)))
    reader.start()
    for i in range(n_msgs):
        block = make_block(n, 2, seq0=i * n, seed=i % 7)
        bus.publish_raw(block)
        bus.publish_corrected(make_corrected(block, tensor=False))
    reader.join(40.0)
    raw = [m.value for m in got if m.stream == "raw"]
    cor = [m.value for m in got if m.stream == "corrected"]
    assert len(raw) == n_msgs and len(cor) == n_msgs
    assert np.array_equal(np.concatenate([b.seq for b in raw]), np.arange(n_msgs * n))   # in order, no gap
    assert np.array_equal(np.concatenate([b.seq for b in cor]), np.arange(n_msgs * n))
    assert bus.stats["published_raw"] == n_msgs and bus.stats["publish_errors"] == 0


def test_a_lossy_client_keeps_the_newest_and_never_holds_the_service_back(stack):
    cfg, ep = peer_cfg()
    bus = stack.enter_context(ServiceBus(cfg, "u1", per_probe=False))
    client = stack.enter_context(BusClient(ZenohConfig.client(ep), "u1", streams=["raw"], lossless=False,
                                           capacity=4))
    wait_until(lambda: bus.has_subscribers("raw"), what="subscriber")
    t0 = time.monotonic()
    for i in range(500):                                   # nobody reads the client meanwhile
        bus.publish_raw(make_block(5, 2, seq0=5 * i))
    publish_s = time.monotonic() - t0
    time.sleep(0.3)
    got = client.drain()
    assert 1 <= len(got) <= 8
    assert int(got[-1].value.seq[-1]) == 2499               # the newest survived
    assert publish_s < 5.0


def test_malformed_payloads_are_counted_not_fatal(stack):
    cfg, ep = peer_cfg()
    bus = stack.enter_context(ServiceBus(cfg, "u1"))
    client = stack.enter_context(BusClient(ZenohConfig.client(ep), "u1", streams=["raw", "health"]))
    wait_until(lambda: bus.has_subscribers("raw") and bus.has_subscribers("health"), what="subscribers")
    bus.session.put("fluxcal/u1/raw", b"not a block")
    bus.session.put("fluxcal/u1/health", b"{not json")
    bus.publish_raw(make_block(3, 2))
    msgs = collect(client, 1)
    assert len(msgs) == 1 and msgs[0].stream == "raw"
    wait_until(lambda: client.stats["decode_errors"] == 2, what="decode errors")
    assert "fluxcal/u1/" in client.last_decode_error


# --- state and commands ----------------------------------------------------------------------------

def test_state_query_is_answered_from_the_service_thread(stack):
    cfg, ep = peer_cfg()
    calls: list[str] = []

    def state_fn() -> dict:
        calls.append(threading.current_thread().name)
        return {"usable": True, "gate": {"coverage": 0.83}, "health": {"frames_accepted": 17}}

    bus = stack.enter_context(ServiceBus(cfg, "u1", state_fn=state_fn, probe_names=["s1", "s2"]))
    daemon = FakeDaemon(bus)
    stack.callback(daemon.close)
    client = stack.enter_context(BusClient(ZenohConfig.client(ep), "u1", streams=[]))
    st = client.query_state(timeout=2.0)
    assert st["usable"] is True and st["gate"]["coverage"] == 0.83 and st["health"]["frames_accepted"] == 17
    assert st["unit"] == "u1" and st["probe_names"] == ["s1", "s2"] and st["bus"]["state_queries"] == 1
    assert calls and set(calls) == {daemon.thread.name}        # never on a zenoh thread
    assert st["stale"] is False and st["state_age_s"] == 0.0


def test_state_without_a_callback_reports_the_last_published_calibration_and_health(stack):
    cfg, ep = peer_cfg()
    bus = stack.enter_context(ServiceBus(cfg, "u1"))
    daemon = FakeDaemon(bus)
    stack.callback(daemon.close)
    client = stack.enter_context(BusClient(ZenohConfig.client(ep), "u1", streams=[]))
    assert client.query_state()["usable"] is False
    bus.publish_calibration({"kind": "calibration", "state": {"usable": True, "cal_id": 2}})
    bus.publish_health({"frames_accepted": 5})
    st = client.query_state()
    assert st["usable"] is True and st["cal_id"] == 2 and st["health"] == {"frames_accepted": 5}


def test_commands_reach_the_service_queue_and_the_client_gets_its_answer(stack):
    cfg, ep = peer_cfg()
    bus = stack.enter_context(ServiceBus(cfg, "u1"))
    daemon = FakeDaemon(bus, answer={"ok": True, "cal_id": 7})
    stack.callback(daemon.close)
    client = stack.enter_context(BusClient(ZenohConfig.client(ep), "u1", streams=[]))
    cal_text = json.dumps({"method": "ellipsoid", "sensors": []})
    r1 = client.command("freeze")
    r2 = client.command("apply", cal_text)
    r3 = client.command("add-effect", "temperature")
    assert r1 == {"id": 1, "command": "freeze", "ok": True, "cal_id": 7, "applied": "freeze"}
    assert (r2["id"], r2["command"], r3["id"], r3["command"]) == (2, "apply", 3, "add-effect")
    assert [(i, n, p) for i, n, p, _ in daemon.seen] == [(1, "freeze", ""), (2, "apply", cal_text),
                                                          (3, "add-effect", "temperature")]
    assert {t for *_, t in daemon.seen} == {daemon.thread.name}      # applied on the service's thread


def test_malformed_commands_are_refused_at_once_and_never_reach_the_service(stack):
    cfg, ep = peer_cfg()
    bus = stack.enter_context(ServiceBus(cfg, "u1"))
    daemon = FakeDaemon(bus)
    stack.callback(daemon.close)
    client = stack.enter_context(BusClient(ZenohConfig.client(ep), "u1", streams=[]))
    with pytest.raises(BusError, match="cmd/apply: refused: needs a payload"):
        client.command("apply")
    with pytest.raises(BusError, match="'Temperature!' is not an effect name"):
        client.command("add-effect", "Temperature!")
    with pytest.raises(ConfigError, match="command 'calibrate' is not allowed"):
        client.command("calibrate")
    assert daemon.seen == [] and bus.stats["commands_refused"] == 2


def test_a_wildcard_query_reads_state_and_runs_no_command(stack):
    """One get of fluxcal/** (what a zenoh browser sends) ran reset, freeze and unfreeze in whatever order they came,
    and left the service frozen (a field trial). A command runs only when asked by its own key; the state answers."""
    import zenoh

    cfg, ep = peer_cfg()
    bus = stack.enter_context(ServiceBus(cfg, "u1", state_fn=lambda: {"unit": "u1"}))
    daemon = FakeDaemon(bus)
    stack.callback(daemon.close)
    client = stack.enter_context(BusClient(ZenohConfig.client(ep), "u1", streams=[]))
    for wild in ("fluxcal/**", "fluxcal/u1/cmd/*", "fluxcal/*/cmd/freeze"):
        replies = list(client.session.get(wild, timeout=2.0, consolidation=zenoh.ConsolidationMode.NONE))
        oks = [json.loads(r.ok.payload.to_bytes()) for r in replies if r.ok is not None]
        errs = [json.loads(r.err.payload.to_bytes()) for r in replies if r.err is not None]
        assert all("command" not in o for o in oks), (wild, oks)
        assert errs and all(e["ok"] is False and "a command runs only when asked by its own key" in e["error"]
                            for e in errs), (wild, errs)
    time.sleep(0.1)
    assert daemon.seen == []
    assert client.command("freeze")["applied"] == "freeze"          # its own key still runs it


def test_a_command_nobody_takes_is_withdrawn_unapplied_and_a_full_queue_says_busy(stack):
    cfg, ep = peer_cfg()
    bus = stack.enter_context(ServiceBus(cfg, "u1", command_queue_size=1))
    client = stack.enter_context(BusClient(ZenohConfig.client(ep), "u1", streams=[]))
    answers: list = []
    first = threading.Thread(target=lambda: answers.append(client.command("reset", timeout=0.6)))
    t0 = time.monotonic()
    first.start()
    wait_until(lambda: bus.stats["commands_received"] == 1, what="first command")
    with pytest.raises(BusError, match="refused: busy: 1 commands pending"):
        client.command("freeze", timeout=0.6)        # the queue (size 1) is full: refused at once
    first.join(3.0)
    elapsed = time.monotonic() - t0
    # the client waits 0.6 s; the bus gives up 0.12 s earlier (0.2 x timeout) so its answer arrives in time
    assert len(answers) == 1 and answers[0]["ok"] is False and answers[0]["command"] == "reset"
    assert "not applied" in answers[0]["error"] and 0.4 < elapsed < 0.6
    assert bus.stats["commands_expired"] == 1
    assert bus.pending_commands() == []              # withdrawn: the service never applies it later
    # a service that takes its commands in time applies them and is heard
    daemon = FakeDaemon(bus, answer={"ok": True})
    stack.callback(daemon.close)
    assert client.command("reset", timeout=0.6)["ok"] is True
    assert [n for _, n, _, _ in daemon.seen] == ["reset"]


def test_a_busy_service_thread_still_answers_state_from_its_last_state(stack):
    """The daemon's thread sleeps up to 5 s in a reconnect back-off: state comes from the bus's own thread."""
    cfg, ep = peer_cfg()
    counters = {"read_errors": 0}
    bus = stack.enter_context(ServiceBus(cfg, "u1", state_fn=lambda: {"usable": True, "cal_id": 3,
                                                                      "health": dict(counters)}))
    client = stack.enter_context(BusClient(ZenohConfig.client(ep), "u1", streams=[]))
    t0 = time.monotonic()
    st = client.query_state(timeout=2.0)            # nobody ever drained: no state computed yet
    assert time.monotonic() - t0 < 1.0
    assert st["stale"] is True and st["state_age_s"] is None and st["usable"] is False and st["unit"] == "u1"
    bus.pending_commands()                          # the service's thread passes once, then is busy
    counters["read_errors"] = 5
    time.sleep(0.3)
    t0 = time.monotonic()
    st = client.query_state(timeout=2.0)
    assert time.monotonic() - t0 < 1.0
    assert st["stale"] is True and st["state_age_s"] >= 0.3
    assert st["cal_id"] == 3 and st["health"] == {"read_errors": 0}     # as of when it was computed
    assert st["bus"]["state_queries_stale"] == 2
    bus.pending_commands()                          # the thread is back: fresh again
    daemon = FakeDaemon(bus)
    stack.callback(daemon.close)
    st = client.query_state(timeout=2.0)
    assert st["stale"] is False and st["health"] == {"read_errors": 5}


def test_close_answers_pending_commands_drops_the_token_and_is_idempotent(stack):
    cfg, ep = peer_cfg()
    bus = ServiceBus(cfg, "u1")
    client = stack.enter_context(BusClient(ZenohConfig.client(ep), "u1", streams=[]))
    assert client.alive() is True and discover_units(client.session) == ["u1"]
    answers: list = []
    t = threading.Thread(target=lambda: answers.append(client.command("freeze", timeout=3.0)))
    t.start()
    wait_until(lambda: bus.stats["commands_received"] == 1, what="command")
    bus.close()
    bus.close()
    t.join(3.0)
    assert answers and answers[0]["ok"] is False and "stopping" in answers[0]["error"]
    wait_until(lambda: not client.alive(timeout=0.2), timeout=3.0, what="token gone")
    with pytest.raises(BusError, match="after the bus was closed"):
        bus.publish_health({})


def test_a_bus_on_a_shared_session_leaves_the_session_open(stack):
    cfg, _ = peer_cfg()
    session = open_session(cfg)
    stack.callback(session.close)
    with ServiceBus(session, "u1") as bus:
        bus.publish_health({"frames_accepted": 1})
    assert not session.is_closed()
    session.put("fluxcal/u1/health", b"{}")          # still usable


# --- the multi-host layout on loopback ------------------------------------------------------------

@pytest.mark.parametrize("unit_mode", ["client", "peer"])
def test_router_in_the_middle_relays_streams_state_and_commands(stack, unit_mode):
    """unit (client or peer) -> router <- dashboard (client): what a site does with zenohd, here a Python router."""
    router_ep = f"tcp/127.0.0.1:{free_port()}"
    router = open_session(load_section(ZenohConfig, {"mode": "router", "listen": [router_ep]}, "zenoh"))
    stack.callback(router.close)
    unit_table = {"mode": unit_mode, "connect": [router_ep]}
    if unit_mode == "peer":
        unit_table["listen"] = [f"tcp/127.0.0.1:{free_port()}"]
    unit_cfg = load_section(ZenohConfig, unit_table, "zenoh")
    bus = stack.enter_context(ServiceBus(unit_cfg, "far1", state_fn=lambda: {"usable": True, "cal_id": 9}))
    daemon = FakeDaemon(bus, answer={"ok": True, "cal_id": 10})
    stack.callback(daemon.close)
    dash = stack.enter_context(BusClient(ZenohConfig.client(router_ep), "far1",
                                         streams=["corrected", "calibration", "health"]))
    wait_until(lambda: bus.has_subscribers("corrected") and bus.has_subscribers("health"), what="routed subscribers")
    block = make_block(20, 2, seq0=77)
    cor = make_corrected(block, tensor=False)
    for i in range(50):
        bus.publish_corrected(CorrectedBlock(t_s=cor.t_s, seq=cor.seq + 20 * i, corrected_nT=cor.corrected_nT,
                                             diff_nT=cor.diff_nT, tensor_nT_m=None, center_nT=cor.center_nT,
                                             cal_id=cor.cal_id))
    bus.publish_calibration({"kind": "calibration", "state": {"usable": True}})
    bus.publish_health({"frames_accepted": 1000})
    msgs = collect(dash, 52)
    cors = [m.value for m in msgs if m.stream == "corrected"]
    assert len(cors) == 50
    assert np.array_equal(np.concatenate([c.seq for c in cors]), 77 + np.arange(1000))
    assert_blocks_equal(cor, cors[0])
    assert {m.stream for m in msgs} == {"corrected", "calibration", "health"}
    assert dash.query_state()["cal_id"] == 9
    assert dash.command("unfreeze")["cal_id"] == 10
    assert dash.alive() and discover_units(dash.session) == ["far1"]
    info = dash.session.info
    assert info.routers_zid() and not info.peers_zid()                 # it talks to the router only
