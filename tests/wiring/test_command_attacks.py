"""An operator's one message must never read a file on the service's host, hang it, stop it, or put an
absurd calibration (or another unit's) in use: the red team's cases over Zenoh with the documented TLS
and access-control setup (docs/security.md), against the real service on a simulated unit, and a fuzz
of the command handler.

Before: `apply /etc/shadow` sent the first 60 characters of the file's first line back to the operator
(and the refusals told which files exist), a FIFO's path hung the service's only thread, /dev/zero was
read until MemoryError, 200 kB of nested arrays stopped `fluxcal run` with a RecursionError, and a matrix
of 1e-9 times the identity, a mirror, offsets of 1e300, booleans as offsets, another unit's probe names
or two probes' entries swapped were applied, held and persisted.
"""

from __future__ import annotations

import copy
import json
import os
import threading
import time
from contextlib import ExitStack
from pathlib import Path

import numpy as np
import pytest
from certs import Authority
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from test_recording import service_config
from test_zenoh_security import free_port

from fluxcal.drivers.errors import DataError
from fluxcal.service.io.bus import BusClient, ZenohConfig, ZenohTlsConfig
from fluxcal.service.io.calfile import calibration_to_dict, load_calibration
from fluxcal.service.numerics.calib.model import ArrayCalibration, ProbeCalibration
from fluxcal.service.wiring.config import load_config
from fluxcal.service.wiring.daemon import Daemon, build_pipeline
from fluxcal.service.wiring.startcal import calibration_from_payload

#: what this file tests besides what it imports (tests/index.py: every module findable from its test)
COVERS = ("fluxcal.service.numerics.calib.plausible", "fluxcal.drivers.text")

NAMES = ["s1", "s2"]


def good_calibration(names=NAMES, scale: float = 1.0) -> dict:
    probes = [ProbeCalibration(n, np.array([100.0 * (k + 1), -50.0, 20.0]), np.eye(3) * scale, np.full(3, 1.0),
                               np.full((3, 3), 1e-4)) for k, n in enumerate(names)]
    return calibration_to_dict(ArrayCalibration(method="ellipsoid", align="rotation", probes=probes,
                                                total_nT=52500.0))


def _set(d: dict, path: tuple, value) -> dict:
    d = copy.deepcopy(d)
    node = d
    for key in path[:-1]:
        node = node[key]
    node[path[-1]] = value
    return d


#: the red team's absurd calibrations, and the check each must be refused by (as the refusal names it)
ABSURD = {
    "matrix 1e-9 x identity": (_set(good_calibration(), ("probes", 0, "matrix"), (np.eye(3) * 1e-9).tolist()),
                               "scale"),
    "matrix 1e200 x identity": (_set(good_calibration(), ("probes", 1, "matrix"), (np.eye(3) * 1e200).tolist()),
                                "scale"),
    "condition 1e11": (_set(good_calibration(), ("probes", 0, "matrix"), np.diag([1.0, 1.0, 1e-11]).tolist()),
                       "condition"),
    "a mirror (det -1)": (_set(good_calibration(), ("probes", 0, "matrix"), np.diag([1.0, 1.0, -1.0]).tolist()),
                          "mirror"),
    "offsets of 1e300": (_set(good_calibration(), ("probes", 1, "offset_nT"), [1e300, 0.0, 0.0]), "offset"),
    "booleans as offsets": (_set(good_calibration(), ("probes", 0, "offset_nT"), [True, False, True]),
                            "expected numbers"),
    "strings as offsets": (_set(good_calibration(), ("probes", 0, "offset_nT"), ["1", "2", "3"]),
                           "expected numbers"),
    "a total field of 1e-300": (_set(good_calibration(), ("total_nT",), 1e-300), "total field"),
    "probe names not the unit's": (good_calibration(["a", "b"]), "probe names"),
    "a third probe": (good_calibration(["s1", "s2", "s3"]), "probe names"),
    "the two probes' entries swapped": (_set(good_calibration(), ("probes",), good_calibration()["probes"][::-1]),
                                        "probe names"),
    "fitted with effects": (_set(_set(good_calibration(), ("effects",), ["temperature"]), ("effect_params",),
                                 {"temperature": {"s1.x nT/degC": {"value": 2.0, "se": 0.1, "unit": "nT/degC"}}}),
                            "effects"),
}


