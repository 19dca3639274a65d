"""What discovery finds beyond the catalogue reaches the HTML report and the dashboard, as it reaches the terminal
(issue 30: --write-effect, "the same from the HTML report and the dashboard's diagnosis")."""

from __future__ import annotations

import http.client
import json
from pathlib import Path

import pytest

from fluxcal.service.wiring.cli import main

ROOT = Path(__file__).resolve().parents[2]
PUMP = ROOT / "recordings" / "grad3-pump.mcap"


@pytest.mark.slow
def test_the_report_says_what_was_discovered_and_how_to_write_it(tmp_path, capsys, monkeypatch):
    from matplotlib.axes import Axes

    bars, bar = [], Axes.bar

    def told(self, *args, **kwargs):                  # the bars drawn, by label
        bars.append(kwargs.get("label"))
        return bar(self, *args, **kwargs)
    monkeypatch.setattr(Axes, "bar", told)
    assert main(["diagnose", str(PUMP), "--report", str(tmp_path / "rep"), "--json"]) == 0
    # the error per channel after what explains it: discovery's finding (the plot drew "before" alone, under a
    # caption that said "before and after": a field trial)
    i = bars.index("before")
    assert bars[i:i + 3] == ["before", "after + what discovery found", "noise floor"], bars
    d = json.loads(capsys.readouterr().out)
    assert d["discovery"]["claimed"]
    page = (tmp_path / "rep" / "index.html").read_text()
    assert "<h2>Beyond the catalogue</h2>" in page and "a field periodic at 1.5 Hz" in page
    assert "--write-effect FILE.py" in page
    # its long lines (195 characters on this recording) wrap inside the page (60em wide), not off its right edge
    pre = page.split("<h2>Beyond the catalogue</h2><pre>")[1].split("</pre>")[0]
    assert max(len(line) for line in pre.splitlines()) > 150
    style = page.split("<style>")[1].split("</style>")[0]
    assert "pre { white-space: pre-wrap; overflow-wrap: anywhere; }" in style


def test_the_dashboard_offers_the_discovered_term_as_an_effect_module(tmp_path):
    from fluxcal.service.wiring.dashboard.hub import discovered_effect
    from fluxcal.service.wiring.dashboard.server import DashboardServer
    from fluxcal.service.wiring.dashboard.view import UnitView

    view = UnitView("grad3")
    with pytest.raises(Exception, match="nothing to write"):
        discovered_effect(view)
    view.diagnosis = {"status": "done", "effect_module": "class Discovered: pass\n",
                      "discovery": {"claimed": True, "sentence": "a field periodic at 1.5 Hz on s2"}}

    class _Hub:
        def units(self):
            return {"units": []}

        def discovered_effect(self, unit):
            if unit != "grad3":
                raise KeyError(unit)
            return discovered_effect(view)

    server = DashboardServer(_Hub(), "127.0.0.1", 0).start()
    try:
        host, port = server.server_address[:2]
        conn = http.client.HTTPConnection(host, port, timeout=5)
        conn.request("GET", "/api/effect?unit=grad3", headers={"Host": f"127.0.0.1:{port}"})
        r = conn.getresponse()
        body = r.read().decode()
        assert r.status == 200 and body == "class Discovered: pass\n"
        assert 'filename="grad3_discovered.py"' in r.getheader("Content-Disposition")
    finally:
        server.stop()
