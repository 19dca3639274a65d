"""State and recordings per unit and source kind, found relative to the configuration, and a calibration
learned on one unit or source never silently applied to another."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from fluxcal.service.io.calfile import load_calibration, save_calibration
from fluxcal.service.numerics.calib.model import ArrayCalibration, ProbeCalibration
from fluxcal.service.wiring.config import load_config
from fluxcal.service.wiring.startcal import initial_calibration, learned_on

ROOT = Path(__file__).resolve().parents[2]


def test_the_examples_keep_their_calibrations_apart_and_beside_the_repository():
    files = {}
    for name in ("sim-gradiometer", "serial-example", "can-example", "sim-cross"):
        cfg = load_config(ROOT / "configs" / f"{name}.toml")
        files[name] = Path(cfg.calibration.file)
        assert files[name].parent == ROOT / "state"                   # relative to configs/, not the cwd
        assert Path(cfg.mcap.dir) == ROOT / "recordings" / "live"
        assert f"{cfg.unit.name}-{learned_on(cfg)['source']}" in files[name].name
    assert len(set(files.values())) == len(files)


def test_relative_paths_follow_the_configuration_not_the_working_directory(tmp_path, monkeypatch):
    site = tmp_path / "site"
    site.mkdir()
    (site / "unit.toml").write_text('[unit]\nname = "north"\nn_probes = 2\n[source]\nkind = "sim"\n'
                                    '[mcap]\ndir = "rec"\n[calibration]\ninitial = "cal/start.json"\n')
    monkeypatch.chdir(tmp_path)
    cfg = load_config("site/unit.toml")
    assert Path(cfg.mcap.dir) == site / "rec" and Path(cfg.calibration.initial) == site / "cal" / "start.json"
    # no file named: one per unit and source kind, beside the configuration
    assert Path(cfg.calibration.file) == site / "state" / "north-sim-cal.json"


def _cal(tmp_path, origin) -> Path:
    cal = ArrayCalibration("rls", None, [ProbeCalibration("s1", np.zeros(3), np.eye(3))],
                           diagnostics={"learned_on": origin})
    path = tmp_path / "state" / "cal.json"
    path.parent.mkdir(exist_ok=True)
    save_calibration(cal, path)
    return path


def test_a_calibration_learned_on_the_simulator_is_not_applied_to_hardware(tmp_path):
    (tmp_path / "serial.toml").write_text('[unit]\nname = "grad1"\nn_probes = 1\n[source]\nkind = "serial"\n'
                                          'port = "/dev/null"\nn_probes = 1\nrate_hz = 200.0\n[calibration]\n'
                                          'file = "state/cal.json"\n')
    cfg = load_config(tmp_path / "serial.toml")
    path = _cal(tmp_path, {"unit": "grad1", "source": "sim"})
    said: list[str] = []
    assert initial_calibration(cfg, said.append) is None
    assert "learned on unit grad1 from a sim source" in said[0] and "calibration.initial" in said[0]
    # the user says so by naming it: then it is used, and what it was learned on is said
    cfg.calibration.initial = str(path)
    said.clear()
    assert initial_calibration(cfg, said.append) is not None
    assert "learned on unit grad1, source sim" in said[0]
    # learned here: reloaded
    _cal(tmp_path, {"unit": "grad1", "source": "serial"})
    cfg.calibration.initial = None
    said.clear()
    assert initial_calibration(cfg, said.append) is not None and "reloaded" in said[0]
    assert load_calibration(path).diagnostics["learned_on"] == {"unit": "grad1", "source": "serial"}


def test_a_missing_initial_calibration_or_serial_port_names_its_key(tmp_path, capsys):
    """A config that names a calibration file or a port that is not there: the key, then the reason (exit 2 for
    the file, 1 for the port: hardware), and no 'learning online' line before the error."""
    from fluxcal.service.wiring.cli import main

    base = ('[unit]\nname = "grad1"\nn_probes = 1\n[source]\nkind = "serial"\nport = "{port}"\nn_probes = 1\n'
            'rate_hz = 200.0\n[calibration]\nfile = "state/cal.json"\n{initial}'
            '[zenoh]\nlisten = ["tcp/127.0.0.1:{zport}"]\n'
            '[mcap]\nenabled = false\n')
    cfg = tmp_path / "a.toml"
    import socket

    with socket.socket() as sk:
        sk.bind(("127.0.0.1", 0))
        zport = sk.getsockname()[1]
    cfg.write_text(base.format(port="/dev/ttyNOPE0", initial='initial = "state/nope.json"\n', zport=zport))
    assert main(["run", "--config", str(cfg)], install_signals=False) == 2
    err = capsys.readouterr().err
    assert f"fluxcal run: calibration.initial: {tmp_path / 'state' / 'nope.json'}: calibration file not found" in err
    cfg.write_text(base.format(port="/dev/ttyNOPE0", initial="", zport=zport))
    import signal

    handlers = [signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)]
    assert main(["run", "--config", str(cfg)], install_signals=False) == 1
    # the daemon's stop handlers are the process's own again: a caller in the same process keeps its Ctrl-C (a test
    # after this one, interrupted by a real SIGINT, ran on to exit 0)
    assert [signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)] == handlers
    err = capsys.readouterr().err
    assert "fluxcal run: source.port: serial port /dev/ttyNOPE0: cannot open" in err and "learning online" not in err


def test_an_applied_calibration_is_persisted_and_reloaded_held(tmp_path):
    """`apply` persists the calibration (it was kept only in memory) marked applied; a restart reloads it held,
    as it was (build_pipeline, which replay shares); `reset` persists it no longer held."""
    from fluxcal.service.wiring.daemon import Daemon, build_pipeline
    from fluxcal.service.wiring.sinks import Sinks

    (tmp_path / "sim.toml").write_text('[unit]\nname = "grad1"\nn_probes = 1\n[source]\nkind = "sim"\n'
                                       '[sim]\nrate_hz = 100.0\n[[sim.probes]]\nname = "s1"\n'
                                       '[calibration]\nfile = "state/cal.json"\n')
    cfg = load_config(tmp_path / "sim.toml")
    daemon = Daemon(cfg, say=lambda m: None)
    pipeline = build_pipeline(cfg, None)
    lab = ArrayCalibration("ellipsoid", None, [ProbeCalibration("s1", np.array([5.0, 0, 0]), np.eye(3))])
    bus = Sinks([], print)                                          # no output: persisting is the daemon's
    ev = pipeline.command("apply", lab, seq=0, t_s=0.0)
    daemon._on_event(ev, pipeline, bus)
    saved = load_calibration(tmp_path / "state" / "cal.json")
    assert saved.diagnostics["applied"] is True and saved.probes[0].offset_nT[0] == 5.0
    said: list[str] = []
    again = build_pipeline(cfg, initial_calibration(cfg, said.append))
    assert again.held and again.state()["held"] and "held until `reset`" in said[0]
    other = tmp_path / "state" / "other.json"                       # calibration.initial wins: said
    save_calibration(ArrayCalibration("ellipsoid", None, [ProbeCalibration("s1", np.zeros(3), np.eye(3))]), other)
    cfg.calibration.initial = str(other)
    said.clear()
    assert not build_pipeline(cfg, initial_calibration(cfg, said.append)).held
    assert any("applied by command and persisted" in m and "is not used" in m for m in said), said
    cfg.calibration.initial = None
    daemon._on_event(again.command("reset", None, seq=0, t_s=0.0), again, bus)
    assert load_calibration(tmp_path / "state" / "cal.json").diagnostics["applied"] is False
    assert not build_pipeline(cfg, initial_calibration(cfg, said.append)).held
