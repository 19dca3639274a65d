"""End to end: the simulated unit on a pty -> `fluxcal run` (a subprocess) -> our own Zenoh subscriber.

The subscriber sees corrected vectors, tensor components and the calibration state, and they match
the simulator's truth within the noise once the online estimator has converged.
"""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time

import numpy as np
import pytest

from fluxcal.service.io.bus import BusClient, ZenohConfig

pytestmark = pytest.mark.slow

PROBES = [  # name, position, offset, scale, non-orthogonality, misalignment
    ("s1", [0.2, 0, 0], [357.0, 160.0, -213.0], [1.05, 0.97, 1.02], [1.5, -0.8, 1.1], [-3.0, 2.0, 4.0]),
    ("s2", [0, 0.2, 0], [-253.0, 183.0, 97.0], [0.96, 1.03, 1.01], [-0.7, 1.2, 0.6], [2.5, -1.0, 3.5]),
    ("s3", [-0.2, 0, 0], [169.0, -364.0, 245.0], [1.01, 0.99, 0.97], [0.9, -1.5, 1.3], [-1.5, 3.0, -2.5]),
    ("s4", [0, -0.2, 0], [256.0, 169.0, -166.0], [0.98, 1.04, 1.03], [-1.2, 0.4, -0.9], [2.0, 1.5, 1.0]),
]
NOISE_NT = 0.5
TOTAL_NT = 52000.0


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def write_config(tmp_path, port: int, transport: str = "pty") -> str:
    lines = ['[unit]', 'name = "e2e"', 'n_probes = 4', '']
    for name, pos, *_ in PROBES:
        lines += ['[[probes]]', f'name = "{name}"', f'position_m = {pos}', '']
    lines += ['[source]', 'kind = "sim"', f'transport = "{transport}"', 'run_s = 40.0', '',
              '[sim]', 'seed = 7', 'rate_hz = 100.0', 'realtime = false',
              '[sim.field]', f'total_nT = {TOTAL_NT}', 'inclination_deg = 60.0', 'declination_deg = 3.0',
              '[sim.reference]', 'enabled = true', 'noise_nT = 0.02',
              '[sim.motion]', 'kind = "tumble"', 'rate_deg_s = 45.0', 'tumble_period_s = 4.0', '']
    for name, pos, off, scale, nono, mis in PROBES:
        lines += ['[[sim.probes]]', f'name = "{name}"', f'position_m = {pos}', f'offset_nT = {off}',
                  f'scale = {scale}', f'nonorth_deg = {nono}', f'misalign_deg = {mis}', f'noise_nT = {NOISE_NT}', '']
    lines += ['[estimator]', f'total_nT = {TOTAL_NT}', 'forgetting = 0.9999', 'min_samples = 1500', 'check_every_s = 1.0',
              'window_s = 20.0', '',
              '[calibration]', f'file = "{tmp_path / "state" / "cal.json"}"', '',
              '[zenoh]', f'listen = ["tcp/127.0.0.1:{port}"]', '',
              '[mcap]', 'enabled = false', '']
    path = tmp_path / "e2e.toml"
    path.write_text("\n".join(lines))
    return str(path)


def run_service(cfg_path: str):
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    return subprocess.Popen([sys.executable, "-m", "fluxcal.service.wiring.cli", "run", "--config", cfg_path],
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, env=env, text=True)


def stop(proc) -> str:
    if proc.poll() is None:
        proc.send_signal(signal.SIGTERM)
    try:
        out, _ = proc.communicate(timeout=20)
    except subprocess.TimeoutExpired:
        proc.kill()
        out, _ = proc.communicate()
    return out