@pytest.fixture
def cfg(tmp_path):
    return load_config(service_config(tmp_path, run_s=5))


@pytest.mark.parametrize("case", list(ABSURD))
def test_every_absurd_calibration_is_refused_naming_its_check(cfg, case):
    d, check = ABSURD[case]
    with pytest.raises(DataError) as e:
        calibration_from_payload(json.dumps(d), cfg)
    msg = str(e.value)
    assert check in msg and len(msg) < 500, msg
    if check not in ("expected numbers",):
        assert f"fails the {check} check" in msg


def test_a_good_calibration_passes_and_order_matters_not_position(cfg):
    cal = calibration_from_payload(json.dumps(good_calibration()), cfg)
    assert [p.name for p in cal.probes] == NAMES
    # a real board's fit (offset 6x the field, scale errors of 50 %) is not absurd
    d = _set(good_calibration(), ("probes", 0, "offset_nT"), [222952.0, 48610.0, -35030.0])
    d = _set(d, ("probes", 0, "matrix"), np.diag([1.50, 0.99, 0.67]).tolist())
    calibration_from_payload(json.dumps(d), cfg)


def test_paths_and_special_files_are_refused_without_touching_the_filesystem(cfg, tmp_path, monkeypatch):
    fifo = tmp_path / "fifo"
    os.mkfifo(fifo)
    opened: list = []
    real_open = os.open

    def spy(path, *a, **k):                   # every file opened while the payload is taken
        opened.append(path)
        return real_open(path, *a, **k)

    monkeypatch.setattr(os, "open", spy)
    import builtins
    real_builtin_open = builtins.open
    monkeypatch.setattr(builtins, "open", lambda p, *a, **k: (opened.append(p), real_builtin_open(p, *a, **k))[1])
    answers = set()
    for payload in ("/etc/passwd", "/etc/shadow", str(fifo), "/dev/zero", "/proc/self/environ", str(tmp_path),
                    "/nonexistent/x.json", "file:///etc/passwd"):
        t0 = time.monotonic()
        with pytest.raises(DataError) as e:
            calibration_from_payload(payload, cfg)
        assert time.monotonic() - t0 < 1.0
        answers.add(str(e.value).split(" characters)")[1].split(" it begins ")[0])
        assert "root:" not in str(e.value)
    assert opened == [] and len(answers) == 1


def test_nested_json_is_refused_not_a_recursion_error(cfg):
    for text in ('{"a":' * 50_000 + "1" + "}" * 50_000, '{"a": ' + "[" * 100_000 + "]" * 100_000 + "}",
                 '{"format": "fluxcal.calibration", "x": ' + "[" * 30 + "]" * 30 + "}"):
        with pytest.raises(DataError, match="nested"):
            calibration_from_payload(text, cfg)
    with pytest.raises(DataError, match="not a calibration's JSON content"):
        calibration_from_payload("[" * 100_000 + "]" * 100_000, cfg)


# --- the real service, over Zenoh with mutual TLS and access control ------------------------------

