"""A kind of input and a protocol added from a test module alone (issue 41): an in-memory fake bus ("membus") and
an ASCII line per sample with an NMEA checksum ("fxg-line"), declared through fluxcal.drivers.registry with no edit of the
package, then `fluxcal run --config` on them. The kind's [source] table is validated (the key, the value and what is
allowed named as for fluxcal's own kinds), its source opened (a failure to open said with its port's key first),
its clock checked against the configured rate, its counters in health (its own and the protocol's: no serial or CAN
counter) and its faults said in its own words. The same protocol added to the serial kind reads a pty through the
service. Before, a new kind meant editing seven lists of kinds in five files."""

from __future__ import annotations

import dataclasses
import signal
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
from test_can_garbage import LastHealth
from test_recording import service_config

from fluxcal.drivers.block import SampleBlock
from fluxcal.drivers.config import spec
from fluxcal.drivers.declare import Counted, NoDecode, Protocol, ProtocolTable, SourceKind, resolve
from fluxcal.drivers.errors import DriverError
from fluxcal.drivers.registry import (
    allowed,
    forget_kind,
    forget_protocol,
    kinds,
    register_kind,
    register_protocol,
    source_kind,
)
from fluxcal.drivers.source import Counters, Source
from fluxcal.service.io.recordings.reader import read_recording
from fluxcal.service.wiring.cli import main
from fluxcal.service.wiring.config import load_config
from fluxcal.service.wiring.daemon import Daemon

N_PROBES, RATE_HZ = 2, 100.0


# --- the protocol: "$FXG,seq,t_us,x1,y1,z1,...,temp1,...*HH" (nT, degC), one line per sample ---------------------

def nmea_checksum(body: bytes) -> int:
    out = 0
    for ch in body:
        out ^= ch
    return out


class FxgLine:
    """Bytes as they come -> the samples of the lines they complete; a line whose checksum fails is counted."""

    def __init__(self, n_probes: int, *, counters: Counters, **_: object) -> None:
        self.n, self.counters, self.tail = n_probes, counters, b""

    def feed(self, data: bytes, rx_time_s: float | None = None) -> SampleBlock | None:
        *lines, self.tail = (self.tail + data).split(b"\n")
        rows = []
        for line in lines:
            line = line.strip()
            head, star, cs = line.partition(b"*")
            if not (line.startswith(b"$") and star and cs and nmea_checksum(head[1:]) == int(cs, 16)):
                self.counters.checksum_failures += 1
                continue
            rows.append([float(x) for x in head[1:].split(b",")[1:]])
        self.counters.lines_accepted += len(rows)
        if not rows:
            return None
        a = np.asarray(rows)
        n = self.n
        return SampleBlock(t_s=a[:, 1] / 1e6, seq=a[:, 0].astype(np.int64),
                           field_nT=a[:, 2:2 + 3 * n].reshape(-1, n, 3).copy(), temp_C=a[:, 2 + 3 * n:].copy(),
                           flags=np.zeros(len(a), np.uint8))

    def discard_tail(self) -> None:
        self.tail = b""


LINE = Protocol(
    "fxg-line", "one ASCII line per sample with an NMEA checksum", decoder=FxgLine,
    counters=(Counted("lines_accepted", "lines whose checksum holds", decoded=True, what="{n:,} line(s) decoded"),
              Counted("checksum_failures", "lines whose NMEA checksum fails", fault="checksum",
                      label="checksum failures", what="{n:,} line(s) failed their checksum",
                      advice="bit errors, or a second talker on the line: check the cable", share="lines")),
    no_decode=NoDecode("bytes", begin="bytes arrive but no line's checksum holds: {n:,} bytes in {t}",
                       end="lines decode again after {t}; {n:,} bytes in between", total="{k} stretch(es), {n:,} bytes",
                       label="no line decodes"))


# --- the kind: a fake bus that hands out its chunks at a pace, and loses one (an overrun) ----------------------

@dataclass(kw_only=True)
class MemBusConfig(ProtocolTable):
    channel: str = spec(doc="the fake bus's channel")
    n_probes: int = spec(min=1, max=8)
    rate_hz: float | None = spec(None, min=0.001, max=1e5)


@dataclass
class FakeBus:
    chunks: list                      # bytes, or None where the bus's buffer overran (its data lost)
    period_s: float


