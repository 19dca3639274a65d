"""`fluxcal watch` against a publishing bus on loopback: the live vectors, differences, tensor, error
metric, health and calibration state it prints; what it says when nothing arrives; clean stops."""

from __future__ import annotations

import os
import re
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from fluxcal.drivers.block import SampleBlock
from fluxcal.service.io.bus import Message, Series, ServiceBus, ZenohConfig
from fluxcal.service.numerics.outputs import CorrectedBlock
from fluxcal.service.wiring.cli import main as cli_main
from fluxcal.service.wiring.commands.client import dashboard_endpoints
from fluxcal.service.wiring.commands.watch import TerminalView

REPO = Path(__file__).resolve().parents[2]


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


S1 = np.array([1000.5, -2000.0, 3000.0])
S2 = S1 + [1.0, 2.0, 3.0]
TENSOR = np.arange(9.0).reshape(3, 3) / 4.0
STATE = {"usable": True, "cal_id": 2, "method": "rls", "frozen": False, "samples_seen": 4000,
         "gate": {"usable": True, "coverage": 0.83, "condition": 12.0, "rms_nT": [0.7, 0.8], "reasons": []}}


def corrected_block(i: int, n: int = 10) -> CorrectedBlock:
    c = np.empty((n, 2, 3))
    c[:, 0], c[:, 1] = S1, S2
    return CorrectedBlock(t_s=(i * n + np.arange(n)) / 200.0, seq=i * n + np.arange(n, dtype=np.int64),
                          corrected_nT=c, diff_nT=c[:, 1:] - c[:, :1], tensor_nT_m=np.tile(TENSOR, (n, 1, 1)),
                          center_nT=c.mean(axis=1), cal_id=2)


class Publisher:
    """A service stand-in: publishes 20 Hz blocks of known vectors and serves state between blocks."""

    def __init__(self, unit: str = "u1", silent: bool = False, ep: str | None = None) -> None:
        self.ep = ep or f"tcp/127.0.0.1:{free_port()}"
        self.bus = ServiceBus(ZenohConfig(listen=[self.ep]), unit, state_fn=lambda: STATE, probe_names=["s1", "s2"])
        self.silent = silent
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self.run, daemon=True)
        self.thread.start()

    def run(self) -> None:
        i = 0
        while not self.stop.wait(0.05):
            self.bus.pending_commands()
            if self.silent:
                continue
            cb = corrected_block(i)
            self.bus.publish_raw(SampleBlock(t_s=cb.t_s, seq=cb.seq, field_nT=cb.corrected_nT * 1.1,
                                             temp_C=np.zeros((10, 2)), flags=np.zeros(10, np.uint8)))
            self.bus.publish_corrected(cb)
            self.bus.publish_error({"s1.scalar": 0.71, "s2.scalar": 0.805})
            if i % 10 == 0:
                self.bus.publish_health({"frames_accepted": 10 * i, "crc_failures": 3, "seq_gaps": 0})
            i += 1

    def close(self) -> None:
        self.stop.set()
        self.thread.join(2.0)
        self.bus.close()


@pytest.fixture
def publisher():
    made: list[Publisher] = []

    def make(**kw) -> Publisher:
        p = Publisher(**kw)
        made.append(p)
        return p

    yield make
    for p in made:
        p.close()


def test_watch_prints_the_live_vectors_once_a_second_when_not_a_terminal(publisher, capsys):
    pub = publisher()
    t0 = time.monotonic()
    status = cli_main(["watch", "--connect", pub.ep, "--unit", "u1", "--seconds", "1.7"])
    elapsed = time.monotonic() - t0
    out = capsys.readouterr().out
    lines = out.strip().splitlines()
    assert status == 0 and 1.7 <= elapsed < 3.5
    assert len(lines) == 2                                    # one line per second, the first after 0.5 s
    last = lines[-1]
    b1, b2 = np.linalg.norm(S1), np.linalg.norm(S2)
    assert f"s1=[+1000.5, -2000.0, +3000.0] |B|={b1:.1f}" in last
    assert f"s2=[+1001.5, -1998.0, +3003.0] |B|={b2:.1f}" in last
    assert "s2-s1=[+1.0, +2.0, +3.0]" in last
    assert "G=[+0.00, +0.25, +0.50, +0.75, +1.00, +1.25, +1.50, +1.75, +2.00] nT/m" in last
    assert "cal=usable cov=0.83" in last
    assert "err s1.scalar=0.710 s2.scalar=0.805" in last
    assert re.search(r"frames_accepted=\d+ crc_failures=3", last) and "seq_gaps" not in last


