"""`apply` given the wrong file (a CSV instead of a calibration JSON): a short error naming the file and
what was expected, at the command line and in the service, never the payload itself (before: 1.2 MB of
CSV on the terminal, 2.5 MB in the service's log, and `[Errno 36] File name too long`)."""

from __future__ import annotations

import re
import threading
import time
from pathlib import Path

import pytest
from test_recording import service_config
from test_watch import free_port
from test_zenoh_bus import FakeDaemon, wait_until

from fluxcal.drivers.errors import DataError
from fluxcal.service.io.bus import MAX_COMMAND_PAYLOAD_BYTES, BusClient, BusError, ServiceBus, ZenohConfig
from fluxcal.service.io.calfile import load_calibration
from fluxcal.service.wiring.cli import main
from fluxcal.service.wiring.config import load_config
from fluxcal.service.wiring.daemon import Daemon
from fluxcal.service.wiring.startcal import calibration_from_payload

HEADER = "t,s1_x,s1_y,s1_z,s2_x,s2_y,s2_z,s1_temp,s2_temp,ref_total,seq,flags\n"
ROW = "0.005000,46000.174,-28171.471,1854.467,40316.566,-32362.920,1211.754,22.00,22.00,52500.0454,1,0\n"


def lab_csv(path, n_bytes: int):
    """A lab CSV of about n_bytes (the 60-s example is 1.2 MB)."""
    path.write_text("# fluxcal simulate: simulated unit 'grad1'\n" + HEADER + ROW * (n_bytes // len(ROW)))
    return path


def test_command_apply_of_a_csv_is_a_short_usage_error_and_nothing_is_sent(tmp_path, capsys):
    csv = lab_csv(tmp_path / "grad.csv", 1_250_000)
    ep = f"tcp/127.0.0.1:{free_port()}"
    bus = ServiceBus(ZenohConfig(listen=[ep]), "grad9")
    svc = FakeDaemon(bus)
    try:
        for f in (csv, lab_csv(tmp_path / "small.csv", 20_000)):
            assert main(["command", "apply", str(f), "--connect", ep]) == 2
            out, err = capsys.readouterr()
            assert out == "" and len(err) < 300, err
            assert f"{f}: not a calibration file: expected a calibration JSON written by `fluxcal fit --out`" in err
            assert "it begins \"# fluxcal simulate: simulated unit 'grad1'\" ..." in err
        assert svc.seen == [] and bus.stats["commands_received"] == 0
    finally:
        svc.close()
        bus.close()


def test_the_wrong_file_elsewhere_is_refused_alike(tmp_path):
    csv = lab_csv(tmp_path / "grad.csv", 50_000)
    with pytest.raises(DataError) as e:                     # diagnose --calibration, the service's own file
        load_calibration(csv)
    assert len(str(e.value)) < 250 and "not a calibration file" in str(e.value)
    with pytest.raises(DataError) as e:                     # a payload that is not a calibration's content
        calibration_from_payload(csv.read_text())
    msg = str(e.value)
    assert len(msg) < 400 and "not a calibration's JSON content" in msg and "fluxcal fit --out" in msg
    # a path is never read: the same answer whether it names a file or not (no oracle of the host's files)
    answers = set()
    for path in (tmp_path / "nosuch.json", csv, tmp_path, "/etc/passwd"):
        with pytest.raises(DataError) as e:
            calibration_from_payload(str(path))
        answers.add(re.sub(r"\(\d+ characters\)", "(#)", str(e.value).split(" it begins ")[0]))
    assert len(answers) == 1 and "never a path" in answers.pop()


def test_the_bus_refuses_a_huge_payload_at_once_with_a_counter(tmp_path):
    ep = f"tcp/127.0.0.1:{free_port()}"
    bus = ServiceBus(ZenohConfig(listen=[ep]), "grad9")
    svc = FakeDaemon(bus)
    try:
        with BusClient(ZenohConfig.client(ep), "grad9", streams=[]) as client:
            with pytest.raises(BusError) as e:
                client.command("apply", "x" * (MAX_COMMAND_PAYLOAD_BYTES + 1))
            assert len(str(e.value)) < 250 and "payload of 1,048,577 bytes is too large (at most 1,048,576" in str(e.value)
            with pytest.raises(BusError) as e:
                client.command("add-effect", "y" * 10_000)
            assert len(str(e.value)) < 250 and "is not an effect name" in str(e.value)
        assert svc.seen == [] and bus.stats["commands_refused"] == 2
        assert bus.last_refused.startswith("add-effect: 'yyyy") and len(bus.last_refused) < 120
    finally:
        svc.close()
        bus.close()


def test_the_service_logs_a_short_line_and_counts_what_it_refused(tmp_path):
    port = free_port()
    text = Path(service_config(tmp_path, run_s=5)).read_text().replace('listen = ["tcp/127.0.0.1:0"]',
                                                                        f'listen = ["tcp/127.0.0.1:{port}"]')
    (tmp_path / "c.toml").write_text(text)
    said: list[str] = []
    daemon = Daemon(load_config(tmp_path / "c.toml"), say=said.append)
    thread = threading.Thread(target=daemon.run, daemon=True)
    thread.start()
    csv = lab_csv(tmp_path / "grad.csv", 1_250_000).read_text()
    try:
        wait_until(lambda: any(m.startswith("publishing on zenoh") for m in said), timeout=10, what="service")
        with BusClient(ZenohConfig.client(f"tcp/127.0.0.1:{port}"), "grad1", streams=[]) as client:
            answer = client.command("apply", csv[:20_000], timeout=5.0)         # under the bus's limit
            assert answer["ok"] is False and len(answer["error"]) < 300
            assert "not a calibration's JSON content" in answer["error"]
            with pytest.raises(BusError, match="too large"):
                client.command("apply", csv, timeout=5.0)                        # over it
            time.sleep(1.5)                                                      # a health tick
            health = client.query_state()["health"]
            assert health["commands_refused"] == 1
    finally:
        thread.join(20.0)
    assert max(len(m) for m in said) < 600
    assert sum("command apply: refused: apply: the payload (20,000 characters)" in m for m in said) == 1
    assert sum(m.startswith("1 command(s) refused by the bus; the last: apply: payload of 1,") for m in said) == 1


def test_inline_calibration_json_is_never_taken_for_a_file_name():
    """A calibration's JSON text given inline is longer than a file name may be: asking whether it names a file
    raised OSError (File name too long) on Python 3.11, a traceback (the review's case)."""
    from fluxcal.service.wiring.commands.command import _is_file

    text = '{"format": "fluxcal-calibration", "probes": [' + ", ".join(["{}"] * 200) + "]}"
    assert len(text) > 300
    assert _is_file(text) is False and _is_file("a" * 5000) is False and _is_file("x\0y") is False
