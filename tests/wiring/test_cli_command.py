"""`fluxcal command`: the running service's commands and state from the command line, over Zenoh on
loopback, against a bus that answers as the service does."""

from __future__ import annotations

import json

import numpy as np
from test_watch import free_port
from test_zenoh_bus import FakeDaemon

from fluxcal.service.io.bus import ServiceBus, ZenohConfig
from fluxcal.service.io.calfile import save_calibration
from fluxcal.service.numerics.calib.model import ArrayCalibration, ProbeCalibration
from fluxcal.service.wiring.cli import main


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
        assert main(["command", "state", "--connect", svc.ep, "--json"]) == 0     # the unit is found by itself
        st = json.loads(capsys.readouterr().out)
        assert st["unit"] == "grad9" and st["cal_id"] == 3
        assert main(["command", "freeze", "--connect", svc.ep, "--unit", "grad9", "--json"]) == 0
        assert json.loads(capsys.readouterr().out)["ok"] is True
        assert main(["command", "freeze", "--connect", svc.ep, "--unit", "grad9"]) == 0
        assert capsys.readouterr().out == "freeze: done by unit grad9; calibration 4 in use\n"
        assert main(["command", "add-effect", "eddy", "--connect", svc.ep, "--json"]) == 1
        out, err = capsys.readouterr()
        assert json.loads(out)["ok"] is False and "not applied by unit grad9" in err and "'eddy'" in err
        assert main(["command", "add-effect", "eddy", "--connect", svc.ep]) == 1
        out, err = capsys.readouterr()
        assert out == "" and "not applied by unit grad9" in err
        cal = tmp_path / "cal.json"
        save_calibration(ArrayCalibration("ellipsoid", None, [ProbeCalibration("s1", np.zeros(3), np.eye(3))]), cal)
        assert main(["command", "apply", str(cal), "--connect", svc.ep]) == 0
        applied = [(name, payload) for _, name, payload, _ in svc.seen if name != "add-effect"]
        assert applied == [("freeze", ""), ("freeze", ""), ("apply", cal.read_text().strip())]
    finally:
        svc.close()
        bus.close()


def test_a_wrong_verb_or_a_missing_payload_is_a_usage_error(capsys):
    assert main(["command", "explode", "--connect", "tcp/127.0.0.1:1"]) == 2
    assert "VERB: 'explode' is not allowed (allowed: state, " in capsys.readouterr().err
    assert main(["command", "add-effect", "--connect", "tcp/127.0.0.1:1"]) == 2
    assert "add-effect: needs a payload" in capsys.readouterr().err


#: a running service's state as `fluxcal run --config configs/sim-gradiometer.toml` gave it (shortened)
STATE = {"cal_id": 10, "usable": True, "frozen": False, "held": False, "method": "rls", "align": "rotation",
         "total_nT": 52500.0, "span": [65.0, 94.995, 6000], "effects": [],
         "probes": [{"name": n, "offset_nT": o, "matrix": m, "offset_se_nT": [0.0549, -1.0, 0.291],
                     "matrix_se": [[1e-6] * 3] * 3,
                     "params": {"misalign_deg": {"value": [1.947, -2.0035, 2.1215], "se": None, "unit": "deg"}}}
                    for n, o, m in (("s1", [214.994, -339.920, 120.016], [[0.97855, 0.06244, 0.01854],
                                                                          [-0.03741, 1.01466, -0.00207],
                                                                          [-0.03298, -0.03668, 0.98874]]),
                                    ("s2", [-179.984, 265.0, 390.147], [[1.02666, -0.04705, -0.01693],
                                                                        [0.03803, 0.96562, 0.01266],
                                                                        [0.03594, 0.03249, 1.01015]]))],
         "gate": {"usable": False, "reasons": ["s1: only 27% of the directions seen (at least 30% needed)"],
                  "coverage": 0.27, "condition": 53.49, "rms_nT": [0.5689, 0.8872]},
         "samples_seen": 19500, "probe_names": ["s1", "s2"],
         "health": {"frames_accepted": 19597, "crc_failures": 2, "seq_gaps": 0},
         "recording": {"files": 1, "current": "live/grad1-0001.mcap", "messages_written": 6860,
                       "bytes_written": 3230907, "dropped": 0, "errors": 0, "last_error": ""}}


def test_state_is_printed_for_a_person_and_as_json_with_json(capsys):
    """`command state` printed one line of raw JSON, some 3,000 characters: now lines a person reads, each figure
    with what it is, and the JSON itself with --json."""
    ep = f"tcp/127.0.0.1:{free_port()}"
    bus = ServiceBus(ZenohConfig(listen=[ep]), "grad9", state_fn=lambda: STATE)
    svc = FakeDaemon(bus)
    try:
        assert main(["command", "state", "--connect", ep]) == 0
        text = capsys.readouterr().out
        assert main(["command", "state", "--connect", ep, "--json"]) == 0
        st = json.loads(capsys.readouterr().out)
    finally:
        svc.close()
        bus.close()
    assert {k: st[k] for k in STATE} == STATE and st["unit"] == "grad9"
    lines = text.splitlines()
    assert len(lines) > 10 and "{" not in text and all(len(ln) < 200 for ln in lines)
    assert lines[0] == "unit grad9: calibration 10 in use (method rls, align rotation, total field 52500.0 nT)"
    assert ("quality gate, latest online candidate: refused; coverage 27% of the 26 direction bins in its window; "
            "condition 53.5; scalar residual RMS s1 0.569 nT, s2 0.887 nT (the calibration in use stays)") in lines
    assert "  s1: only 27% of the directions seen (at least 30% needed)" in lines
    assert "probe s2" in lines and "  offset nT      214.994 ± 0.055    -339.920 ± n/a     120.016 ± 0.29" in lines
    assert "               -0.03741     1.01466    -0.00207" in lines
    assert "input: 19,597 frames accepted; crc failures 2" in lines
    assert "recording: live/grad1-0001.mcap (1 file(s), 6,860 messages written, 3.2 MB)" in lines
