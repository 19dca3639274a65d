"""docs/tutorial-discover.md runs as written: diagnose discovers the pump beyond the catalogue and writes it as an
effect module; the user names it; fit takes it back; the running service's pipeline adds it, and the dashboard's
error table falls to the noise (issue 30: learn which effect is missing, add it, watch the error fall)."""

from __future__ import annotations

import json
import re
import shlex
from pathlib import Path

import pytest
from test_tutorial import pump_config

from fluxcal.service.wiring.cli import main

ROOT = Path(__file__).resolve().parents[2]
TUTORIAL = ROOT / "docs" / "tutorial-discover.md"


def _commands() -> list[list[str]]:
    return [shlex.split(m.group(1)) for m in re.finditer(r"^    fluxcal (.+)$", TUTORIAL.read_text(), re.M)]


@pytest.mark.slow
def test_the_discovery_tutorial_runs_as_written(tmp_path, monkeypatch, capsys, clean_registry):
    cmds = _commands()[:3]
    assert [c[0] for c in cmds] == ["diagnose", "fit", "command"]
    monkeypatch.chdir(tmp_path)
    for c in cmds:                                   # the recordings as the repository's root names them
        c[1:] = [str(ROOT / a) if a.startswith("recordings/") else a for a in c[1:]]
    # 1. diagnose finds the pump and writes it
    capsys.readouterr()
    assert main(cmds[0]) == 0
    out, err = capsys.readouterr()
    assert "a field periodic at 1.5 Hz" in out and "on s2" in out
    quoted = re.search(r"discovery: \d+ groups of \d+ parameters", TUTORIAL.read_text()).group(0)
    assert quoted in out, quoted                     # the figures the tutorial quotes are the run's
    written = tmp_path / "found_pump.py"
    assert written.is_file() and "written to found_pump.py" in err and "--effects found_pump.py:Discovered" in err
    text = written.read_text()
    assert "class Discovered(EffectTerm):" in text and "per_sample = True" in text
    # 2. the user names it
    text = text.replace("class Discovered(EffectTerm):", "class FoundPump(EffectTerm):")
    text = text.replace("name = 'discovered'", "name = 'found-pump'")
    written.write_text(text)
    # 3. fit takes it back: at the floor, the pump's 4 nT on s2's x cosine and y sine
    assert main(cmds[1] + ["--json"]) == 0
    d = json.loads(capsys.readouterr().out)
    p = {name: q["value"] for name, q in d["effect_params"]["found-pump"].items()}
    assert abs(p["s2.line at 1.5 Hz cos x nT"] - 4.0) < 0.15 and abs(p["s2.line at 1.5 Hz sin y nT"] - 4.0) < 0.15
    scal = {s["name"]: s["scalar_rms_nT"] for s in d["sensors"]}
    assert scal["s2"] < 0.65 and d["rms_nT"] < 0.8
    assert main(cmds[1]) == 0 and (tmp_path / "found-pump-cal.json").exists()
    assert json.loads((tmp_path / "found-pump-cal.json").read_text())["effects"] == ["found-pump"]
    # 4. the running service's pipeline adds it; the dashboard's error table falls to s2's noise
    before, after = _service_and_dashboard(tmp_path, written)
    print(f"dashboard, s2.scalar over the last 10 s: {before:.2f} nT before add-effect found-pump, {after:.2f} after")
    assert before > 2.0 and after < 0.75, (before, after)
    assert cmds[2] == ["command", "add-effect", "found-pump"]


def _service_and_dashboard(tmp_path: Path, effect: Path) -> tuple[float, float]:
    """The recording through the pipeline of `fluxcal run` (build_pipeline, the [effects] plugin named), block by
    block; `add-effect found-pump` once usable; each block's error message to the dashboard's view of the unit, whose
    10-s table is read just before the command and at the end."""
    from fluxcal.service.io.bus import Message
    from fluxcal.service.io.recordings.reader import read_recording
    from fluxcal.service.wiring.config import load_config
    from fluxcal.service.wiring.daemon import build_pipeline
    from fluxcal.service.wiring.dashboard.view import UnitView

    cfg_path = pump_config(tmp_path, f"{effect}:FoundPump")
    pl = build_pipeline(load_config(cfg_path))
    block = read_recording(ROOT / "recordings" / "grad3-pump.mcap").raw_blocks[0]
    view = UnitView("grad3")
    before = None
    i = 0
    while i < block.n_samples:
        if before is None and pl.calibration is not None and i >= 2000:
            before = view.windows()["error_rms_nT"]["s2.scalar"]
            pl.command("add-effect", "found-pump", seq=int(block.seq[i]), t_s=float(block.t_s[i]))
        piece = block.slice(i, min(i + 25, block.n_samples))
        res = pl.process(piece)
        if res.error and res.corrected is not None:
            c = res.corrected
            view.update(Message("error", "fluxcal/grad3/error", {"rms_nT": res.error, "seq": int(c.seq[0]),
                                                                 "t_s": float(c.t_s[0]), "n": c.n_samples}))
        i += piece.n_samples
    assert before is not None, "the calibration never became usable"
    return float(before), float(view.windows()["error_rms_nT"]["s2.scalar"])


@pytest.mark.slow
def test_the_shape_section_runs_as_written_with_the_figures_it_quotes(tmp_path, monkeypatch, capsys, clean_registry):
    """Section 5: diagnose finds the flap's magnet as a distance power at s2 and s1, writes it, and fit takes it
    back alone with the same parameters; the figures the tutorial and docs/effects.md quote are the run's."""
    cmds = _commands()[3:]
    assert [c[0] for c in cmds] == ["diagnose", "fit"]
    monkeypatch.chdir(tmp_path)
    for c in cmds:
        c[1:] = [str(ROOT / a) if a.startswith("recordings/") else a for a in c[1:]]
    text = TUTORIAL.read_text()
    capsys.readouterr()
    assert main(cmds[0]) == 0
    out = " ".join(capsys.readouterr().out.split())
    section = " ".join(text[text.index("## 5."):].split())
    for quote in (re.search(r"discovery: \d+ groups of \d+ parameters", section).group(0),
                  "f1 + f2 of its lines at 0.05831, 0.1897 Hz", "s1 from -2.67 to 11.7 nT (0.15 of s2's",
                  "(c / (c - flap_deg))^n with c = 82.46 +- 1.8 deg and n = 2.95 +- 0.096",
                  "distance power 8, 0.7727"):
        assert quote in section and quote in out, quote
    assert "polynomial 7, 1.217" in out and "cubic 8, 0.8107" in out
    assert "a quadratic (held-out 1.217 nT) and a cubic (0.8107 nT)" in section
    for doc in ("effects.md", "diagnose.md"):
        quoted = " ".join((ROOT / "docs" / doc).read_text().split())
        assert "c = 82.46 +- 1.8 deg and n = 2.95 +- 0.096" in quoted and "s1 from -2.67 to 11.7 nT" in quoted, doc
    written = (tmp_path / "found_flap.py").read_text()
    assert "def law_1(x, p, ref, span)" in written and "'flap_deg c deg'" in written and "beside = ()" in written
    assert main(cmds[1]) == 0
    fitted = capsys.readouterr().out
    for line in ("discovered   flap_deg c deg               82.4622 ± 1.76",
                 "discovered   flap_deg n                   2.94968 ± 0.0958"):
        assert line in fitted and line in text, line
    assert re.search(r"s2\.scalar\s+329\.88\s+0\.607", fitted) and "from 329.88 nT, uncalibrated, to 0.607 nT" in text