class SecuredService:
    """`fluxcal run` on the simulated unit (pty), listening on tls/localhost with the site's certificates;
    the operator `ops` may command, `dashboard` may only read."""

    def __init__(self, tmp: Path, stack: ExitStack) -> None:
        ca = Authority(tmp, "site-ca")
        certs = {cn: ca.issue(cn) for cn in ("grad1-service", "ops", "dashboard")}
        self.endpoint = f"tls/localhost:{free_port()}"
        cert, key = certs["grad1-service"]
        text = Path(service_config(tmp, run_s=0)).read_text().replace(
            'listen = ["tcp/127.0.0.1:0"]', f'listen = ["{self.endpoint}"]')
        text += (f'\n[zenoh.tls]\nroot_ca = "{ca.pem}"\ncert = "{cert}"\nkey = "{key}"\n'
                 f'\n[zenoh.access]\nreaders = ["dashboard"]\ncommanders = ["ops"]\n')
        (tmp / "secure.toml").write_text(text)
        self.cfg = load_config(tmp / "secure.toml")
        self.said: list[str] = []
        self.stop = threading.Event()
        self.daemon = Daemon(self.cfg, stop=self.stop, say=self.said.append)
        self.result: list = []
        self.thread = threading.Thread(target=lambda: self.result.append(self._run()), daemon=True)
        self.thread.start()
        stack.callback(self.close)
        deadline = time.monotonic() + 20
        while not any(m.startswith("publishing on zenoh") for m in self.said):
            assert time.monotonic() < deadline and self.thread.is_alive(), self.said
            time.sleep(0.05)
        o_cert, o_key = certs["ops"]
        self.ops = stack.enter_context(BusClient(ZenohConfig.client(
            self.endpoint, tls=ZenohTlsConfig(root_ca=ca.pem, cert=o_cert, key=o_key)), "grad1", streams=["raw"]))

    def _run(self):
        try:
            return self.daemon.run()
        except BaseException as e:  # noqa: BLE001 - the test asserts there was none
            return e

    def close(self) -> None:
        self.stop.set()
        self.thread.join(20)

    def samples_seen(self) -> int:
        return int(self.ops.query_state(timeout=5.0).get("samples_seen", 0))


def test_over_tls_no_payload_reads_a_file_hangs_or_stops_the_service(tmp_path):
    fifo = tmp_path / "fifo"
    os.mkfifo(fifo)
    secret = tmp_path / "secret.key"
    secret.write_text("-----BEGIN PRIVATE KEY----- the first line of a key\n")
    with ExitStack() as stack:
        svc = SecuredService(tmp_path, stack)
        before = svc.samples_seen()
        refusals = {}
        for payload in (str(secret), "/etc/passwd", str(fifo), "/dev/zero", str(tmp_path), "/no/such/file",
                        '{"a": ' + "[" * 100_000 + "]" * 100_000 + "}"):
            t0 = time.monotonic()
            answer = svc.ops.command("apply", payload, timeout=5.0)
            assert time.monotonic() - t0 < 3.0, payload[:40]
            assert answer["ok"] is False and "BEGIN PRIVATE KEY" not in answer["error"]
            assert "root:" not in answer["error"]
            refusals[payload[:40]] = answer["error"]
        # the same answer for a file that exists, one that does not, a FIFO and a directory: no oracle
        same = {r.split(" characters)")[1].split(" it begins ")[0] for k, r in refusals.items() if k[0] == "/"}
        assert len(same) == 1 and "never a path" in same.pop()
        assert "nested 100001 deep" in refusals['{"a": ' + "[" * 34]
        for case, (d, check) in ABSURD.items():
            answer = svc.ops.command("apply", json.dumps(d), timeout=5.0)
            assert answer["ok"] is False and check in answer["error"], (case, answer)
        state = svc.ops.query_state(timeout=5.0)
        assert state["cal_id"] == 0 and not state.get("held")           # nothing was put in use
        assert not Path(svc.cfg.calibration.file).exists()              # nor persisted
        answer = svc.ops.command("apply", json.dumps(good_calibration()), timeout=5.0)
        assert answer["ok"] is True and answer["cal_id"] == 1
        assert load_calibration(svc.cfg.calibration.file).probes[0].offset_nT.tolist() == [100.0, -50.0, 20.0]
        deadline = time.monotonic() + 10
        while svc.samples_seen() <= before + 200:                       # still reading and processing
            assert time.monotonic() < deadline
            time.sleep(0.2)
        assert svc.thread.is_alive()
        refused = [m for m in svc.said if "command apply: refused" in m]
        from fluxcal.service.wiring.status import StatusLog

        # said one by one up to ten between two status lines (the rest with the next one), every one counted
        assert len(refused) == min(7 + len(ABSURD), StatusLog.COMMAND_LINES) and max(len(m) for m in refused) < 700
        assert svc.daemon._status.refused == 7 + len(ABSURD)
    assert svc.result == [0], (svc.result, svc.said[-5:])


