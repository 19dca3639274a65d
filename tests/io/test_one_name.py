"""One unit name, one service (issue 38, build 3), on two local Zenoh peers: a second service under a name another
live service holds refuses to start and names the holder (or, with unit.duplicate = "suffix", serves under the first
free name-2), two that started at once each say the other, and a command answered by both is reported as such.

Before: two services with the same unit name (a copied configuration) said nothing; a subscriber to
fluxcal/grad1/raw got both streams interleaved, one `freeze` was applied by both, and the client got one answer.
"""

from __future__ import annotations

import time
from contextlib import ExitStack
from pathlib import Path

import pytest
from test_zenoh_bus import FakeDaemon
from test_zenoh_security import free_port

from fluxcal.service.io.bus import BusClient, BusError, ServiceBus, ZenohConfig, open_session
from fluxcal.service.io.bus import claim as claim_mod
from fluxcal.service.wiring.status import StatusLog


def peers(stack: ExitStack) -> tuple[str, ZenohConfig, ZenohConfig]:
    """Two peers on loopback: the first listens, the second listens too and connects to the first."""
    a, b = f"tcp/127.0.0.1:{free_port()}", f"tcp/127.0.0.1:{free_port()}"
    return a, ZenohConfig(listen=[a]), ZenohConfig(listen=[b], connect=[a])


def test_a_second_service_under_a_held_name_refuses_to_start_naming_the_holder(tmp_path):
    with ExitStack() as stack:
        _, first_cfg, second_cfg = peers(stack)
        first = stack.enter_context(ServiceBus(first_cfg, "grad1", state_fn=lambda: {"usable": False},
                                               config="/site/grad1.toml"))
        stack.callback(FakeDaemon(first).close)          # answers state queries, as the service's thread does
        t0 = time.monotonic()
        with pytest.raises(BusError) as e:
            ServiceBus(second_cfg, "grad1", config="/copy/grad1.toml")
        msg = str(e.value)
        assert msg.startswith("unit.name: 'grad1' is already served on this Zenoh network by fluxcal on host ")
        assert f"zenoh id {first.identity['zid']}" in msg and "configuration '/site/grad1.toml'" in msg
        assert f"pid {first.identity['pid']}" in msg and 'unit.duplicate = "suffix"' in msg
        assert time.monotonic() - t0 < 5.0
        # configured so, it takes the first free suffix and says so
        second = stack.enter_context(ServiceBus(second_cfg, "grad1", duplicate="suffix"))
        assert second.unit == "grad1-2" and second.keys.root == "fluxcal/grad1-2"
        assert "held on this network by fluxcal on host" in second.claim_note and "serving as 'grad1-2'" in second.claim_note
        third = stack.enter_context(ServiceBus(ZenohConfig(listen=[f"tcp/127.0.0.1:{free_port()}"],
                                                           connect=first_cfg.listen), "grad1", duplicate="suffix"))
        assert third.unit == "grad1-3"


def test_two_services_that_started_at_once_each_say_the_other_and_a_shared_command_is_reported(monkeypatch):
    with ExitStack() as stack:
        a_ep, first_cfg, second_cfg = peers(stack)
        first = stack.enter_context(ServiceBus(first_cfg, "grad1"))
        monkeypatch.setattr(claim_mod, "free_name", lambda session, unit, duplicate: (unit, ""))   # a race: unseen
        second = stack.enter_context(ServiceBus(second_cfg, "grad1"))
        for bus in (first, second):
            stack.callback(FakeDaemon(bus, answer={"ok": True, "cal_id": 1}).close)
        deadline = time.monotonic() + 5
        while not (first.other_holders() and second.other_holders()):
            assert time.monotonic() < deadline, "the holders never saw each other"
            time.sleep(0.05)
        assert first.other_holders() == [second.identity["zid"]] and first.stats["duplicate_holders"] == 1
        said: list[str] = []
        status = StatusLog(said.append, 10.0)
        status.holders(first)
        status.holders(first)                                   # said once
        assert len(said) == 1 and f"another service announces unit grad1 on this Zenoh network (zenoh id " \
            f"{second.identity['zid']})" in said[0]
        client = stack.enter_context(BusClient(ZenohConfig.client(a_ep), "grad1", streams=[]))
        answer = client.command("freeze", timeout=5.0)
        assert answer["ok"] is True and answer["answered_by"] == 2 and len(answer["answers"]) == 2
        assert answer["warning"].startswith("2 services answered for unit 'grad1'")


def test_fluxcal_run_under_a_held_name_exits_naming_the_holder(tmp_path, capsys):
    """The whole service: a second `fluxcal run` with a copied configuration, connected to the first."""
    from test_unit_identity import Service

    from fluxcal.service.wiring.cli import main

    with ExitStack() as stack:
        (tmp_path / "a").mkdir()
        first = Service(tmp_path / "a", stack)
        copy = Path(first.cfg.path).read_text().replace(
            f'listen = ["{first.endpoint}"]', f'listen = ["tcp/127.0.0.1:{free_port()}"]').replace(
            "connect = []", f'connect = ["{first.endpoint}"]')
        (tmp_path / "copy.toml").write_text(copy)
        assert main(["run", "--config", str(tmp_path / "copy.toml")], install_signals=False) == 1
        err = capsys.readouterr().err
        assert "fluxcal run: unit.name: 'grad1' is already served on this Zenoh network by fluxcal on host" in err
        assert f"configuration {first.cfg.path!r}" in err
        assert first.thread.is_alive() and first.client.query_state(timeout=5.0)["unit"] == "grad1"


def test_a_session_alone_sees_no_holder_quickly():
    with open_session(ZenohConfig(listen=[f"tcp/127.0.0.1:{free_port()}"])) as s:
        t0 = time.monotonic()
        assert claim_mod.holders(s, claim_mod.Keys("nobody")) == [] and time.monotonic() - t0 < 2.5


def test_fluxcal_run_configured_to_take_a_suffix_serves_under_it(tmp_path):
    import threading

    from test_unit_identity import Service

    from fluxcal.service.wiring.config import load_config
    from fluxcal.service.wiring.daemon import Daemon

    with ExitStack() as stack:
        (tmp_path / "a").mkdir()
        first = Service(tmp_path / "a", stack)
        copy = Path(first.cfg.path).read_text().replace(
            f'listen = ["{first.endpoint}"]', f'listen = ["tcp/127.0.0.1:{free_port()}"]').replace(
            "connect = []", f'connect = ["{first.endpoint}"]').replace("[unit]\n", '[unit]\nduplicate = "suffix"\n')
        (tmp_path / "copy.toml").write_text(copy)
        said: list[str] = []
        second = Daemon(load_config(tmp_path / "copy.toml"), say=said.append)
        thread = threading.Thread(target=second.run, daemon=True)
        thread.start()
        stack.callback(lambda: (second.stop.set(), thread.join(20)))
        deadline = time.monotonic() + 20
        while not any(m.startswith("publishing on zenoh under fluxcal/grad1-2/") for m in said):
            assert time.monotonic() < deadline and thread.is_alive(), said
            time.sleep(0.05)
        assert any("unit name 'grad1' is held on this network by fluxcal on host" in m and "serving as 'grad1-2'" in m
                   for m in said), said
        assert first.client.query_state(timeout=5.0)["unit"] == "grad1"