@pytest.mark.parametrize("transport", ["pty", "can-virtual"])
def test_service_publishes_calibrated_outputs_matching_truth(tmp_path, transport):
    port = free_port()
    cfg_path = write_config(tmp_path, port, transport)
    proc = run_service(cfg_path)
    client = None
    try:
        deadline = time.monotonic() + 30
        while client is None:
            try:
                client = BusClient(ZenohConfig.client(f"tcp/127.0.0.1:{port}"), "e2e",
                                   streams=["corrected", "tensor", "calibration", "health"])
            except Exception:
                if time.monotonic() > deadline or proc.poll() is not None:
                    raise
                time.sleep(0.2)
        usable_state = None
        corrected, tensors = [], []
        deadline = time.monotonic() + 90
        while time.monotonic() < deadline and proc.poll() is None:
            msg = client.recv(timeout=0.5)
            if msg is None:
                continue
            if msg.stream == "calibration" and msg.value.get("kind") == "calibration":
                usable_state = msg.value["state"]
            elif msg.stream == "corrected" and usable_state is not None:
                corrected.append(msg.value.corrected_nT)
            elif msg.stream == "tensor" and usable_state is not None:
                tensors.append(msg.value.values)
            if sum(len(c) for c in corrected) > 1500 and sum(len(t) for t in tensors) > 1500:
                break
    finally:
        if client is not None:
            client.close()
        log = stop(proc)
    assert usable_state is not None, log
    assert usable_state["usable"]
    # the calibration state carries each probe's offset: the simulator's truth within a few nT
    for st, (name, _, off, *_rest) in zip(usable_state["probes"], PROBES):
        assert st["name"] == name
        assert np.allclose(st["offset_nT"], off, atol=3.0), (name, st["offset_nT"], off)
    c = np.concatenate(corrected)[-1000:]
    mag = np.linalg.norm(c, axis=2)
    assert np.sqrt(np.mean((mag - TOTAL_NT) ** 2)) < 4 * NOISE_NT, mag.mean(axis=0)
    # uniform field: every tensor component is noise, sqrt(2)·σ / baseline ≈ 1.8 nT/m, and the array agrees
    g = np.concatenate(tensors)[-1000:]
    rms = np.sqrt(np.mean(g ** 2, axis=0))
    assert rms.max() < 4 * np.sqrt(2) * NOISE_NT / 0.4, rms
    assert "calibration usable" in log


def test_effect_added_over_zenoh_makes_the_published_error_fall(tmp_path):
    port = free_port()
    text = (open("configs/sim-gradiometer.toml").read()
            .replace('transport = "pty"', 'transport = "direct"')
            .replace('run_s = 0 ', 'run_s = 0 ')
            .replace('dir = "../recordings/live"', 'enabled = false')
            .replace('file = "../state/grad1-sim-cal.json"', f'file = "{tmp_path / "cal.json"}"')
            .replace('listen = ["tcp/127.0.0.1:7447"]', f'listen = ["tcp/127.0.0.1:{port}"]')
            .replace('amplitude_C = 0.0 ', 'amplitude_C = 6.0 ')
            .replace('# period_s = 600.0 ', 'period_s = 30.0 ')
            .replace('# temp_offset_nT_per_C = [0.0, 0.0, 0.0]', 'temp_offset_nT_per_C = [3.0, -2.0, 1.5]', 1)
            .replace('# speed = 1.0 ', 'speed = 3.0 '))           # the unit's time three times the wall clock's
    cfg = tmp_path / "fx.toml"
    cfg.write_text(text)
    proc = run_service(str(cfg))
    client = None
    try:
        deadline = time.monotonic() + 30
        while client is None:
            try:
                client = BusClient(ZenohConfig.client(f"tcp/127.0.0.1:{port}"), "grad1", streams=["error"])
            except Exception:
                if time.monotonic() > deadline or proc.poll() is not None:
                    raise
                time.sleep(0.2)

        def mean_error(seconds: float) -> float:
            vals, end = [], time.monotonic() + seconds
            while time.monotonic() < end:
                m = client.recv(timeout=0.5)
                if m is not None and "s1.scalar" in m.value.get("rms_nT", {}):
                    vals.append(m.value["rms_nT"]["s1.scalar"])
            return float(np.sqrt(np.mean(np.square(vals)))) if vals else float("nan")

        deadline = time.monotonic() + 60
        while not np.isfinite(mean_error(1.0)):                      # wait for a usable calibration
            assert time.monotonic() < deadline and proc.poll() is None
        time.sleep(4.0)                                              # let the ring buffer fill (12 s of data)
        before = mean_error(2.0)                                     # 6 s of data
        reply = client.command("add-effect", "temperature", timeout=30.0)
        assert reply["ok"], reply
        client.drain()
        after = mean_error(2.0)
    finally:
        if client is not None:
            client.close()
        log = stop(proc)
    print(f"published scalar error of s1: {before:.2f} nT before the temperature term, {after:.2f} nT after")
    assert before > 2.5 * 0.6, (before, log)                          # the hidden temperature effect
    assert after < 1.3 * 0.6, (after, log)                           # down to the probe's 0.6 nT noise