# --- a fuzz of the handler: 10,000 payloads, the service's calibration unchanged after each refusal -----

class _Cmd:
    def __init__(self, name: str, payload) -> None:
        self.name, self.payload, self.answer = name, payload, None

    def reply(self, answer) -> None:
        self.answer = answer


json_values = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats() | st.text(max_size=20),
    lambda inner: st.lists(inner, max_size=5) | st.dictionaries(st.text(max_size=10), inner, max_size=5),
    max_leaves=30)
GOOD = good_calibration()
_PATHS = [("probes",), ("probes", 0), ("probes", 1), ("probes", 0, "offset_nT"), ("probes", 0, "matrix"),
          ("probes", 1, "matrix"), ("probes", 0, "name"), ("total_nT",), ("effects",), ("format",), ("version",),
          ("align",), ("span",), ("probes", 0, "offset_nT", 1), ("probes", 1, "matrix", 2), ("effect_params",)]
mutated = st.builds(lambda path, v: json.dumps(_set(GOOD, path, v), allow_nan=True),
                    st.sampled_from(_PATHS), json_values)
payloads = st.one_of(
    mutated,
    json_values.map(lambda v: json.dumps(v, allow_nan=True)),
    st.text(max_size=200),
    st.binary(max_size=200),
    st.integers(1, 5000).map(lambda n: "[" * n + "]" * n),
    st.sampled_from(["/etc/passwd", "/dev/zero", "~/.ssh/id_rsa", "../../etc/shadow", "\0", "{", "{}" * 1000]),
)


def test_fuzzing_the_handler_leaves_the_service_running_and_its_calibration_unchanged(cfg):
    daemon = Daemon(cfg, say=lambda m: None)
    start = calibration_from_payload(json.dumps(good_calibration()), cfg)
    pipeline = build_pipeline(cfg, start)
    from fluxcal.service.wiring.sinks import Sinks

    sinks = Sinks([], print)
    seen = {"n": 0, "ok": 0}

    @settings(max_examples=10_000, deadline=None, database=None, derandomize=True,
              suppress_health_check=list(HealthCheck))
    @given(name=st.sampled_from(["apply", "apply", "apply", "add-effect"]), payload=payloads)
    def fuzz(name, payload):
        before = (pipeline.cal_id, pipeline.held, pipeline.calibration)
        cmd = _Cmd(name, payload)
        daemon._apply_command(cmd, pipeline, sinks)            # must not raise, whatever the payload
        seen["n"] += 1
        assert isinstance(cmd.answer, dict) and isinstance(cmd.answer.get("ok"), bool)
        if cmd.answer["ok"]:                                    # a payload that is a good calibration: put back
            seen["ok"] += 1
            pipeline.set_calibration(start)
            pipeline.held = before[1]
            pipeline.cal_id = before[0]
        else:
            assert isinstance(cmd.answer["error"], str) and len(cmd.answer["error"]) < 2000
            assert (pipeline.cal_id, pipeline.held, pipeline.calibration) == before

    fuzz()
    assert seen["n"] == 10_000
    assert pipeline.calibration is start


