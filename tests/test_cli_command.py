"""`fluxcal command`: the running service's commands and state from the command line, over Zenoh on
loopback, against a bus that answers as the service does."""

from __future__ import annotations

import json

import numpy as np
from test_watch import free_port
from test_zenoh_bus import FakeDaemon

from service.io.bus import ServiceBus, ZenohConfig
from service.io.calfile import save_calibration
from service.numerics.calib.model import ArrayCalibration, ProbeCalibration
from service.wiring.cli import main


def _as_the_daemon_does(cmd) -> dict:
    """freeze and apply are applied; add-effect of an effect the running service cannot add is refused."""
    if cmd.name == "add-effect" and cmd.payload != "temperature":
        return {"ok": False, "error": f"add-effect: {cmd.payload!r} cannot be added"}
    return {"ok": True, "cal_id": 4}


def test_state_and_commands_round_trip_and_a_refusal_exits_1(capsys, tmp_path):
    ep = f"tcp/127.0.0.1:{free_port()}"
    bus = ServiceBus(ZenohConfig(listen=[ep]), "grad9", state_fn=lambda: {"usable": True, "cal_id": 3})
    svc = FakeDaemon(bus, decide=_as_the_daemon_does)
    svc.ep = ep
    try:
        assert main(["command", "state", "--connect", svc.ep]) == 0     # the unit is found by itself
        st = json.loads(capsys.readouterr().out)
        assert st["unit"] == "grad9" and st["cal_id"] == 3
        assert main(["command", "freeze", "--connect", svc.ep, "--unit", "grad9"]) == 0
        assert json.loads(capsys.readouterr().out)["ok"] is True
        assert main(["command", "add-effect", "eddy", "--connect", svc.ep]) == 1
        out, err = capsys.readouterr()
        assert json.loads(out)["ok"] is False and "not applied by unit grad9" in err and "'eddy'" in err
        cal = tmp_path / "cal.json"
        save_calibration(ArrayCalibration("ellipsoid", None, [ProbeCalibration("s1", np.zeros(3), np.eye(3))]), cal)
        assert main(["command", "apply", str(cal), "--connect", svc.ep]) == 0
        applied = [(name, payload) for _, name, payload, _ in svc.seen if name != "add-effect"]
        assert applied == [("freeze", ""), ("apply", cal.read_text().strip())]
    finally:
        svc.close()
        bus.close()


def test_a_wrong_verb_or_a_missing_payload_is_a_usage_error(capsys):
    assert main(["command", "explode", "--connect", "tcp/127.0.0.1:1"]) == 2
    assert "VERB: 'explode' is not allowed (allowed: state, " in capsys.readouterr().err
    assert main(["command", "add-effect", "--connect", "tcp/127.0.0.1:1"]) == 2
    assert "add-effect: needs a payload" in capsys.readouterr().err
