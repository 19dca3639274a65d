"""One unit name, one service on a Zenoh network: a service holds `fluxcal/<unit>/holder/<zenoh id>` besides its
`alive` token, looks for another holder before it publishes anything, and watches for one that comes later.

Two services under one name (a copied configuration) interleaved their streams (a subscriber to fluxcal/grad1/raw
saw the sequence go back 256 times in 557 blocks), both obeyed one `freeze`, and the client heard one of them;
nothing was said. Now the second refuses to start, naming the peer that holds the name (or, with
unit.duplicate = "suffix", takes the first free name-2, name-3, ...), and a holder that appears later (two
started at once) is said and counted by both.
"""

from __future__ import annotations

import json
import os
import socket
import threading
import time
from typing import Any

import zenoh

from .keys import Keys

#: how long a starting service waits for another holder's answer (the network's tokens arrive with the session)
LOOK_S = 1.0
#: how many suffixes are tried with unit.duplicate = "suffix"
MAX_SUFFIX = 9


def holder_key(keys: Keys, zid: str = "*") -> str:
    return f"{keys.root}/holder/{zid}"


def holders(session: zenoh.Session, keys: Keys, timeout: float = LOOK_S) -> list[str]:
    """The zenoh ids of the services holding `keys.unit` now (this session's own token included, if declared)."""
    out = []
    for r in session.liveliness().get(holder_key(keys), timeout=timeout):
        if r.ok is not None:
            out.append(str(r.ok.key_expr).rsplit("/", 1)[1])
    for r in session.liveliness().get(keys.alive, timeout=timeout):      # a fluxcal too old to hold a holder token
        if r.ok is not None and not out:
            out.append("?")
    return out


def describe(session: zenoh.Session, keys: Keys, zid: str, timeout: float = LOOK_S) -> str:
    """Who holds the unit's name: the host, process and configuration its state says, and its zenoh id."""
    try:
        for r in session.get(keys.state, timeout=timeout, consolidation=zenoh.ConsolidationMode.NONE):
            if r.ok is None:
                continue
            svc = json.loads(r.ok.payload.to_bytes()).get("service") or {}
            if zid in ("?", str(svc.get("zid", ""))):
                since = time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime(float(svc.get("started_unix_s", 0))))
                return (f"fluxcal on host {svc.get('host', '?')!r} (pid {svc.get('pid', '?')}, configuration "
                        f"{svc.get('config', '?')!r}, zenoh id {svc.get('zid', zid)}, running since {since})")
    except (zenoh.ZError, ValueError, AttributeError, TypeError):
        pass
    return f"a service of zenoh id {zid} (its state did not say more)"


def service_identity(session: zenoh.Session, config: str = "") -> dict[str, Any]:
    """What this service says of itself in its state (`service`): who holds the name, for another that looks."""
    return {"zid": str(session.zid()), "host": socket.gethostname(), "pid": os.getpid(), "config": config,
            "started_unix_s": time.time()}


def free_name(session: zenoh.Session, unit: str, duplicate: str) -> tuple[str, str]:
    """(the name to serve under, what to say): `unit` when no live service holds it; else a BusError naming the
    holder (duplicate = "refuse"), or the first free unit-2 ... unit-9 (duplicate = "suffix")."""
    from .settings import BusError

    keys = Keys(unit)
    held = holders(session, keys)
    if not held:
        return unit, ""
    who = describe(session, keys, held[0])
    if duplicate == "suffix":
        for k in range(2, MAX_SUFFIX + 1):
            name = f"{unit}-{k}"[:64]
            if not holders(session, Keys(name)):
                return name, (f"unit name {unit!r} is held on this network by {who}: serving as {name!r} "
                              f"(unit.duplicate = \"suffix\"); its topics are fluxcal/{name}/...")
    raise BusError(f"unit.name: {unit!r} is already served on this Zenoh network by {who}: a second service "
                   f"under one name would interleave both streams and obey one client's commands twice; give this "
                   f"unit its own name (unit.name), stop the other, or set unit.duplicate = \"suffix\"")


def take_name(bus: Any, zenoh_cfg: Any, duplicate: str) -> None:
    """Serve `bus` (a ServiceBus whose session is open) under its unit's name only if no other live service holds it:
    free_name's answer, with the bus's session opened again for a new name (its access rules name the unit)."""
    name, bus.claim_note = free_name(bus.session, bus.unit, duplicate)
    if name == bus.unit:
        return
    if bus._own_session:
        bus._release()
        bus._hold(zenoh_cfg, name)
    bus.unit, bus.keys = name, Keys(name)


def other_holders(watch: "Watch | None", stats: dict[str, int]) -> list[str]:
    """The zenoh ids of other live services announcing the name `watch` holds; stats["duplicate_holders"]: how
    many appeared since it started."""
    if watch is None:
        return []
    stats["duplicate_holders"] = watch.appeared
    return watch.live_others()


class Watch:
    """This service's holder token, and the other holders that appear while it runs (a liveliness subscriber whose
    callback only notes them: zenoh callbacks never block or call zenoh)."""

    def __init__(self, session: zenoh.Session, keys: Keys) -> None:
        self.zid = str(session.zid())
        self._lock = threading.Lock()
        self.others: dict[str, bool] = {}        # zid -> alive now
        self.appeared = 0                        # other holders seen appear (the bus's stats: duplicate_holders)
        self._token = session.liveliness().declare_token(holder_key(keys, self.zid))
        self._sub = session.liveliness().declare_subscriber(holder_key(keys), self._on_sample, history=True)

    def _on_sample(self, sample: zenoh.Sample) -> None:
        zid = str(sample.key_expr).rsplit("/", 1)[1]
        if zid == self.zid:
            return
        with self._lock:
            alive = sample.kind == zenoh.SampleKind.PUT
            if alive and not self.others.get(zid):
                self.appeared += 1
            self.others[zid] = alive

    def live_others(self) -> list[str]:
        with self._lock:
            return [z for z, alive in self.others.items() if alive]

    def close(self) -> None:
        for ent in (self._sub, self._token):
            try:
                ent.undeclare()
            except zenoh.ZError:
                pass
