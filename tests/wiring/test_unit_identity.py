"""A unit knows who it is (issue 38, builds 2 and 10): a calibration carries the unit's name and its probes' serial
numbers; `apply`, the reload and calibration.initial refuse one made for another unit and say which; a calibration
that the service's own data say is not this unit's (the gate's residual) is refused before it is held, and without
data yet one far from the unit's calibration history; the summary at stop counts what was refused or not saved.

Before (the red team's trial): another unit's calibration (the same probe names, offsets 5,000 nT away, "unit":
"grad2") was applied, held, persisted and reloaded; the error went from 0.75 to ~8,000 nT, seen only as a figure in
the status line, and the summary at stop said "no loss and no fault seen". A calibration.file naming a folder said
"could not persist" every 5 s, and the summary said no fault.
"""

from __future__ import annotations

import json
import threading
import time
from contextlib import ExitStack
from pathlib import Path

import pytest
from test_command_attacks import _Cmd, _set, good_calibration
from test_recording import service_config
from test_zenoh_security import free_port

from fluxcal.drivers.errors import ConfigError, DataError
from fluxcal.service.io.bus import BusClient, ZenohConfig
from fluxcal.service.io.calfile import calibration_from_dict, load_calibration
from fluxcal.service.wiring.config import load_config
from fluxcal.service.wiring.daemon import Daemon, build_pipeline
from fluxcal.service.wiring.identity import judge_on_data, recording_identity
from fluxcal.service.wiring.sinks import Sinks
from fluxcal.service.wiring.startcal import calibration_from_payload, initial_calibration

SERIALS = '\n[[probes]]\nname = "s1"\nposition_m = [-0.25, 0.0, 0.0]\nserial = "FG-1001"\n' \
          '\n[[probes]]\nname = "s2"\nposition_m = [0.25, 0.0, 0.0]\nserial = "FG-1002"\n'


def config(tmp_path: Path, serials: bool = False, **kw):
    path = Path(service_config(tmp_path, run_s=kw.pop("run_s", 5), **kw))
    text = path.read_text()
    if serials:                            # the probes' serial numbers instead of the example's [[probes]]
        head, _, rest = text.partition("[[probes]]")
        rest = rest.split("[source]", 1)[1]
        text = head + SERIALS + "\n[source]" + rest
    path.write_text(text)
    return load_config(path)


def test_a_calibration_made_for_another_unit_or_probe_is_refused_naming_it(tmp_path):
    cfg = config(tmp_path, serials=True)
    theirs = _set(good_calibration(), ("unit",), "grad2")                     # the red team's form: a bare name
    with pytest.raises(DataError, match="fails the unit check: it was made for unit 'grad2', this is unit 'grad1'"):
        calibration_from_payload(json.dumps(theirs), cfg)
    other_probe = _set(good_calibration(), ("unit",), {"name": "grad1", "probes": {"s2": "FG-7777"}})
    with pytest.raises(DataError, match="fails the probe serial check: s2: it was made for the probe with serial "
                                        "'FG-7777', this unit's s2 is 'FG-1002'"):
        calibration_from_payload(json.dumps(other_probe), cfg)
    mine = _set(good_calibration(), ("unit",), {"name": "grad1", "probes": {"s1": "FG-1001"}})
    assert calibration_from_payload(json.dumps(mine), cfg).unit == {"name": "grad1", "probes": {"s1": "FG-1001"}}
    # the reload and calibration.initial: the same check, said and counted
    Path(cfg.calibration.file).write_text(json.dumps(theirs))
    said, refused = [], []
    assert initial_calibration(cfg, said.append, refused=lambda: refused.append(1)) is None
    assert refused == [1] and "ignoring the persisted calibration: fails the unit check" in said[0]
    cfg.calibration.initial = cfg.calibration.file
    with pytest.raises(ConfigError, match="calibration.initial: fails the unit check: it was made for unit 'grad2'"):
        initial_calibration(cfg, said.append)


def test_a_recordings_calibration_carries_the_unit_that_made_it(tmp_path):
    stored = {"unit": "grad1", "config": json.dumps({"probes": [{"name": "s1", "serial": "FG-1001"}, {"name": "s2"}]})}
    assert recording_identity(stored) == {"name": "grad1", "probes": {"s1": "FG-1001"}}
    assert recording_identity({}) == {}
    from fluxcal.service.wiring.cli import main

    rec = Path(__file__).resolve().parents[2] / "recordings" / "grad1-sim-30s.mcap"
    assert main(["fit", str(rec), "--out", str(tmp_path / "cal.json")]) == 0
    assert load_calibration(tmp_path / "cal.json").unit["name"] == "grad1"


def sim_blocks(cfg, seconds: float):
    """The configured simulated unit's samples, in blocks of 0.5 s."""
    from fluxcal.drivers.sim import Unit

    u = Unit(cfg.sim)
    step = int(0.5 * cfg.sim.rate_hz)
    return [u.digitise(a, a + step).to_block() for a in range(0, int(seconds * cfg.sim.rate_hz), step)]


