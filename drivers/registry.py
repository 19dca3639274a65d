"""Where the kinds of input are found: fluxcal's own declarations (each module of drivers/kinds/ that defines
`KIND`), those of installed packages (the entry-point group `fluxcal.sources`: a SourceKind, or a Protocol whose
`kind` names the kind it adds to), and those code registers (`register_kind`, `register_protocol`: a test's fake
bus, a user's script). Configuration, the daemon, the rate check, the fault watch, the simulator and the docs
(docs/sources.md, `python -m fluxcal.drivers.registry`) read the kinds here; nothing else lists them.

    source_kind(name)       the declaration (a ConfigError naming source.kind and what is allowed)
    kinds()                 every declaration, the default kind first
    allowed()               the kinds' names, quoted and joined, for messages ("allowed: ...")
    transport(name)         the simulator's transport of that name and the kind it feeds
"""

from __future__ import annotations

import dataclasses
import importlib
import pkgutil
import threading
from importlib.metadata import entry_points

from .declare import Protocol, SourceKind, Transport
from .errors import ConfigError

GROUP = "fluxcal.sources"

_lock = threading.Lock()
_kinds: dict[str, SourceKind] = {}
_own: dict[str, SourceKind] = {}          # fluxcal's own, as declared in drivers/kinds/
_found = False


def _find() -> None:
    """fluxcal's own kinds, then the installed packages' (once)."""
    global _found
    with _lock:
        if _found:
            return
        from . import kinds as package

        for info in sorted(pkgutil.iter_modules(package.__path__), key=lambda m: m.name):
            if info.name.startswith("_"):
                continue
            decl = getattr(importlib.import_module(f"{package.__name__}.{info.name}"), "KIND", None)
            if isinstance(decl, SourceKind):
                _own[decl.name] = decl
                _kinds.setdefault(decl.name, decl)
        _found = True
    load_installed()


def load_installed() -> list[str]:
    """Register the kinds and protocols of the installed packages (the entry-point group); a broken one is an error
    that names it. Returns what each entry point added, as `kind` or `kind/protocol`."""
    added = []
    for ep in entry_points(group=GROUP):
        try:
            decl = ep.load()
        except Exception as e:                         # noqa: BLE001 - an installed package's code
            raise ConfigError(f"entry point {GROUP} {ep.name} = {ep.value!r}: loading it raised "
                              f"{type(e).__name__}: {e}") from None
        if isinstance(decl, SourceKind):
            added.append(register_kind(decl).name)
        elif isinstance(decl, Protocol) and decl.kind:
            register_protocol(decl.kind, decl)
            added.append(f"{decl.kind}/{decl.name}")
        else:
            raise ConfigError(f"entry point {GROUP} {ep.name} = {ep.value!r}: not a fluxcal.drivers.declare.SourceKind nor "
                              f"a Protocol naming its kind")
    return added


def kinds() -> list[SourceKind]:
    """Every kind declared: the default kind first, then by name."""
    _find()
    return sorted(_kinds.values(), key=lambda k: (not k.default, k.name))


def allowed() -> str:
    return ", ".join(repr(k.name) for k in kinds())


def source_kind(name: object, key: str = "source.kind") -> SourceKind:
    """The declaration of a kind by its name; a ConfigError naming the key, the value and the kinds allowed."""
    _find()
    decl = _kinds.get(name) if isinstance(name, str) else None
    if decl is None:
        raise ConfigError(f"{key}: {name!r} is not allowed (allowed: {allowed()})")
    return decl


def default_kind() -> SourceKind:
    return kinds()[0]


def register_kind(decl: SourceKind, *, replace: bool = False) -> SourceKind:
    """Declare a kind of your own (docs/sources.md): its name then stands in [source] kind like fluxcal's own."""
    if not isinstance(decl, SourceKind):
        raise ConfigError(f"register_kind: {decl!r} is no fluxcal.drivers.declare.SourceKind")
    if not decl.name or not all(ch.isalnum() or ch in "-_" for ch in decl.name):
        raise ConfigError(f"register_kind: {decl.name!r} is not allowed (allowed: letters, digits, - and _)")
    _find()
    clash = [t.name for t in decl.transports if t.name in _transports() and _transports()[t.name][0] != decl.name]
    if clash:
        raise ConfigError(f"register_kind {decl.name!r}: transport(s) {', '.join(clash)} already declared")
    if decl.default and any(k.default and k.name != decl.name for k in _kinds.values()):
        raise ConfigError(f"register_kind {decl.name!r}: default is not allowed (allowed: one default kind, "
                          f"{default_kind().name!r})")
    for p in decl.protocols or (None,):
        decl.words(p.name if p else "")               # counters named twice: said now, not when it first opens
    with _lock:
        if decl.name in _kinds and not replace and _kinds[decl.name] != decl:
            raise ConfigError(f"register_kind: {decl.name!r} is already declared (factory "
                              f"{_kinds[decl.name].factory!r}); give yours another name")
        _kinds[decl.name] = decl
    return decl


