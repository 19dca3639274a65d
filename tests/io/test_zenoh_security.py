"""A networked deployment's security on loopback, with certificates the test makes itself
(tests/certs.py): TLS with mutual authentication and access control by certificate name.

The service listens on tls/localhost only. A dashboard whose certificate the site CA signed may read
the streams and the state but not send commands, nor inject data; an operator's certificate may also
command; a certificate the CA signed for a name nobody granted gets nothing; a client without a
certificate, one with a certificate from another CA (even under an allowed name) and a clear-text
client cannot connect at all.
"""

from __future__ import annotations

import json
import socket
import threading
import time
from contextlib import ExitStack
from pathlib import Path

import numpy as np
import pytest
from certs import Authority

from fluxcal.drivers.block import SampleBlock
from fluxcal.drivers.config import load_section
from fluxcal.drivers.errors import ConfigError
from fluxcal.service.io.bus import (
    BusClient,
    BusError,
    ServiceBus,
    ZenohAccessConfig,
    ZenohConfig,
    ZenohTlsConfig,
    discover_units,
    make_zenoh_config,
    open_session,
)
from fluxcal.service.wiring.cli import main as cli_main

UNIT = "grad1"


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def block(seq0: int, n: int = 10, value: float = 1.0) -> SampleBlock:
    return SampleBlock(t_s=(seq0 + np.arange(n)) / 100.0, seq=seq0 + np.arange(n, dtype=np.int64),
                       field_nT=np.full((n, 2, 3), value), temp_C=np.full((n, 2), 20.0),
                       flags=np.zeros(n, np.uint8))


class Site:
    """A site CA with node certificates, a rogue CA, and a secured service publishing raw blocks."""

    def __init__(self, tmp: Path, stack: ExitStack) -> None:
        ca = Authority(tmp, "site-ca")
        rogue = Authority(tmp, "rogue-ca")
        self.ca = ca.pem
        self.certs = {cn: ca.issue(cn) for cn in ("grad1-service", "dashboard", "ops", "intruder")}
        self.certs["rogue-ops"] = rogue.issue("ops", file_name="rogue-ops")
        self.endpoint = f"tls/localhost:{free_port()}"
        cert, key = self.certs["grad1-service"]
        cfg = ZenohConfig(listen=[self.endpoint], tls=ZenohTlsConfig(root_ca=self.ca, cert=cert, key=key),
                          access=ZenohAccessConfig(readers=["dashboard"], commanders=["ops"]))
        self.bus = stack.enter_context(ServiceBus(cfg, UNIT, probe_names=["a", "b"],
                                                  state_fn=lambda: {"usable": True, "cal_id": 3}))
        self.applied: list[str] = []
        stop = threading.Event()

        def service_thread() -> None:
            while not stop.is_set():
                cmd = self.bus.next_command(timeout=0.02)
                if cmd is not None:
                    self.applied.append(cmd.name)
                    cmd.reply({"ok": True})

        t = threading.Thread(target=service_thread, daemon=True)
        t.start()
        stack.callback(lambda: (stop.set(), t.join(2.0)))

    def tls(self, name: str, ca: str | None = None) -> ZenohTlsConfig:
        cert, key = self.certs[name]
        return ZenohTlsConfig(root_ca=ca or self.ca, cert=cert, key=key)

    def client(self, stack: ExitStack, name: str, streams=("raw",)) -> BusClient:
        return stack.enter_context(BusClient(ZenohConfig.client(self.endpoint, tls=self.tls(name)), UNIT,
                                             streams=list(streams)))


def received(client: BusClient, publish, timeout: float = 3.0) -> list:
    """Publish (again and again, until the first arrives or time is up), then collect what arrives."""
    out, deadline = [], time.monotonic() + timeout
    while not out and time.monotonic() < deadline:
        publish()
        m = client.recv(timeout=0.2)
        if m is not None:
            out.append(m)
    end = time.monotonic() + 0.3
    while time.monotonic() < end:
        m = client.recv(timeout=0.05)
        if m is not None:
            out.append(m)
    return out


def publish_raw_blocks(s: "Site", stack: ExitStack) -> None:
    """The secured service publishes a raw block every 50 ms until the test ends."""
    stop = threading.Event()

    def publisher() -> None:
        k = 0
        while not stop.is_set():
            s.bus.publish_raw(block(k))
            k += 10
            time.sleep(0.05)

    t = threading.Thread(target=publisher, daemon=True)
    t.start()
    stack.callback(lambda: (stop.set(), t.join(2.0)))


@pytest.fixture
def site(tmp_path):
    with ExitStack() as stack:
        yield Site(tmp_path, stack), stack