BUSES: dict[str, FakeBus] = {}


class MemBusSource(Source):
    def __init__(self, config: MemBusConfig) -> None:
        bus = BUSES.get(config.channel)
        if bus is None:
            raise DriverError(f"fake bus {config.channel!r}: no such channel")
        kind = source_kind("membus")
        protocol = kind.protocol(config.protocol)
        super().__init__(config.n_probes, Counters.of(kind.words(protocol.name)))
        self.decoder = resolve(protocol.decoder)(config.n_probes, counters=self.counters)
        self.bus, self.next, self.t0 = bus, 0, time.monotonic()

    @property
    def exhausted(self) -> bool:
        return self.next >= len(self.bus.chunks)

    def _read_block(self, timeout: float | None) -> SampleBlock | None:
        due = min(len(self.bus.chunks), int((time.monotonic() - self.t0) / self.bus.period_s) + 1)
        if due <= self.next:
            time.sleep(max(0.0, min(timeout or 0.0, self.t0 + self.next * self.bus.period_s - time.monotonic())))
            return None
        blocks = []
        for chunk in self.bus.chunks[self.next:due]:
            if chunk is None:
                self.counters.bus_overruns += 1
                continue
            self.counters.bus_bytes += len(chunk)
            b = self.decoder.feed(chunk)
            if b is not None:
                blocks.append(b)
        self.next = due
        return SampleBlock.concat(blocks) if blocks else None


MEMBUS = SourceKind(
    "membus", "a test's in-memory fake bus", config=MemBusConfig, factory=MemBusSource,
    counters=(Counted("bus_bytes", "bytes the fake bus delivered", arrival=True),
              Counted("bus_overruns", "times the fake bus's buffer overran", fault="overruns", label="bus overruns",
                      what="{n:,} overrun(s) of the fake bus's buffer, its data lost",
                      advice="the reader fell behind the bus")),
    protocols=(LINE,), port_keys=("source.channel",), unit_clock=True, needs_rate=True)


@pytest.fixture
def declared():
    """The fake kind and the line protocol on the serial kind, while the test runs; the service's signal handlers
    (fluxcal run installs its own) as they were after it."""
    handlers = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)}
    register_kind(MEMBUS)
    register_protocol("serial", dataclasses.replace(LINE, kind="serial"))
    yield
    forget_kind("membus")
    forget_protocol("serial", "fxg-line")
    BUSES.clear()
    for s, h in handlers.items():
        signal.signal(s, h)


def fxg_lines(n: int, bad: set[int], seed: int = 0) -> list[bytes]:
    """n samples of a 2-probe unit turning in a 50,000 nT field at RATE_HZ, as lines; those in `bad` with a wrong
    checksum."""
    rng = np.random.default_rng(seed)
    out = []
    for i in range(n):
        t = i / RATE_HZ
        a, b = 0.7 * t, 0.3 * np.sin(0.4 * t)
        field = 50_000.0 * np.array([np.cos(a) * np.cos(b), np.sin(a) * np.cos(b), np.sin(b)])
        vals = [f"{v:.3f}" for k in range(N_PROBES) for v in field + 40.0 * k + rng.normal(0, 0.5, 3)]
        body = f"FXG,{i},{round(t * 1e6)},{','.join(vals)},{','.join(['21.50'] * N_PROBES)}".encode()
        cs = nmea_checksum(body) ^ (0x5A if i in bad else 0)
        out.append(b"$" + body + f"*{cs:02X}\r\n".encode())
    return out


def membus_config(tmp_path: Path, channel: str, **source: object) -> Path:
    keys = {"kind": "membus", "protocol": "fxg-line", "channel": channel, "n_probes": N_PROBES, "rate_hz": RATE_HZ,
            **source}
    table = "\n".join(f"{k} = {v!r}".replace("'", '"') for k, v in keys.items() if v is not None)
    path = tmp_path / "membus.toml"
    path.write_text(f'[unit]\nname = "fake1"\nn_probes = {N_PROBES}\nstatus_s = 1.0\n\n[source]\n{table}\n\n'
                    f'[calibration]\nfile = "{tmp_path / "cal.json"}"\n\n[zenoh]\nlisten = ["tcp/127.0.0.1:0"]\n\n'
                    f'[mcap]\ndir = "{tmp_path / "rec"}"\n')
    return path


