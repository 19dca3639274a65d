"""The contracts a user needs are in the repository's docs/, and they say what the code does."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from fluxcal.drivers import icd

ROOT = Path(__file__).resolve().parents[2]


def test_the_documented_test_vector_decodes_to_the_documented_values():
    text = (ROOT / "docs" / "wire-format.md").read_text()
    hex_line = re.search(r"^ {4}(a5 5a(?: [0-9a-f]{2})+)$", text, flags=re.M).group(1)
    frame = bytes.fromhex(hex_line.replace(" ", ""))
    assert len(frame) == icd.frame_length(1) == 27
    parsed = icd.parse_serial(frame, 1, final=True)
    f = parsed.frames
    assert parsed.crc_failures == 0 and len(f) == 1
    assert (int(f.seq[0]), int(f.t_us[0])) == (1, 1000)
    assert f.counts[0, 0].tolist() == [1, -1, 50_000_000] and int(f.temp_raw[0, 0]) == 2500 and int(f.flags[0]) == 0


def test_the_readme_and_docs_point_into_the_repository_not_beside_it():
    for path in [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]:
        for ref in re.findall(r"\.\./shared/[\w./-]+", path.read_text()):
            assert ref.startswith("../shared/real-data"), (path.name, ref)     # public test data only
    for name in ("wire-format.md", "csv.md", "contracts.md", "zenoh.md", "recording.md"):
        assert (ROOT / "docs" / name).stat().st_size > 1000, name
    csv = (ROOT / "docs" / "csv.md").read_text()
    assert "s1_x" in csv and "ref_total" in csv and "_temp" in csv
    assert np.all([k in (ROOT / "docs" / "contracts.md").read_text() for k in ("warnings", "coverage", "candidates")])


def test_the_zenoh_snippet_runs_against_a_service_that_started_from_a_saved_calibration(capsys):
    """docs/zenoh.md's Python snippet, run as written against a bus whose state has no gate verdict yet
    (a service that reloaded its calibration): it must not raise."""
    import threading

    from test_watch import free_port

    from fluxcal.service.io.bus import ServiceBus, ZenohConfig

    text = (ROOT / "docs" / "zenoh.md").read_text()
    snippet = re.search(r"\n((?: {4}.*\n)+)", text[text.index("From Python:"):]).group(1)
    port = free_port()
    snippet = "\n".join(line[4:] for line in snippet.splitlines()).replace("7447", str(port))
    state = {"usable": True, "cal_id": 1, "gate": None}
    bus = ServiceBus(ZenohConfig(listen=[f"tcp/127.0.0.1:{port}"]), "grad1", state_fn=lambda: state)
    stop = threading.Event()

    def serve() -> None:
        while not stop.is_set():
            cmd = bus.next_command(timeout=0.05)
            if cmd is not None:
                cmd.reply({"ok": True})

    t = threading.Thread(target=serve, daemon=True)
    t.start()
    try:
        exec(compile(snippet, "docs/zenoh.md", "exec"), {})
    finally:
        stop.set()
        t.join(2.0)
        bus.close()
    out = capsys.readouterr().out
    assert "'ok': True" in out and "no gate verdict yet" in out