def test_a_dashboard_reads_streams_and_state_but_cannot_command_or_inject(site):
    s, stack = site
    dash = s.client(stack, "dashboard")
    seq = iter(range(0, 10 ** 6, 10))
    got = received(dash, lambda: s.bus.publish_raw(block(next(seq))))
    assert got and all(m.stream == "raw" for m in got)
    np.testing.assert_array_equal(got[0].value.field_nT, np.ones((10, 2, 3)))
    assert dash.query_state(timeout=2.0)["cal_id"] == 3
    assert discover_units(dash.session, timeout=1.0) == [UNIT]              # readers see the unit alive
    with pytest.raises(BusError, match="no answer from fluxcal/grad1/cmd/freeze"):
        dash.command("freeze", timeout=1.0)
    assert s.applied == []
    # a dashboard publishing on the unit's keys reaches nobody: the operator sees only the service's blocks
    ops = s.client(stack, "ops")
    received(ops, lambda: s.bus.publish_raw(block(next(seq))))          # the operator's link is up
    with open_session(ZenohConfig.client(s.endpoint, tls=s.tls("dashboard"))) as rogue_pub:
        fake = block(999_000, value=-7.0)
        from fluxcal.service.io.encoding import encode_raw
        for _ in range(5):
            rogue_pub.put(f"fluxcal/{UNIT}/raw", encode_raw(fake))
        time.sleep(0.3)
    s.bus.publish_raw(block(500_000, value=2.0))
    after = received(ops, lambda: None, timeout=1.0)
    values = {float(m.value.field_nT[0, 0, 0]) for m in after}
    assert values == {2.0}, values                                      # never -7: the injection was denied
    assert ops.stats["decode_errors"] == 0


def test_an_operator_may_command(site):
    s, stack = site
    ops = s.client(stack, "ops")
    assert ops.command("freeze", timeout=3.0)["ok"] is True
    assert ops.command("unfreeze", timeout=3.0)["ok"] is True
    assert s.applied == ["freeze", "unfreeze"]
    seq = iter(range(0, 10 ** 6, 10))
    assert received(ops, lambda: s.bus.publish_raw(block(next(seq))))


def test_a_valid_certificate_with_an_unlisted_name_gets_nothing(site):
    s, stack = site
    stranger = s.client(stack, "intruder")                              # the CA signed it: it connects
    seq = iter(range(0, 10 ** 6, 10))
    assert received(stranger, lambda: s.bus.publish_raw(block(next(seq))), timeout=1.5) == []
    with pytest.raises(BusError):
        stranger.query_state(timeout=1.0)
    assert discover_units(stranger.session, timeout=0.5) == []
    with pytest.raises(BusError):
        stranger.command("reset", timeout=1.0)
    assert s.applied == []


def test_no_certificate_another_ca_or_clear_text_cannot_connect(site):
    s, stack = site
    port = s.endpoint.rsplit(":", 1)[1]
    # a certificate for an allowed name, but signed by another CA
    with pytest.raises(BusError, match="With TLS, also check the certificates"):
        open_session(ZenohConfig.client(s.endpoint, tls=s.tls("rogue-ops")))
    # the right CA to check the service, but no certificate of its own
    bare = make_zenoh_config(ZenohConfig.client(s.endpoint))
    bare.insert_json5("transport/link/tls/root_ca_certificate", json.dumps(s.ca))
    with pytest.raises(BusError):
        open_session(bare)
    # clear text to the same port
    with pytest.raises(BusError):
        open_session(ZenohConfig.client(f"tcp/127.0.0.1:{port}"))
    assert s.applied == []


def test_watch_connects_with_a_dashboard_certificate(site, capsys):
    s, stack = site
    publish_raw_blocks(s, stack)
    cert, key = s.certs["dashboard"]
    assert cli_main(["watch", "--connect", s.endpoint, "--unit", UNIT, "--seconds", "2.5",
                     "--ca", s.ca, "--cert", cert, "--key", key]) == 0
    out = capsys.readouterr().out
    assert "raw" in out
    # and a key that is no PEM file is a usage error naming the flag
    assert cli_main(["watch", "--connect", s.endpoint, "--unit", UNIT, "--seconds", "1",
                     "--ca", s.ca, "--cert", cert, "--key", __file__]) == 2
    assert "--key:" in capsys.readouterr().err