def test_a_kind_declared_by_a_test_is_validated_like_fluxcals_own(declared, tmp_path, capsys):
    assert "'membus'" in allowed() and [k.name for k in kinds()][0] == "sim"
    cases = [({"chanel": "x"}, "source.chanel: unknown key (allowed: kind, protocol, channel, n_probes, rate_hz)"),
             ({"protocol": "nmea"}, "source.protocol: 'nmea' is not allowed (allowed: 'fxg-line')"),
             ({"rate_hz": None}, "source.rate_hz: missing (allowed: the unit's sample rate in Hz"),
             ({"kind": "membuss"}, "source.kind: 'membuss' is not allowed (allowed: 'sim', 'can', 'membus', "
                                   "'replay', 'serial')")]
    for source, message in cases:
        path = membus_config(tmp_path, "nowhere", **source)
        assert main(["run", "--config", str(path)], install_signals=False) == 2
        assert message in capsys.readouterr().err
    # opened by its factory: a channel that is not there is said with the key to change first
    assert main(["run", "--config", str(membus_config(tmp_path, "nowhere"))], install_signals=False) == 1
    assert "source.channel: fake bus 'nowhere': no such channel" in capsys.readouterr().err
    assert load_config(membus_config(tmp_path, "x", protocol=None)).source.protocol == "fxg-line"   # the first


def test_a_kind_declared_by_a_test_runs_through_fluxcal_run_counted_and_said_in_its_words(declared, tmp_path, capsys):
    bad = {122, 125, 131, 137, 410, 411}                       # lines of the 7th and the 21st chunk
    lines = fxg_lines(600, bad)
    chunks: list = [b"".join(lines[i:i + 20]) for i in range(0, 600, 20)]
    chunks.insert(12, None)                                    # the bus's buffer overran once: nothing of it lost
    BUSES["b1"] = FakeBus(chunks, period_s=0.1)                # 6 s of the unit's clock in about 3 s
    path = membus_config(tmp_path, "b1", rate_hz=50.0)         # the unit runs at 100 Hz: its clock says so
    assert main(["run", "--config", str(path)], install_signals=False) == 0
    err = capsys.readouterr().err
    assert "source exhausted" in err
    assert "checksum failures: 4 line(s) failed their checksum in the last" in err
    assert "(check the cable) (health: counters.checksum_failures)" in err.replace("bit errors, or a second talker "
                                                                                   "on the line: ", "")
    assert "summary at stop: 594 line(s) decoded; 2 kind(s) of loss or fault:" in err
    assert "summary: checksum failures: 6 line(s) failed their checksum (1.0% of the lines)" in err
    assert "summary: bus overruns: 1 overrun(s) of the fake bus's buffer, its data lost" in err
    assert "the unit's clock shows 100 samples/s but source.rate_hz = 50" in err
    assert "CRC" not in err and "check the cable, its screen" not in err           # no serial ICD's words
    health = read_recording(tmp_path / "rec").health[-1]
    c = health["counters"]
    assert (c["lines_accepted"], c["checksum_failures"], c["bus_overruns"]) == (594, 6, 1)
    assert c["bus_bytes"] == sum(len(x) for x in lines)
    own = set(MEMBUS.words("fxg-line").names)
    assert own <= set(c) and not set(c) & (set(source_kind("serial").words().names)
                                           | set(source_kind("can").words().names))
    assert health["faults"]["totals"]["checksum"] == 6 and health["faults"]["totals"]["overruns"] == 1