def register_protocol(kind: str, protocol: Protocol, *, replace: bool = False) -> SourceKind:
    """Add a protocol to a declared kind (docs/sources.md): [source] protocol then names it."""
    decl = source_kind(kind, "register_protocol")
    names = [p.name for p in decl.protocols]
    if not decl.protocols:
        raise ConfigError(f"register_protocol: source kind {kind!r} takes no protocols")
    if protocol.name in names and not replace:
        if protocol in decl.protocols:
            return decl                                # the same declaration again (an entry point loaded twice)
        raise ConfigError(f"register_protocol: {kind!r} already has protocol {protocol.name!r}")
    kept = tuple(p for p in decl.protocols if p.name != protocol.name)
    new = dataclasses.replace(decl, protocols=kept + (protocol,))
    new.words(protocol.name)
    with _lock:
        _kinds[kind] = new
    return new


def forget_kind(name: str) -> None:
    """Undo register_kind (a test's fake kind, at its end): fluxcal's own kind of that name, if any, is back."""
    with _lock:
        if name in _own:
            _kinds[name] = _own[name]
        else:
            _kinds.pop(name, None)


def forget_protocol(kind: str, name: str) -> None:
    """Undo register_protocol: the kind as it was declared, but for the other protocols added since."""
    decl = source_kind(kind, "forget_protocol")
    own = {p.name: p for p in _own[kind].protocols} if kind in _own else {}
    kept = tuple(own.get(p.name, p) for p in decl.protocols if p.name != name or p.name in own)
    with _lock:
        _kinds[kind] = dataclasses.replace(decl, protocols=kept)


def _transports() -> dict[str, tuple[str, Transport]]:
    return {t.name: (k.name, t) for k in sorted(_kinds.values(), key=lambda k: (not k.default, k.name))
            for t in k.transports}


def transports() -> list[tuple[SourceKind, Transport]]:
    """Every transport of the simulated unit, with the kind it feeds: the default kind's first."""
    return [(k, t) for k in kinds() for t in k.transports]


def transport(name: object, key: str = "source.transport") -> tuple[SourceKind, Transport]:
    for k, t in transports():
        if t.name == name:
            return k, t
    raise ConfigError(f"{key}: {name!r} is not allowed (allowed: {', '.join(repr(t.name) for _, t in transports())})")


def _keys(decl: SourceKind) -> list[str]:
    rows = []
    for f in dataclasses.fields(decl.table_class()):
        if f.name in ("kind", "protocol"):
            continue
        default = ("required" if f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING
                   else repr(f.default) if f.default is not dataclasses.MISSING else "")
        rows.append(f"| `{f.name}` | {default} | {f.metadata.get('doc', '')} |".replace("|axis|", "\\|axis\\|"))
    return ["| key | default | what |", "| --- | --- | --- |"] + rows if rows else []


def _counters(counted) -> list[str]:
    return [f"- `{c.name}`: {c.doc}" + (f"; said as {c.label!r} (`faults.{c.fault}`)" if c.fault else "")
            for c in counted]


def markdown() -> str:
    """Every kind declared, as docs/sources.md shows them (`python -m fluxcal.drivers.registry` prints it)."""
    out = []
    for k in kinds():
        out += [f"### `{k.name}`", "", k.doc[:1].upper() + k.doc[1:] + ".", ""]
        clock = "the unit's own clock (the configured rate is checked against it)" if k.unit_clock else \
            "no unit clock: t_s = seq / rate_hz"
        rate = "source.rate_hz or [sim] rate_hz required" if k.needs_rate else "the rate from its own table or [sim]"
        out += [f"Time: {clock}; rate: {rate}." + (f" Opening it names {', '.join(k.port_keys)}." if k.port_keys
                                                    else ""), ""]
        out += _keys(k) + ([""] if _keys(k) else [])
        if k.counters:
            out += ["Its counters:", ""] + _counters(k.counters) + [""]
        for p in k.protocols:
            first = " (the default)" if p is k.protocols[0] else ""
            out += [f"Protocol `{p.name}`{first}: {p.doc}.", ""] + _counters(p.counters) + [""]
        for t in k.transports:
            out += [f"Simulator transport `{t.name}`: {t.doc}" + (" (also for another process)" if t.process else "")
                    + ".", ""]
    return "\n".join(out).rstrip() + "\n"


if __name__ == "__main__":
    print(markdown(), end="")