def test_secured_configuration_is_checked_at_start(tmp_path):
    ca = Authority(tmp_path, "ca")
    cert, key = ca.issue("svc")
    tls = {"root_ca": ca.pem, "cert": cert, "key": key}
    ok = load_section(ZenohConfig, {"listen": ["tls/0.0.0.0:7447"], "tls": tls,
                                    "access": {"readers": ["dash"], "commanders": ["ops"]}}, "zenoh")
    z = make_zenoh_config(ok, UNIT)
    assert json.loads(z.get_json("transport/link/tls/enable_mtls")) is True
    assert json.loads(z.get_json("transport/link/protocols")) == ["tls", "quic"]
    acl = json.loads(z.get_json("access_control"))
    assert acl["enabled"] is True and acl["default_permission"] == "deny"
    names = {x["id"]: x["cert_common_names"] for x in acl["subjects"]}
    granted = {p["id"]: sorted(n for sub in p["subjects"] for n in names[sub]) for p in acl["policies"]}
    assert granted == {"readers": ["dash", "ops"], "commanders": ["ops"]}
    assert ok.exposed() == []                                            # TLS on all interfaces is not exposed
    assert ZenohConfig(listen=["tcp/0.0.0.0:7447"]).exposed() == ["tcp/0.0.0.0:7447"]
    assert ZenohConfig(listen=["tcp/127.0.0.1:7447", "tcp/localhost:1"]).exposed() == []
    (tmp_path / "notpem.txt").write_text("hello")
    bad = [
        ({"listen": ["tcp/0.0.0.0:7447"], "tls": tls}, "zenoh.listen[0]: 'tcp/0.0.0.0:7447' would carry the "
                                                       "streams and commands in clear text"),
        ({"listen": ["tls/127.0.0.1:7447"], "tls": {**tls, "key": str(tmp_path / "missing.key")}},
         "zenoh.tls.key: "),
        ({"listen": ["tls/127.0.0.1:7447"], "tls": {**tls, "cert": str(tmp_path / "notpem.txt")}},
         "zenoh.tls.cert: '" + str(tmp_path / "notpem.txt") + "' is not a PEM file"),
        ({"listen": ["tls/127.0.0.1:7447"], "tls": {**tls, "mutual": False}, "access": {"readers": ["d"]}},
         "zenoh.access: access control names peers by their client certificate"),
    ]
    for table, message in bad:
        with pytest.raises(ConfigError) as e:
            load_section(ZenohConfig, table, "zenoh")
        assert message in str(e.value)
    assert "file not found" in str(pytest.raises(ConfigError, load_section, ZenohConfig, bad[1][0], "zenoh").value)


def test_a_key_that_does_not_belong_to_its_certificate_is_named_as_such(tmp_path):
    ca = Authority(tmp_path, "ca")
    cert_a, key_a = ca.issue("a")
    cert_b, key_b = ca.issue("b")
    ep = f"tls/localhost:{free_port()}"
    for cert, key in ((cert_a, key_b), (key_a, cert_a)):                 # another certificate's key; swapped
        with pytest.raises(BusError) as e:
            open_session(ZenohConfig(listen=[ep], tls=ZenohTlsConfig(root_ca=ca.pem, cert=cert, key=key)))
        assert "does zenoh.tls.key belong to zenoh.tls.cert" in str(e.value)
        assert "another fluxcal already listening" not in str(e.value)


def test_the_web_dashboard_obeys_tls_and_access_control(site):
    """A reader's certificate: the page gets the data and the state, and a command comes back refused; an
    operator's certificate: the command is applied; a name not granted: nothing at all."""
    import json
    import urllib.request

    from fluxcal.service.wiring.dashboard import DashboardServer, Hub

    s, stack = site
    publish_raw_blocks(s, stack)

    def dashboard(name: str):
        hub = Hub([s.endpoint], [UNIT], s.tls(name)).start()
        server = DashboardServer(hub, "127.0.0.1", 0).start()
        stack.callback(lambda: (server.stop(), hub.close()))
        return server.url

    def view(url: str, until, timeout: float = 10.0) -> dict:
        deadline = time.monotonic() + timeout
        while True:
            with urllib.request.urlopen(url + f"api/view?unit={UNIT}", timeout=5) as r:
                v = json.loads(r.read())
            if until(v) or time.monotonic() > deadline:
                return v
            time.sleep(0.2)

    def command(url: str, name: str) -> dict:
        from test_dashboard import page_token

        req = urllib.request.Request(url + "api/command", data=json.dumps({"unit": UNIT, "command": name}).encode(),
                                     headers={"Content-Type": "application/json", "X-Fluxcal-Token": page_token(url)})
        with urllib.request.urlopen(req, timeout=10) as r:
            return json.loads(r.read())

    reader = dashboard("dashboard")
    v = view(reader, lambda v: v["raw"] and v["raw"]["t"] and v["state"])
    assert v["status"] == "live" and v["state"]["cal_id"] == 3 and v["raw"]["t"]
    answer = command(reader, "freeze")
    assert answer["ok"] is False and "not connected" not in answer["error"] and s.applied == [], answer
    ops = dashboard("ops")
    view(ops, lambda v: v["status"] == "live")
    answer = command(ops, "freeze")
    assert answer["ok"] is True and s.applied == ["freeze"], answer
    intruder = dashboard("intruder")
    v = view(intruder, lambda v: False, timeout=3.0)
    assert v["raw"] is None and not v["state"] and v["status"] != "live"
