"""What diagnose writes beside its result (fluxcal.service.wiring.commands.written): no effect module where discovery found
nothing (said, exit status kept), and a report that cannot be written costs the exit status, never the diagnosis."""

from __future__ import annotations

from types import SimpleNamespace

from fluxcal.service.wiring.commands.diagnose import DiagnoseResult
from fluxcal.service.wiring.commands.written import write_diagnosis_report, write_discovered
from fluxcal.service.wiring.result import Said


def _out(discovery=None) -> DiagnoseResult:
    return DiagnoseResult("diagnose", "rec.mcap", diagnosis=SimpleNamespace(discovery=discovery))


def test_no_module_is_written_where_discovery_claimed_nothing(tmp_path):
    said = Said("diagnose")
    for found, why in ((None, "discovery did not run"),
                       (SimpleNamespace(claimed=False, reason="no group passes the selection"),
                        "no group passes the selection")):
        out = _out(found)
        write_discovered(out, str(tmp_path / "found.py"), "rec.mcap", said)
        assert out.written == [] and out.status == 0
        assert not (tmp_path / "found.py").exists()
        assert said.notes[-1].kind == "write-effect" and said.notes[-1].is_warning
        assert f"nothing written: no term was discovered beyond the catalogue ({why})" in said.notes[-1].text


def test_a_report_that_cannot_be_written_is_said_and_costs_the_status(tmp_path, monkeypatch):
    import fluxcal.service.io.report as report
    import fluxcal.service.wiring.calib_report as calib_report

    def full_disk(*args, **kwargs):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(report, "write_report", full_disk)
    monkeypatch.setattr(calib_report, "section_from_diagnosis", lambda d: None)
    said = Said("diagnose")
    out = _out()
    diagnosis = out.diagnosis
    write_diagnosis_report(out, str(tmp_path / "rep"), said)
    assert out.status == 1 and out.report is None and out.written == []
    assert out.diagnosis is diagnosis                             # the diagnosis stays
    assert said.notes[-1].kind == "report"
    assert f"{tmp_path / 'rep'}: the report could not be written" in said.notes[-1].text
    assert "No space left on device" in said.notes[-1].text


def test_writing_the_module_again_keeps_what_the_user_edited(tmp_path):
    """A new user renamed the written class in found.py, ran diagnose --write-effect found.py again, and lost the
    edits without a word. Now a file there that differs is kept as found.py.~1~ (then ~2~), and that is said; the
    same text written again keeps nothing."""
    import numpy as np

    from fluxcal.service.numerics.diagnose.library import Feature, Group

    f = Feature("heater_A", "heater_A", "A", "value", {"source": "column", "column": "heater_A", "centre": 0.0},
                np.linspace(0.0, 1.0, 50))
    found = SimpleNamespace(claimed=True, groups=[SimpleNamespace(group=Group("offset", 0, "s1", f),
                                                                  reading="s1's offset follows heater_A")])
    target = tmp_path / "found.py"
    said = Said("diagnose")
    write_discovered(_out(found), str(target), "rec.mcap", said)
    first = target.read_text()
    write_discovered(_out(found), str(target), "rec.mcap", said)            # the same text: nothing kept
    assert not list(tmp_path.glob("found.py.~*~"))
    target.write_text(first.replace("class Discovered(", "class Heater("))   # the user's edit
    write_discovered(_out(found), str(target), "rec.mcap", said)
    assert (tmp_path / "found.py.~1~").read_text().count("class Heater(") == 1 and target.read_text() == first
    assert any("held another module (your edits?): kept as" in n.text and "found.py.~1~" in n.text
               for n in said.notes), [n.text for n in said.notes]
    target.write_text("# edited again\n")
    write_discovered(_out(found), str(target), "rec.mcap", said)
    assert (tmp_path / "found.py.~2~").read_text() == "# edited again\n"