def test_watch_json_prints_what_the_view_shows_as_data_once_a_second(publisher, capsys):
    """`watch --json`: JSON lines a program reads (trials asked for it: `command state --json` has no vectors)."""
    import json

    pub = publisher()
    status = cli_main(["watch", "--connect", pub.ep, "--unit", "u1", "--seconds", "1.7", "--json"])
    lines = capsys.readouterr().out.strip().splitlines()
    assert status == 0 and len(lines) == 2
    rec = json.loads(lines[-1])
    assert rec["unit"] == "u1" and rec["status"] is None and rec["messages"] > 0
    assert [p["name"] for p in rec["probes"]] == ["s1", "s2"]
    assert rec["probes"][0]["corrected_nT"] == S1.tolist()
    assert rec["probes"][1]["total_nT"] == pytest.approx(float(np.linalg.norm(S2)))
    assert rec["differences"] == {"s2-s1": [1.0, 2.0, 3.0]} and rec["tensor_nT_m"] == TENSOR.tolist()
    assert rec["calibration"]["usable"] is True and rec["calibration"]["coverage"] == 0.83
    assert rec["error_rms_nT"]["s1.scalar"] == pytest.approx(0.71) and rec["counters"]["crc_failures"] == 3


def test_watch_json_leaves_the_last_vectors_out_while_samples_do_not_arrive():
    from fluxcal.service.wiring.commands.watch import view_record

    now = [100.0]
    dash = TerminalView("u1", ["tcp/127.0.0.1:7447"], clock=lambda: now[0])
    dash.connected = True
    dash.update(Message("corrected", "fluxcal/u1/corrected", corrected_block(0)))
    assert view_record(dash)["status"] is None and "probes" in view_record(dash)
    now[0] += 10.0                                          # the stream stops
    dash.alive = False
    rec = view_record(dash)
    assert "no data from fluxcal/u1 for 10 s" in rec["status"] and "probes" not in rec


def test_watch_finds_the_only_running_unit_without_unit(publisher, capsys):
    pub = publisher(unit="auto7")
    assert cli_main(["watch", "--connect", pub.ep, "--seconds", "1.7"]) == 0
    assert "fluxcal/auto7 | cal=usable" in capsys.readouterr().out


def test_watch_says_clearly_when_nothing_arrives(publisher, capsys):
    pub = publisher(silent=True)
    status = cli_main(["watch", "--connect", pub.ep, "--unit", "u1", "--seconds", "1.2"])
    cap = capsys.readouterr()
    assert status == 1
    assert (f"no data from fluxcal/u1 yet — is `fluxcal run` running and listening on {pub.ep}?") in cap.out
    assert f"nothing received from fluxcal/u1 via {pub.ep} in 1.2 s" in cap.err


def test_watch_waits_for_a_service_that_is_not_there(capsys):
    ep = f"tcp/127.0.0.1:{free_port()}"
    assert cli_main(["watch", "--connect", ep, "--unit", "u1", "--seconds", "1.2"]) == 1
    assert f"cannot reach {ep} — is `fluxcal run` running and listening there?" in capsys.readouterr().out


@pytest.mark.slow
def test_watch_picks_up_a_service_started_after_it(capsys):
    ep = f"tcp/127.0.0.1:{free_port()}"
    started: list[Publisher] = []
    timer = threading.Timer(0.8, lambda: started.append(Publisher(ep=ep)))
    timer.start()
    try:
        status = cli_main(["watch", "--connect", ep, "--unit", "u1", "--seconds", "2.6"])
    finally:
        timer.join()
        for p in started:
            p.close()
    lines = capsys.readouterr().out.strip().splitlines()
    assert status == 0
    assert "cannot reach" in lines[0]
    assert "s1=[+1000.5, -2000.0, +3000.0]" in lines[-1]


@pytest.mark.parametrize("argv, message", [
    (["--connect", "127.0.0.1:7447"], "--connect: '127.0.0.1:7447' is not a Zenoh endpoint"),
    (["--seconds", "-1"], "--seconds: -1.0 is not allowed"),
    (["--unit", "a/b"], "unit name 'a/b' is not allowed"),
])
def test_watch_usage_errors_exit_2_with_a_message(argv, message, capsys):
    assert cli_main(["watch", *argv]) == 2
    assert message in capsys.readouterr().err


