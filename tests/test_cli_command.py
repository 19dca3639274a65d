"""`fluxcal command`: the running service's commands and state from the command line, over Zenoh on
loopback, against a bus that answers as the service does."""

from __future__ import annotations

import json
import threading

from test_watch import free_port

from service.io.bus import ServiceBus, ZenohConfig
from service.wiring.cli import main


class Service:
    """Answers commands as the daemon does: freeze is applied, add-effect of an unknown effect refused."""

    def __init__(self) -> None:
        self.ep = f"tcp/127.0.0.1:{free_port()}"
        self.applied: list[tuple[str, str]] = []
        self.bus = ServiceBus(ZenohConfig(listen=[self.ep]), "grad9", state_fn=lambda: {"usable": True, "cal_id": 3})
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self.run, daemon=True)
        self.thread.start()

    def run(self) -> None:
        while not self.stop.is_set():
            cmd = self.bus.next_command(timeout=0.05)
            if cmd is None:
                continue
            if cmd.name == "add-effect" and cmd.payload != "temperature":
                cmd.reply({"ok": False, "error": f"add-effect: {cmd.payload!r} cannot be added"})
            else:
                self.applied.append((cmd.name, cmd.payload))
                cmd.reply({"ok": True, "cal_id": 4})

    def close(self) -> None:
        self.stop.set()
        self.thread.join(2.0)
        self.bus.close()


def test_state_and_commands_round_trip_and_a_refusal_exits_1(capsys, tmp_path):
    svc = Service()
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
        cal.write_text('{"format": "fluxcal-calibration"}')
        assert main(["command", "apply", str(cal), "--connect", svc.ep]) == 0
        assert svc.applied == [("freeze", ""), ("apply", '{"format": "fluxcal-calibration"}')]
    finally:
        svc.close()


def test_a_wrong_verb_or_a_missing_payload_is_a_usage_error(capsys):
    assert main(["command", "explode", "--connect", "tcp/127.0.0.1:1"]) == 2
    assert "VERB: 'explode' is not allowed (allowed: state, " in capsys.readouterr().err
    assert main(["command", "add-effect", "--connect", "tcp/127.0.0.1:1"]) == 2
    assert "add-effect: needs a payload" in capsys.readouterr().err