@pytest.fixture(scope="module")
def learned(tmp_path_factory):
    """A pipeline that has learned the simulated unit's calibration on 40 s of its data, and the calibration."""
    tmp = tmp_path_factory.mktemp("learned")
    cfg = config(tmp)
    pipeline = build_pipeline(cfg, None)
    for b in sim_blocks(cfg, 40.0):
        pipeline.process(b)
    assert pipeline.calibration is not None
    return cfg, pipeline


def shifted(cal, offset_nT: float):
    from fluxcal.service.io.calfile import calibration_to_dict

    d = calibration_to_dict(cal)
    for p in d["probes"]:
        p["offset_nT"] = [v + offset_nT for v in p["offset_nT"]]
    d.pop("unit", None)
    d["diagnostics"] = {}
    return calibration_from_dict(d)


def test_the_data_refuse_another_units_calibration_by_the_gates_figures(learned):
    cfg, pipeline = learned
    own = pipeline.calibration
    assert judge_on_data(shifted(own, 3.0), pipeline, cfg).startswith("judged on the last")   # a close one passes
    with pytest.raises(DataError) as e:
        judge_on_data(shifted(own, 5000.0), pipeline, cfg)
    msg = str(e.value)
    assert msg.startswith("fails the data check: s1: on this unit's last ") and "estimator.gate_rms_nT" in msg
    figures = [float(x.replace(",", "")) for x in __import__("re").findall(r"([\d,.]+) nT", msg)[:2]]
    assert figures[0] > 1000 and figures[1] < 5          # the candidate's residual, the one in use's


def test_without_data_yet_a_calibration_far_from_the_units_history_is_refused(tmp_path, learned):
    cfg, trained = learned
    pipeline = build_pipeline(cfg, trained.calibration)                      # just started: no data yet
    with pytest.raises(DataError, match=r"fails the history check: s1: its offsets differ from the calibration in "
                                        r"use by 5000 nT \(at most 2000 nT without data"):
        judge_on_data(shifted(trained.calibration, 5000.0), pipeline, cfg)
    assert judge_on_data(shifted(trained.calibration, 100.0), pipeline, cfg).startswith("not judged on data yet")


def test_a_calibration_started_from_or_applied_before_any_data_is_judged_on_them_once_there_are(learned):
    """Another unit's calibration (offsets 5,000 nT away, no unit said) reloaded at start was used, said usable, with
    errors of 5,000 nT, for a whole run on a static platform, and the summary said no fault (field trial): nothing had
    judged it on the unit's data. It is judged once the service has estimator.min_samples, and where it fails the data
    check that is said, with the two things its figures cannot tell apart (a residual against the total field grows
    where that field is off too, and a static platform learns nothing to replace it, so it stays in use); the unit's
    own passes; one applied before there were data is judged alike."""
    cfg, trained = learned
    blocks = sim_blocks(cfg, 12.0)

    def run(pipeline):
        return [e for b in blocks for e in pipeline.process(b).events if e.kind == "data check"]

    foreign = build_pipeline(cfg, shifted(trained.calibration, 5000.0))
    doubted = run(foreign)
    assert len(doubted) == 1 and foreign.calibration is not None and not foreign.on_trial
    why = doubted[0].detail["reasons"][0]
    assert why.startswith("the calibration in use, not judged on this unit's data until now, fails the data check: "
                          "s1: on this unit's last ") and "estimator.gate_rms_nT" in why, why
    assert why.endswith("it is another unit's or far off, or the total field it is judged against is; it stays in use "
                        "(`fluxcal command reset` learns anew, `apply` gives another)"), why
    own = build_pipeline(cfg, shifted(trained.calibration, 2.0))
    assert run(own) == [] and own.calibration is not None and not own.on_trial
    bare = build_pipeline(cfg, None)
    bare.command("apply", shifted(trained.calibration, 5000.0), seq=0, t_s=0.0)
    assert bare.held and bare.on_trial
    assert len(run(bare)) == 1 and bare.held and not bare.on_trial


def test_two_services_given_one_calibration_file_are_told_so_at_start(tmp_path):
    """Two services given one calibration.file reloaded each other's calibration at their restart, or overwrote each
    other's (a field trial). The file is held by the service that runs; a second is refused at its start, naming the
    key, the file and who holds it; once the first stops, it may start."""
    from fluxcal.service.wiring.startcal import Keeper

    cfg = config(tmp_path)
    first, second = Keeper(cfg, print), Keeper(cfg, print)
    first.claim()
    with pytest.raises(ConfigError) as e:
        second.claim()
    said = str(e.value)
    assert said.startswith(f"calibration.file = {cfg.calibration.file!r} is held by another running service (unit "
                           f"grad1, process ") and "give each service its own calibration.file" in said
    first.release()
    second.claim()
    second.release()
    # a link planted where the lock goes: removed, its target never written through
    victim = tmp_path / "victim.txt"
    victim.write_text("keep me")
    lock = Path(cfg.calibration.file + ".lock")
    lock.unlink()
    lock.symlink_to(victim)
    first.claim()
    assert victim.read_text() == "keep me" and not lock.is_symlink() and "unit grad1" in lock.read_text()
    first.release()


