"""The declarations of the kinds of input and where they are found (fluxcal.drivers.declare, fluxcal.drivers.registry, issue 41):
a declaration that cannot stand is refused when it is registered, naming what is wrong; an installed package's
entry point adds a kind or a protocol; a source's counters are exactly its declaration's; the simulator's
transports come from the kinds that read them."""

from __future__ import annotations

import pickle
import subprocess
import sys
from dataclasses import dataclass
from types import SimpleNamespace

import pytest

from fluxcal.drivers.config import spec
from fluxcal.drivers.declare import Counted, Protocol, SourceKind, SourceTable, Transport, Words
from fluxcal.drivers.errors import ConfigError
from fluxcal.drivers.registry import (
    default_kind,
    forget_kind,
    forget_protocol,
    kinds,
    load_installed,
    register_kind,
    register_protocol,
    source_kind,
    transport,
    transports,
)
from fluxcal.drivers.source import Counters
from fluxcal.service.wiring.config import config_from_dict

#: fluxcal's own declarations, found and read here (their words are said in tests/wiring/test_source_kinds.py)
COVERS = ("fluxcal.drivers.kinds._icd", "fluxcal.drivers.kinds.can", "fluxcal.drivers.kinds.replay", "fluxcal.drivers.kinds.serial",
          "fluxcal.drivers.kinds.sim")


@dataclass(kw_only=True)
class PlainTable(SourceTable):
    rate_hz: float = spec(10.0)


PLAIN = SourceKind("plain", "a kind with no protocol", config=PlainTable, factory=lambda cfg: cfg,
                   counters=(Counted("things", "things seen", decoded=True, what="{n:,} thing(s)"),))


@pytest.fixture
def restored():
    yield
    forget_kind("plain")
    forget_kind("other")
    forget_protocol("can", "extra")


def test_the_kinds_and_transports_are_fluxcals_own_found_in_drivers_kinds():
    assert [k.name for k in kinds()] == ["sim", "can", "replay", "serial"] and default_kind().name == "sim"
    assert [(k.name, t.name) for k, t in transports()] == [("sim", "direct"), ("can", "can-virtual"),
                                                            ("can", "slcan"), ("serial", "pty")]
    with pytest.raises(ConfigError, match=r"source.transport: 'usb' is not allowed \(allowed: 'direct', "
                                          r"'can-virtual', 'slcan', 'pty'\)"):
        transport("usb")
    with pytest.raises(ConfigError, match=r"source.kind: 7 is not allowed \(allowed: 'sim', 'can', 'replay', "
                                          r"'serial'\)"):
        source_kind(7)


def test_a_declaration_that_cannot_stand_is_refused_naming_why(restored):
    twice = (Counted("n", "a"), Counted("n", "b"))
    with pytest.raises(ConfigError, match=r"counters n declared twice for one input"):
        register_kind(SourceKind("plain", "x", config=PlainTable, factory=print, counters=twice))
    assert "plain" not in [k.name for k in kinds()]
    with pytest.raises(ConfigError, match=r"register_kind: 'a b' is not allowed"):
        register_kind(SourceKind("a b", "x", config=PlainTable, factory=print))
    with pytest.raises(ConfigError, match=r"register_kind: 'serial' is already declared"):
        register_kind(SourceKind("serial", "x", config=PlainTable, factory=print))
    with pytest.raises(ConfigError, match=r"transport\(s\) pty already declared"):
        register_kind(SourceKind("other", "x", config=PlainTable, factory=print, transports=(Transport("pty", "x"),)))
    with pytest.raises(ConfigError, match=r"default is not allowed \(allowed: one default kind, 'sim'\)"):
        register_kind(SourceKind("other", "x", config=PlainTable, factory=print, default=True))
    with pytest.raises(ConfigError, match=r"register_protocol: source kind 'sim' takes no protocols"):
        register_protocol("sim", Protocol("extra", "x"))
    with pytest.raises(ConfigError, match=r"register_protocol: 'can' already has protocol 'icd'"):
        register_protocol("can", Protocol("icd", "x"))
    register_kind(PLAIN)
    assert register_kind(PLAIN) is PLAIN                            # the same declaration again: no error
    with pytest.raises(ConfigError, match=r"source.protocol: unknown key \(allowed: kind, rate_hz\)"):
        config_from_dict({"source": {"kind": "plain", "protocol": "icd"}})
    with pytest.raises(ConfigError, match=r"source.protocol: 'icd' is not allowed \(allowed: none: source kind "
                                          r"'plain' has no protocols\)"):
        PLAIN.protocol("icd")
    with pytest.raises(ConfigError, match=r"its config .* is no dataclass deriving fluxcal.drivers.declare.SourceTable"):
        register_kind(SourceKind("other", "x", config=dict, factory=print)).load({})


def test_an_installed_package_adds_a_kind_and_a_protocol(restored, monkeypatch):
    extra = Protocol("extra", "another way of framing", decoder="fluxcal.drivers.can_source:CanIcd", kind="can")
    points = [SimpleNamespace(name="plain", value="pkg:PLAIN", load=lambda: PLAIN),
              SimpleNamespace(name="extra", value="pkg:EXTRA", load=lambda: extra)]
    monkeypatch.setattr("fluxcal.drivers.registry.entry_points", lambda group: points if group == "fluxcal.sources" else [])
    assert load_installed() == ["plain", "can/extra"] and load_installed() == ["plain", "can/extra"]
    cfg = config_from_dict({"unit": {"n_probes": 2}, "source": {"kind": "can", "protocol": "extra", "channel": "x",
                                                                "n_probes": 2, "rate_hz": 100.0}})
    assert (cfg.source.kind, cfg.source.protocol, cfg.calibration.file) == ("can", "extra", "state/unit1-can-cal.json")
    assert config_from_dict({"source": {"kind": "plain"}}).source.rate_hz == 10.0
    bad = [SimpleNamespace(name="bad", value="pkg:BAD", load=lambda: "not a kind")]
    monkeypatch.setattr("fluxcal.drivers.registry.entry_points", lambda group: bad)
    with pytest.raises(ConfigError, match=r"entry point fluxcal.sources bad = 'pkg:BAD': not a "
                                          r"fluxcal.drivers.declare.SourceKind nor a Protocol naming its kind"):
        load_installed()


def test_a_sources_counters_are_its_declarations_and_no_other():
    words = source_kind("serial").words()
    c = Counters.of(words)
    assert list(c.as_dict()) == list(words.names) and c.words == words and not any(c.as_dict().values())
    c.crc_failures += 3
    with pytest.raises(AttributeError):
        c.bad_frames += 1                                           # a CAN counter: not the serial unit's
    again = pickle.loads(pickle.dumps(c))
    assert again.as_dict() == c.as_dict() and type(again) is type(c)
    assert type(Counters.of(Words(words.counted, words.no_decode))) is type(c)     # one class per declaration
    assert Counters.of(Words(())).as_dict() == {}


def test_the_simulators_transports_are_the_kinds_own(tmp_path):
    """`python -m fluxcal.drivers.sim` serves the transports that can reach another process, by the name their kind gives."""
    out = subprocess.run([sys.executable, "-m", "fluxcal.drivers.sim", "--help"], capture_output=True, text=True, timeout=60)
    assert "--transport{slcan,pty}" in out.stdout.replace("\n", "").replace(" ", "")
    with pytest.raises(ConfigError, match=r"source.transport: 'usb' is not allowed"):
        config_from_dict({"source": {"kind": "sim", "transport": "usb"}})
    assert config_from_dict({"source": {"kind": "sim"}}).source.transport == "direct"
