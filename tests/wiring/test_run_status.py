"""`fluxcal run` says what it does: a status line at an interval, the quality gate's reasons when they
change, and every command it received with its answer (before, these reached only Zenoh and MCAP)."""

from __future__ import annotations

import threading
import time

from test_recording import service_config
from test_watch import free_port

from fluxcal.service.io.bus import BusClient, ZenohConfig
from fluxcal.service.wiring.config import load_config
from fluxcal.service.wiring.daemon import Daemon


def test_run_says_status_gate_reasons_and_commands(tmp_path):
    port = free_port()
    path = service_config(tmp_path, run_s=8)              # the example, with its own files
    text = (open(path).read()
            .replace('listen = ["tcp/127.0.0.1:0"]', f'listen = ["tcp/127.0.0.1:{port}"]')
            .replace("status_s = 10 ", "status_s = 1.0 ")
            .replace("min_samples = 2000 ", "min_samples = 200 ")        # a gate verdict within the first second
            .replace("check_every_s = 5.0 ", "check_every_s = 0.5 "))
    (tmp_path / "c.toml").write_text(text)
    said: list[str] = []
    daemon = Daemon(load_config(tmp_path / "c.toml"), say=said.append)
    thread = threading.Thread(target=daemon.run, daemon=True)
    thread.start()
    try:
        time.sleep(4.0)
        with BusClient(ZenohConfig.client(f"tcp/127.0.0.1:{port}"), "grad1", streams=[]) as client:
            assert client.command("freeze", timeout=5.0)["ok"]
            assert not client.command("add-effect", "eddy", timeout=5.0)["ok"]
    finally:
        thread.join(20.0)
    status = [m for m in said if m.startswith("status: ")]
    assert len(status) >= 3 and all("samples/s" in m and ("learning" in m or "in use" in m) for m in status)
    gate = [m for m in said if m.startswith("quality gate: ")]
    assert gate and len(gate) <= 3                      # said when the reasons change, not at every check
    assert any(m.startswith("command freeze: applied") for m in said)
    assert any(m.startswith("command add-effect eddy: refused: add-effect: 'eddy'") for m in said)


def test_the_status_line_says_whose_coverage_it_gives():
    """The gate's figures are the latest check's, said as such: a user read 'calibration 6 in use, coverage 23 %'
    as the coverage of the calibration in use, beside a dashboard saying 38 %."""
    from fluxcal.service.wiring.status import StatusLog

    said: list[str] = []
    log = StatusLog(said.append, 0.0)
    log.block(200, {"s1.scalar": 0.61})
    log.tick({"usable": True, "cal_id": 6, "held": True,
              "gate": {"usable": False, "coverage": 0.23, "condition": 12.5, "reasons": ["s1: only 23 %"]}})
    assert said and ("calibration 6 in use (applied: held until reset); latest check refused: coverage 23% of its "
                     "window, condition 12.5; error rms nT over the last ") in said[-1], said
    assert said[-1].endswith("s (200 samples): s1.scalar 0.61"), said


def test_the_status_line_says_a_silent_input(monkeypatch):
    """With the cable pulled the status line said '0 samples/s; calibration 18 in use; latest check passed' for 70 s
    (a new user): it now says since when no samples came."""
    from fluxcal.service.wiring import status

    clock = [1000.0]
    monkeypatch.setattr(status.time, "monotonic", lambda: clock[0])
    said: list[str] = []
    log = status.StatusLog(said.append, 10.0)
    log.block(100, {})
    clock[0] += 10.0
    log.tick({"usable": True, "cal_id": 18, "gate": {"usable": True}})
    assert said[-1].startswith("status: 10 samples/s; calibration 18 in use") and "silent" not in said[-1]
    for _ in range(7):                                   # 80 s since the last samples (at the first block)
        clock[0] += 10.0
        log.tick({"usable": True, "cal_id": 18, "gate": {"usable": True}})
    assert said[-1].startswith("status: 0 samples/s; no samples for 80 s (since "), said[-1]
    assert "): the input is silent; calibration 18 in use; latest check passed" in said[-1]
    clock[0] += 10.0                                     # bytes arrive that decode into no frame: not silent
    log.tick({"usable": True, "cal_id": 18, "gate": {"usable": True}}, ["no_decode"])
    assert "): the input arrives but decodes into no frame of the unit's; calibration 18" in said[-1], said[-1]
    clock[0] += 10.0
    log.tick({"usable": True, "cal_id": 18, "gate": {"usable": True}}, ["input_lost"])
    assert "): the input is lost (reconnecting); calibration 18" in said[-1], said[-1]
    log.block(50, {})                                    # it comes back
    clock[0] += 10.0
    log.tick({"usable": True, "cal_id": 18, "gate": {"usable": True}})
    assert "silent" not in said[-1]


def test_a_flood_of_commands_is_said_in_ten_lines_and_a_count(monkeypatch):
    """500 commands in 5 s were 500 console lines (a field trial): ten are said one by one between two status lines,
    the rest counted and said with the next, applied and refused apart; the refusals are all counted."""
    from fluxcal.service.wiring import status

    clock = [1000.0]
    monkeypatch.setattr(status.time, "monotonic", lambda: clock[0])
    said: list[str] = []
    log = status.StatusLog(said.append, 10.0)
    for k in range(500):
        log.command("freeze", "", {"ok": True, "cal_id": 3} if k % 2 else {"ok": False, "error": "busy"})
    assert len(said) == status.StatusLog.COMMAND_LINES and log.refused == 250
    clock[0] += 10.0
    log.tick({"usable": True, "cal_id": 3})
    assert said[-2] == ("490 more command(s) since the last status line, not said one by one: 245 applied, 245 "
                        "refused (state: commands_refused)")
    log.command("unfreeze", "", {"ok": True, "cal_id": 3})
    assert said[-1] == "command unfreeze: applied (calibration 3)"            # a new interval: said again
