"""The service's process outlives whatever reads its stderr, and stops cleanly on SIGHUP.

Before: `fluxcal run ... 2>&1 | head -3` ended the service (exit 1) at the next status line with a
BrokenPipeError; SIGHUP (a closed terminal or ssh session) killed it with status 129 and left the
recording without its footer.
"""

from __future__ import annotations

import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from mcap.reader import make_reader
from test_recording import service_config
from test_zenoh_security import free_port

from fluxcal.service.io.bus import BusClient, ZenohConfig


def _config(tmp_path: Path) -> tuple[str, str]:
    port = free_port()
    text = (Path(service_config(tmp_path, run_s=0)).read_text()
            .replace('listen = ["tcp/127.0.0.1:0"]', f'listen = ["tcp/127.0.0.1:{port}"]')
            .replace("status_s = 10 ", "status_s = 0.3 "))
    path = tmp_path / "run.toml"
    path.write_text(text)
    return str(path), f"tcp/127.0.0.1:{port}"


def _start(cfg: str) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "fluxcal.service.wiring.cli", "run", "--config", cfg],
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)


def _read_until(proc: subprocess.Popen, marker: str, timeout: float = 30.0) -> list[str]:
    lines, deadline = [], time.monotonic() + timeout
    while time.monotonic() < deadline:
        line = proc.stderr.readline()
        if not line:
            break
        lines.append(line)
        if marker in line:
            return lines
    raise AssertionError(f"no {marker!r} within {timeout} s: {lines[-5:]}")


def _finished(rec_dir: Path) -> list[Path]:
    """The recordings in rec_dir, each asserted to end with its summary and footer (a clean close)."""
    files = sorted(rec_dir.glob("*.mcap"))
    for f in files:
        with f.open("rb") as fh:
            assert make_reader(fh).get_summary() is not None, f"{f} has no summary: not closed cleanly"
    return files


def _samples_seen(endpoint: str) -> int:
    with BusClient(ZenohConfig.client(endpoint), "grad1", streams=[]) as client:
        return int(client.query_state(timeout=5.0).get("samples_seen", 0))


@pytest.mark.slow
def test_the_service_outlives_the_reader_of_its_stderr(tmp_path):
    cfg, endpoint = _config(tmp_path)
    proc = _start(cfg)
    try:
        _read_until(proc, "publishing on zenoh")
        proc.stderr.close()                       # `| head -3`: the reader goes away
        seen = _samples_seen(endpoint)
        deadline = time.monotonic() + 30
        while _samples_seen(endpoint) < seen + 400:   # status lines every 0.3 s meanwhile, each one a broken pipe
            assert proc.poll() is None, f"the service stopped with {proc.returncode}"
            assert time.monotonic() < deadline
            time.sleep(0.3)
        assert proc.poll() is None
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(30) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(10)
    assert _finished(tmp_path / "rec")


@pytest.mark.slow
def test_sighup_is_a_clean_stop_with_a_finished_recording(tmp_path):
    cfg, endpoint = _config(tmp_path)
    proc = _start(cfg)
    try:
        _read_until(proc, "publishing on zenoh")
        seen = _samples_seen(endpoint)
        deadline = time.monotonic() + 30
        while _samples_seen(endpoint) < seen + 200:
            assert time.monotonic() < deadline
            time.sleep(0.2)
        proc.send_signal(signal.SIGHUP)
        rest = proc.stderr.read()
        assert proc.wait(30) == 0, rest[-2000:]
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(10)
    assert "stopped" in rest and "Traceback" not in rest
    files = _finished(tmp_path / "rec")
    assert len(files) == 1