def test_a_protocol_declared_by_a_test_reads_a_serial_port_through_the_service(declared, tmp_path, pty_port):
    port = pty_port()
    text = (Path("configs/serial-example.toml").read_text()
            .replace('port = "/dev/ttyUSB0" ', f'port = "{port.path}"\nprotocol = "fxg-line" ')
            .replace('listen = ["tcp/127.0.0.1:7447"]', 'listen = ["tcp/127.0.0.1:0"]')
            .replace('file = "../state/grad1-serial-cal.json"', f'file = "{tmp_path / "cal.json"}"')
            .replace('rate_hz = 200.0', f'rate_hz = {RATE_HZ}')
            .replace('[mcap]', '[mcap]\nenabled = false'))
    (tmp_path / "s.toml").write_text(text)
    cfg = load_config(tmp_path / "s.toml")
    assert (cfg.source.kind, cfg.source.protocol) == ("serial", "fxg-line")
    health, said = LastHealth(), []
    daemon = Daemon(cfg, say=said.append, sinks=[health])
    thread = threading.Thread(target=daemon.run, daemon=True)
    thread.start()
    try:
        deadline = time.monotonic() + 15
        while not any(m.startswith("publishing on zenoh") for m in said):
            assert time.monotonic() < deadline and thread.is_alive(), said
            time.sleep(0.05)
        wire = b"".join(fxg_lines(300, {7}))
        port.write(wire, chunk=333)
        while health.counters.get("lines_accepted", 0) < 299:
            assert time.monotonic() < deadline + 15 and thread.is_alive(), (health.counters, said)
            time.sleep(0.1)
    finally:
        daemon.stop.set()
        thread.join(20)
    c = health.counters
    assert (c["lines_accepted"], c["checksum_failures"], c["bytes_received"]) == (299, 1, len(wire))
    assert not set(c) & {"crc_failures", "frames_accepted", "bad_frames", "foreign_frames", "clock_jumps"}
    assert any(m.startswith("checksum failures: 1 line(s) failed their checksum") for m in said), said


@pytest.mark.parametrize("transport, faults, own, words, not_said", [
    ("pty", "bitflip_fraction = 0.01\nrestart_at_s = [1.0]", {"bytes_received", "crc_failures", "clock_jumps"},
     ["unit restart: 1 restart(s) of the unit: its counter and clock went back near zero", "summary: CRC failures: "],
     ["CAN"]),
    ("can-virtual", "can_drop_fraction = 0.002\nrestart_at_s = [1.0]",
     {"foreign_frames", "bad_frames", "wrong_length", "can_incomplete"},
     ["unit restart: 1 restart(s) of the unit: its sample counter went back near zero",
      "summary: CAN samples incomplete: "], ["CRC", "clock", "byte"]),
])
def test_health_holds_the_sources_own_counters_and_says_its_faults_in_its_buss_words(tmp_path, transport, faults,
                                                                                       own, words, not_said):
    """The simulated unit through the serial driver (a pty) and through the CAN driver (a virtual bus): each health
    holds its own kind's counters and not the other's, and a restart is said as that bus can tell it (CAN carries no
    unit clock)."""
    text = (Path(service_config(tmp_path, run_s=3.0, realtime=False)).read_text()
            .replace('transport = "pty"', f'transport = "{transport}"')
            .replace("[sim.field]", "seq_start = 30000\n\n[sim.field]")      # a restart well back from the counter
            .replace("[sim.faults]", f"[sim.faults]\n{faults}")
            .replace("[mcap]", "[mcap]\nenabled = false"))
    (tmp_path / "c.toml").write_text(text)
    health, said = LastHealth(), []
    assert Daemon(load_config(tmp_path / "c.toml"), say=said.append, sinks=[health]).run() == 0
    serial, can = (set(source_kind(k).words().names) for k in ("serial", "can"))
    mine, other = (serial, can) if transport == "pty" else (can, serial)
    assert own <= set(health.counters) and mine <= set(health.counters)
    assert not set(health.counters) & (other - mine), set(health.counters) & (other - mine)
    text = "\n".join(said)
    for w in words:
        assert w in text, (w, said)
    for w in not_said:
        assert w not in text.replace("fluxcal-sim", ""), (w, said)


def test_command_state_says_what_arrives_apart_from_what_was_lost_as_the_source_declares():
    """`fluxcal command state` called every counter but frames_accepted an error: a CAN unit's frames of other nodes
    (no fault: the bus is shared) and a serial unit's bytes were listed as errors. The state's source.counters say
    which count what arrives."""
    from fluxcal.service.wiring.commands.command import state_text

    about = source_kind("can").words().about()
    st = {"unit": "g", "health": {"frames_accepted": 6000, "foreign_frames": 1234, "bad_frames": 3, "seq_gaps": 0,
                                  "read_errors": 0}, "source": {"kind": "can", "protocol": "icd", "counters": about}}
    line = next(x for x in state_text(st).splitlines() if x.startswith("input: "))
    assert line == "input: 6,000 frames accepted, 1,234 foreign frames; bad frames 3"