def test_watch_takes_endpoint_and_unit_from_the_service_config():
    import argparse

    from fluxcal.service.wiring.commands.client import resolve as _resolve

    args = argparse.Namespace(config=str(REPO / "configs" / "sim-gradiometer.toml"), connect=None, unit=None,
                              seconds=None)
    endpoints, unit, tls = _resolve(args)
    assert (endpoints, unit, tls.enabled) == (["tcp/127.0.0.1:7447"], "grad1", False)
    assert dashboard_endpoints(ZenohConfig(listen=["tcp/127.0.0.1:0"], connect=["tcp/10.1.1.1:7447"])) == \
        ["tcp/10.1.1.1:7447"]                                  # a random port is unknowable: use the router


def test_terminal_frame_redraws_in_place_with_every_panel():
    now = [100.0]
    dash = TerminalView("u1", ["tcp/127.0.0.1:7447"], clock=lambda: now[0])
    dash.connected = True
    cb = corrected_block(0)
    dash.update(Message("corrected", "fluxcal/u1/corrected", cb))
    dash.update(Message("diff", "fluxcal/u1/diff", Series(cb.t_s, cb.seq, cb.diff_nT, 2)))
    dash.update(Message("tensor", "fluxcal/u1/tensor", Series(cb.t_s, cb.seq, cb.tensor_nT_m, 2)))
    dash.update(Message("error", "fluxcal/u1/error", {"rms_nT": {"s1.scalar": 0.71}}))
    dash.update(Message("health", "fluxcal/u1/health", {"counters": {"frames_accepted": 10, "crc_failures": 2}}))
    dash.update(Message("calibration", "fluxcal/u1/calibration", {"kind": "calibration", "state": STATE}))
    frame = dash.render_tty()
    assert frame.startswith("\x1b[H") and frame.endswith("\x1b[J") and "\x1b[2J" not in frame
    text = re.sub(r"\x1b\[[0-9;?]*[A-Za-z]", "", frame)
    assert "calibration: USABLE  cal_id 2  method rls  coverage 0.83  condition 12  residual [0.70, 0.80] nT" in text
    assert re.search(r"s1\s+\+1000\.5\s+-2000\.0\s+\+3000\.0\s+3741\.8", text)
    assert re.search(r"s2-s1\s+\+1\.0\s+\+2\.0\s+\+3\.0\s+3\.74\s+nT", text)
    assert re.search(r"d/dz\s+\+1\.50\s+\+1\.75\s+\+2\.00", text)
    assert "error, rms nT: s1.scalar 0.710" in text and "crc_failures 2" in text
    assert "no data" not in text
    now[0] += 10.0                                          # the stream stops
    dash.alive = False
    assert "no data from fluxcal/u1 for 10 s — the service has stopped" in dash.render_tty()


def test_a_pulled_cable_is_said_while_the_service_still_speaks():
    """The unit's cable pulled for 72 s: watch went back every 5 s to the last field values as if they were live and
    never said more than "no data ... for 4 s", because the service's health and calibration messages, which go on,
    reset its clock. Silence is now timed from the samples, and the faults the service says are active are shown; the
    dashboard says the same sentence (commands.client.flow)."""
    from fluxcal.service.wiring.dashboard.view import UnitView

    now = [100.0]
    views = [TerminalView("u1", ["tcp/127.0.0.1:7447"], clock=lambda: now[0]), UnitView("u1", clock=lambda: now[0])]
    views[0].connected = True
    for v in views:
        v.update(Message("corrected", "fluxcal/u1/corrected", corrected_block(0)))
    assert views[0].waiting_message() is None and views[1].status()[0] == "live"
    silence = {"kind": "silence", "phase": "begin", "n": 7,
               "text": "silence: no data from the unit for 5.0 s (unit.silence_s = 5): is it powered, connected and "
                       "sending?"}
    for _ in range(72):                                 # a health message a second, no samples
        now[0] += 1.0
        health = {"counters": {"frames_accepted": 10}, "faults": {"active": ["silence"] if now[0] > 105 else [],
                                                                  "events": [silence] if now[0] > 105 else []}}
        for v in views:
            v.update(Message("health", "fluxcal/u1/health", health))
    said = views[0].waiting_message()
    assert said.startswith("no samples from fluxcal/u1 for 72 s: the service runs, its input is silent (silence: "
                           "no data from the unit for 5.0 s"), said
    assert said in views[0].line() and "s1=[" not in views[0].line()             # no stale vectors as if live
    assert views[1].status() == ("silent", said)
    # bytes arrive that decode into no frame (another probe count's): not "silent", which it said beside the fault
    undecoded = {"kind": "no_decode", "phase": "begin", "n": 20_000, "text": "bytes arrive but no frame decodes"}
    for v in views:
        v.update(Message("health", "fluxcal/u1/health", {"counters": {"frames_accepted": 10},
                                                          "faults": {"active": ["no_decode"], "events": [undecoded]}}))
    said = views[0].waiting_message()
    assert "the service runs, its input arrives but decodes into no frame of the unit's (bytes arrive" in said, said
    assert "silent" not in said
    views[0].alive = views[1].alive = False
    now[0] += 10.0
    assert "no data from fluxcal/u1 for 82 s — the service has stopped" in views[0].waiting_message()
    assert views[1].status()[0] == "stopped"