class Service:
    """`fluxcal run` on the simulated unit, as fast as it can read (no pacing), listening on a free port."""

    def __init__(self, tmp: Path, stack: ExitStack, **kw) -> None:
        self.endpoint = f"tcp/127.0.0.1:{free_port()}"
        path = Path(service_config(tmp, run_s=kw.pop("run_s", 0), realtime=False))
        path.write_text(path.read_text().replace('listen = ["tcp/127.0.0.1:0"]', f'listen = ["{self.endpoint}"]'))
        self.cfg = load_config(path)
        self.said: list[str] = []
        self.stop = threading.Event()
        self.daemon = Daemon(self.cfg, stop=self.stop, say=self.said.append, **kw)
        self.result: list = []
        self.thread = threading.Thread(target=lambda: self.result.append(self._run()), daemon=True)
        self.thread.start()
        stack.callback(self.close)
        deadline = time.monotonic() + 20
        while not any(m.startswith("publishing on zenoh") for m in self.said):
            assert time.monotonic() < deadline and self.thread.is_alive(), (self.said, self.result)
            time.sleep(0.05)
        self.client = stack.enter_context(BusClient(ZenohConfig.client(self.endpoint), self.cfg.unit.name, streams=[]))

    def _run(self):
        try:
            return self.daemon.run()
        except BaseException as e:  # noqa: BLE001 - the test asserts there was none
            return e

    def close(self) -> None:
        self.stop.set()
        self.thread.join(20)

    def wait_usable(self, timeout: float = 60.0) -> dict:
        deadline = time.monotonic() + timeout
        while True:
            st = self.client.query_state(timeout=5.0)
            if st.get("usable") and st.get("samples_seen", 0) > 2 * self.cfg.estimator.min_samples:
                return st
            assert time.monotonic() < deadline and self.thread.is_alive(), (st, self.said[-5:])
            time.sleep(0.2)


@pytest.mark.slow
def test_the_red_teams_foreign_calibration_is_refused_and_the_summary_says_so(tmp_path):
    with ExitStack() as stack:
        svc = Service(tmp_path, stack)
        st = svc.wait_usable()
        own = calibration_from_dict({"format": "fluxcal.calibration", "version": 1, "method": "rls",
                                     "probes": st["probes"], "align": st["align"], "total_nT": st["total_nT"]})
        foreign = shifted(own, 5000.0)                                  # same probe names, no "unit" said
        from fluxcal.service.io.calfile import calibration_to_dict

        answer = svc.client.command("apply", json.dumps(calibration_to_dict(foreign)), timeout=10.0)
        assert answer["ok"] is False and "fails the data check" in answer["error"], answer
        named = _set(calibration_to_dict(own), ("unit",), "grad2")
        answer = svc.client.command("apply", json.dumps(named), timeout=10.0)
        assert answer["ok"] is False and "made for unit 'grad2'" in answer["error"], answer
        after = svc.client.query_state(timeout=5.0)
        assert after["cal_id"] >= st["cal_id"] and not after["held"]                  # nothing was put in use
        assert load_calibration(svc.cfg.calibration.file).unit["name"] == "grad1"   # the persisted one: its own
    assert svc.result == [0], svc.result
    summary = [m for m in svc.said if m.startswith("summary")]
    assert "summary: calibrations refused: 2 calibration(s) refused" in "\n".join(summary), summary
    assert "no loss and no fault seen" not in "\n".join(summary)


def test_a_calibration_file_that_is_a_folder_is_refused_at_start_and_a_failed_save_is_summarised(tmp_path,
                                                                                                 monkeypatch):
    path = Path(service_config(tmp_path, run_s=5))
    (tmp_path / "folder").mkdir()
    path.write_text(path.read_text().replace(f'file = "{tmp_path / "cal.json"}"', f'file = "{tmp_path / "folder"}"'))
    with pytest.raises(ConfigError, match=r"calibration.file: '.*folder' is a folder \(allowed: a file's path"):
        load_config(path)
    # a save that fails later (a full disk): said once with its reason, counted, in the summary at stop
    cfg = config(tmp_path)
    said: list[str] = []
    daemon = Daemon(cfg, say=said.append)
    pipeline = build_pipeline(cfg, None)

    def full(*a, **k):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr("fluxcal.service.wiring.startcal.save_calibration", full)
    for _ in range(3):
        cmd = _Cmd("apply", json.dumps(good_calibration()))
        daemon._apply_command(cmd, pipeline, Sinks([], said.append))
        assert cmd.answer["ok"] is True                             # in use; only its saving failed
    assert len([m for m in said if "could not persist" in m]) == 1 and daemon.keeper.persist_failures == 3
    from fluxcal.service.wiring.faults import FaultWatch

    lines = FaultWatch(said.append).summary({"frames_accepted": 10, "persist_failures": 3,
                                              "calibrations_refused": 0, "commands_refused": 0})
    assert "summary: calibration not persisted: 3 save(s) of the calibration in use failed" in lines