def test_the_same_check_guards_the_reload_and_calibration_initial(tmp_path):
    from fluxcal.drivers.errors import ConfigError
    from fluxcal.service.wiring.startcal import initial_calibration

    cfg = load_config(service_config(tmp_path, run_s=5))
    for case in ("a mirror (det -1)", "the two probes' entries swapped", "fitted with effects"):
        d, check = ABSURD[case]
        Path(cfg.calibration.file).write_text(json.dumps(d))               # persisted by an older fluxcal
        said: list[str] = []
        assert initial_calibration(cfg, said.append) is None
        assert any(f"ignoring the persisted calibration: fails the {check} check" in m for m in said), said
        cfg.calibration.initial = str(tmp_path / "initial.json")
        Path(cfg.calibration.initial).write_text(json.dumps(d))
        with pytest.raises(ConfigError, match=f"calibration.initial: fails the {check} check"):
            initial_calibration(cfg, said.append)
        cfg.calibration.initial = None
    Path(cfg.calibration.file).write_text(json.dumps(good_calibration()))
    assert initial_calibration(cfg, lambda m: None).probe_names == NAMES


# --- text from the network printed escaped (issue 38, build 4) -------------------------------------------------

EVIL = "s1\ncommand apply: applied (calibration 99)\x1b[2J\x1b[31m\u202e"


def test_a_refused_payloads_words_never_make_a_line_of_their_own_nor_act_on_the_console(cfg, capfd):
    """The service's own console (its default `say`): a probe name holding a line break and a line shaped like the
    service's own, and ESC sequences, is one line with the control characters shown."""
    daemon = Daemon(cfg)                                  # says on stderr, as `fluxcal run` does
    from fluxcal.service.wiring.sinks import Sinks

    pipeline = build_pipeline(cfg, None)
    capfd.readouterr()
    for name, payload in (("apply", json.dumps(good_calibration([EVIL, "s2"]))), ("add-effect", EVIL)):
        cmd = _Cmd(name, payload)
        daemon._apply_command(cmd, pipeline, Sinks([], daemon.say))
        assert cmd.answer["ok"] is False
    err = capfd.readouterr().err
    lines = err.splitlines()
    assert len(lines) == 2 and all(line.startswith("fluxcal ") for line in lines), lines
    assert "\x1b" not in err and "\u202e" not in err and "\\x1b[2J" in err and "\\u202e" in err
    assert not any(line.split(": ", 1)[1].startswith("command apply: applied") for line in lines)
    assert "s1\\ncommand apply: applied (calibration 99)" in lines[0]


def test_the_clients_and_the_batch_commands_print_what_they_receive_escaped(capsys, tmp_path):
    """`fluxcal command` prints the service's refusal, the batch commands a file's words, `watch` what the bus
    carries: each escaped."""
    from test_cli_command import FakeDaemon, free_port

    from fluxcal.service.io.bus import ServiceBus, ZenohConfig
    from fluxcal.service.wiring.cli import main
    from fluxcal.service.wiring.commands.watch import TerminalView
    from fluxcal.service.wiring.result import Note, stderr_say

    ep = f"tcp/127.0.0.1:{free_port()}"
    bus = ServiceBus(ZenohConfig(listen=[ep]), "grad9", state_fn=lambda: {"usable": False, "unit": EVIL})
    svc = FakeDaemon(bus, decide=lambda cmd: {"ok": False, "error": f"refused: {EVIL}"})
    try:
        assert main(["command", "freeze", "--connect", ep, "--unit", "grad9"]) == 1
        err = capsys.readouterr().err
        assert "\x1b" not in err and err.count("\n") == 1 and "refused: s1\\ncommand apply" in err
    finally:
        svc.close()
        bus.close()
    stderr_say("fit")(Note("read", f"{tmp_path}/x.csv: line 3, column {EVIL!s}", "say"))
    err = capsys.readouterr().err
    assert "\x1b" not in err and err.count("\n") == 1
    from fluxcal.service.io.bus import Message

    view = TerminalView("grad9", [ep])
    view.connected = True
    view.update(Message("health", "fluxcal/grad9/health", {"counters": {EVIL: 3, "frames_accepted": 1}}))
    line = view.line()
    assert "s1\\ncommand apply" in line and "\x1b" not in line and "\n" not in line
    frame = view.render_tty()
    assert "s1\\ncommand apply" in frame and "\x1b[2J" not in frame and "\u202e" not in frame