def test_not_usable_yet_shows_the_gate_reasons_and_the_raw_vectors():
    dash = TerminalView("u1", ["tcp/127.0.0.1:7447"])
    dash.connected = True
    raw = SampleBlock(t_s=np.zeros(1), seq=np.zeros(1, np.int64), field_nT=np.array([[[10.0, 20.0, 30.0]]]),
                      temp_C=np.zeros((1, 1)), flags=np.zeros(1, np.uint8))
    dash.update(Message("raw", "fluxcal/u1/raw", raw))
    dash.update_state({"usable": False, "cal_id": 0, "gate": {"coverage": 0.31, "reasons": ["s1: coverage 0.31 < 0.6"]}})
    text = "\n".join(dash.frame_lines())
    assert "calibration: not usable yet" in text and "gate: s1: coverage 0.31 < 0.6" in text
    assert re.search(r"s1\s+\+10\.0\s+\+20\.0\s+\+30\.0", text)
    assert "cal=not-usable cov=0.31 | raw s1=[+10.0, +20.0, +30.0]" in dash.line()
    dash.update_state({"stale": True, "state_age_s": 4.2})       # the service's thread is busy
    assert "(state 4 s old: the service is busy, e.g. reconnecting its input)" in "\n".join(dash.frame_lines())
    assert "cal=not-usable cov=0.31 state-age=4s |" in dash.line()
    dash.update_state({"stale": False, "state_age_s": 0.0})
    assert "state-age" not in dash.line() and "old:" not in "\n".join(dash.frame_lines())


@pytest.mark.slow
def test_watch_process_stops_cleanly_on_sigterm(publisher):
    pub = publisher()
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    proc = subprocess.Popen([sys.executable, "-m", "fluxcal.service.wiring.cli", "watch", "--connect", pub.ep, "--unit", "u1"],
                            cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    try:
        first = ""
        deadline = time.monotonic() + 15.0
        while "s1=[" not in first and time.monotonic() < deadline:
            first = proc.stdout.readline()
        assert "s1=[+1000.5, -2000.0, +3000.0]" in first
        t0 = time.monotonic()
        proc.send_signal(signal.SIGTERM)
        proc.wait(timeout=5.0)
        assert proc.returncode == 0 and time.monotonic() - t0 < 3.0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


def test_a_check_without_a_candidate_says_there_is_no_residual_yet():
    """After the service started from its saved calibration, the first check found the online estimate not yet
    determined and the view read "coverage - condition - residual [] nT": now it says what is there. The gate as
    `fluxcal run` gave it then (configs/sim-gradiometer.toml, a saved calibration, 2000 samples in)."""
    from fluxcal.service.wiring.commands.command import state_text

    reason = ("s1: the online estimate is not determined yet (2000 samples, condition 782); keep rotating about "
              "several axes")
    st = {"usable": True, "cal_id": 1, "method": "rls", "probe_names": ["s1", "s2"],
          "gate": {"usable": False, "reasons": [reason], "coverage": None, "condition": None, "rms_nT": []}}
    dash = TerminalView("u1", ["tcp/127.0.0.1:7447"])
    dash.connected = True
    dash.update_state(st)
    text = dash.calibration_summary()
    assert "[]" not in text and "coverage -" not in text and "condition -" not in text
    assert "no residual yet: the online estimate has no candidate since the start or the last reset" in text
    assert f"gate: {reason}" in text                  # why, though the saved calibration is in use
    dash.last_msg_t = dash.last_data_t = dash.clock()   # data flow: the one-line view shows the state
    assert dash.line().endswith("| cal=usable no-candidate-yet") and "cov=" not in dash.line()
    said = state_text({**st, "unit": "u1"})
    assert "no candidate to judge, so no residual yet" in said and "[]" not in said and "None" not in said
    # the next check judged a candidate: its figures are back
    dash.update_state({"gate": {"usable": True, "reasons": [], "coverage": 0.346, "condition": 89.4,
                                "rms_nT": [0.625, 0.790]}})
    text = dash.calibration_summary()
    assert "coverage 0.35  condition 89.4  residual [0.62, 0.79] nT" in text and "no residual yet" not in text
