"""The dashboard's Zenoh side: one client session, one lossy subscription per unit (it never holds a unit
back), liveliness, state queries every 2 s, commands on request, and a diagnosis of the kept raw samples
on request (in the dashboard's process, never the unit's). One thread feeds the views; readers take
`lock`.
"""

from __future__ import annotations

import json
import threading
import time
from dataclasses import dataclass
from typing import Any

import numpy as np
import zenoh

from fluxcal.drivers.errors import ConfigError, FluxcalError
from fluxcal.service.io.bus import BusClient, BusError, Keys, ZenohConfig, ZenohTlsConfig, discover_units, open_session

from .view import UnitView


@dataclass(frozen=True)
class Geometry:
    """A unit's probe positions (P, 3) m and total field nT as its configuration gives them (None: not given),
    and where from."""

    positions_m: np.ndarray | None
    total_nT: float | None
    source: str


#: what the dashboard subscribes to: `corrected` carries the differences, centre and tensor too
STREAMS = ("raw", "corrected", "calibration", "health", "error")
STATE_EVERY_S = 2.0
DISCOVER_EVERY_S = 2.0


class Hub:
    """Connects, follows the named units (or every unit it discovers) and keeps a UnitView of each."""

    def __init__(self, endpoints: list[str], units: list[str] | None, tls: ZenohTlsConfig | None = None,
                 geometry: dict[str, Geometry] | None = None) -> None:
        self.endpoints = endpoints
        #: per unit, what its configuration says of the probe positions and the total field (the diagnosis needs
        #: them; a unit's state does not carry them): `fluxcal dashboard --config` gives its unit's
        self.geometry = dict(geometry or {})
        self.named = list(units) if units else None
        self.tls = tls
        self.lock = threading.Lock()
        self.views: dict[str, UnitView] = {u: UnitView(u) for u in (self.named or [])}
        self.connected = False
        self.connect_error = ""
        self.session: zenoh.Session | None = None
        self._clients: dict[str, BusClient] = {}
        self._alive_sub: Any = None
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="fluxcal-dashboard-hub", daemon=True)
        self._state_q: dict[str, Any] = {}
        self._next_state: dict[str, float] = {}

    def start(self) -> Hub:
        self._thread.start()
        return self

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=5.0)
        for c in self._clients.values():
            c.close()
        for closer in (getattr(self._alive_sub, "undeclare", None), getattr(self.session, "close", None)):
            if closer is not None:
                try:
                    closer()
                except zenoh.ZError:
                    pass

    # --- the loop ---------------------------------------------------------------------------------

    def _run(self) -> None:
        next_connect = next_discover = 0.0
        while not self._stop.is_set():
            now = time.monotonic()
            if self.session is None and now >= next_connect:
                try:
                    self.session = open_session(ZenohConfig.client(*self.endpoints, tls=self.tls))
                    self._alive_sub = self.session.liveliness().declare_subscriber(
                        "fluxcal/*/alive", zenoh.handlers.RingChannel(256), history=True)
                    self.connected, self.connect_error = True, ""
                except BusError as e:
                    self.connect_error = str(e)
                    next_connect = now + 1.0
            if self.session is not None:
                if self.named is None and now >= next_discover:
                    next_discover = now + DISCOVER_EVERY_S
                    for u in discover_units(self.session, timeout=0.3):
                        with self.lock:
                            self.views.setdefault(u, UnitView(u))
                for u in list(self.views):
                    if u not in self._clients:
                        self._clients[u] = BusClient(self.session, u, streams=STREAMS, lossless=False, capacity=256)
                self._liveliness()
                self._poll_states(now)
                self._drain()
            self._stop.wait(0.05)

    def _liveliness(self) -> None:
        while True:
            try:
                s = self._alive_sub.try_recv()
            except zenoh.ZError:
                return
            if s is None:
                return
            parts = str(s.key_expr).split("/")
            if len(parts) == 3 and parts[1] in self.views:
                with self.lock:
                    self.views[parts[1]].alive = s.kind == zenoh.SampleKind.PUT

    def _poll_states(self, now: float) -> None:
        for u in self.views:
            q = self._state_q.get(u)
            if q is None and now >= self._next_state.get(u, 0.0):
                self._state_q[u] = self.session.get(Keys(u).state, timeout=1.5)
                self._next_state[u] = now + STATE_EVERY_S
                continue
            if q is None:
                continue
            try:
                reply = q.try_recv()
            except zenoh.ZError:
                self._state_q[u] = None
                continue
            if reply is None:
                continue
            self._state_q[u] = None
            if reply.ok is not None:
                try:
                    st = json.loads(reply.ok.payload.to_bytes())
                except ValueError:
                    continue
                with self.lock:
                    self.views[u].update_state(st)

    def _drain(self) -> None:
        for u, c in self._clients.items():
            msgs = c.drain()
            if msgs:
                with self.lock:
                    view = self.views[u]
                    for m in msgs:
                        view.update(m)

    # --- what the page asks for -------------------------------------------------------------------

    def units(self) -> dict[str, Any]:
        with self.lock:
            units = [{"unit": u, "status": v.status()[0], "status_text": v.status()[1]} for u, v in self.views.items()]
        where = ", ".join(self.endpoints)
        message = ("" if self.connected else f"cannot reach {where}: is `fluxcal run` running and listening there? "
                   f"(retrying every second) {self.connect_error}".strip())
        if self.connected and not units:
            message = f"no fluxcal unit visible via {where} yet: is `fluxcal run` running?"
        return {"connected": self.connected, "endpoints": self.endpoints, "units": units, "message": message}

    def view(self, unit: str, since: dict[str, int]) -> dict[str, Any]:
        with self.lock:
            v = self.views.get(unit)
            if v is None:
                raise KeyError(unit)
            return v.view(since)

    def command(self, unit: str, name: str, payload: str = "", timeout: float = 5.0) -> dict[str, Any]:
        """Send a command; its answer (or why there is none) is returned and kept in the unit's log."""
        if unit not in self.views:
            raise KeyError(unit)
        client = self._clients.get(unit)
        sent = time.time()
        try:
            if client is None:
                raise BusError(f"not connected to {', '.join(self.endpoints)}")
            answer = client.command(name, payload, timeout=timeout)
        except (BusError, ConfigError) as e:
            answer = {"ok": False, "error": str(e)}
        entry = {"time_unix_s": sent, "command": name, "payload": payload[:200], **answer,
                 "round_trip_s": round(time.time() - sent, 4)}
        with self.lock:
            self.views[unit].commands.append(entry)
        self._next_state[unit] = 0.0                       # show the command's effect at once
        return entry

    def calibration_file(self, unit: str) -> dict[str, Any]:
        """The calibration the unit uses now, as a calibration file that `apply` takes back (calibration_file)."""
        with self.lock:
            st = dict(self.views[unit].state)
        return calibration_file(unit, st)

    def discovered_effect(self, unit: str) -> str:
        """The effect module the unit's last diagnosis discovered (KeyError: a unit not followed)."""
        with self.lock:
            return discovered_effect(self.views[unit])

    def diagnose(self, unit: str) -> dict[str, Any]:
        """Start a diagnosis of the unit's kept raw samples on a thread of this process; returns at once."""
        with self.lock:
            view = self.views[unit]
            if view.diagnosis.get("status") == "running":
                return view.diagnosis
            block = view.raw_keep.block()
            names = list(view.probe_names) or None
            effects = list(view.state.get("effects") or [])
            view.diagnosis = {"status": "running", "started_unix_s": time.time(), "fraction": 0.0}
        threading.Thread(target=run_diagnosis, args=(view, unit, block, names, effects, self.geometry.get(unit)),
                         daemon=True, name=f"fluxcal-dashboard-diagnose-{unit}").start()
        return {"status": "running"}


def run_diagnosis(view: UnitView, unit: str, block: Any, names: list[str] | None, effects: list[str],
                  geometry: Geometry | None = None) -> None:
    """A diagnosis of the kept raw samples (fluxcal.service.numerics.diagnose) with the unit's configured probe positions
    and total field where the dashboard has them; its result or failure put in the view."""
    from fluxcal.service.numerics.diagnose import diagnose, summary_text
    from fluxcal.service.numerics.effects.base import EffectData

    try:
        if block is None or block.n_samples < 200:
            raise FluxcalError(f"only {0 if block is None else block.n_samples} raw samples kept so far: "
                               f"wait for more data")
        positions = None if geometry is None else geometry.positions_m
        if positions is not None and positions.shape[0] != block.n_probes:
            raise FluxcalError(f"{geometry.source} gives {positions.shape[0]} probe positions but fluxcal/{unit} "
                               f"sends {block.n_probes} probes: is it this unit's configuration?")
        data = EffectData.from_block(block, names, total_nT=None if geometry is None else geometry.total_nT,
                                     positions_m=positions)
        if geometry is None:
            given = (f"no configuration of fluxcal/{unit} given to this dashboard (`fluxcal dashboard --config "
                     f"FILE` of the unit's service): no probe positions, no total field")
        else:
            given = (f"from {geometry.source}: " + ", ".join(
                ([f"probe positions of {positions.shape[0]} probes"] if positions is not None else
                 ["no probe positions"]) + ([f"total field {geometry.total_nT:,.0f} nT"]
                                            if geometry.total_nT is not None else ["no total field"])))

        def progress(fraction: float, *_: Any) -> None:
            view.diagnosis = {**view.diagnosis, "fraction": float(fraction)}

        result = diagnose(data, effects=effects, progress=progress)
        out = result.as_dict()
        found = getattr(result, "discovery", None)
        effect = None
        if found is not None and found.claimed:
            from fluxcal.service.numerics.diagnose.write_effect import effect_source

            effect = effect_source(found, data_name=f"fluxcal/{unit}, last {block.n_samples} samples")
        view.diagnosis = {"status": "done", "finished_unix_s": time.time(), "n_samples": int(block.n_samples),
                          "duration_s": float(block.t_s[-1] - block.t_s[0]), "effects": effects,
                          "verdict": out.get("verdict"), "candidates": out.get("candidates"), "given": given,
                          "discovery": None if found is None else {
                              "claimed": bool(found.claimed), "sentence": found.sentence(),
                              # what the page draws of each law found (shape_reading.partial_residual)
                              "shapes": [{"observable": g.group.feature.observable, "unit": g.group.feature.unit,
                                          "law": g.parts.get("law"), "partial": g.parts["partial"]}
                                         for g in (found.groups if found.claimed else [])
                                         if g.parts.get("partial")]},
                          "effect_module": effect,
                          "text": summary_text(result, f"fluxcal/{unit}, last {block.n_samples} samples")}
    except (FluxcalError, ValueError, np.linalg.LinAlgError) as e:
        view.diagnosis = {"status": "failed", "error": str(e)}


def discovered_effect(view: UnitView) -> str:
    """The effect module the last diagnosis discovered (diagnose --write-effect's text); FluxcalError when none."""
    text = (view.diagnosis or {}).get("effect_module")
    if not text:
        raise FluxcalError("no term discovered beyond the catalogue in the last diagnosis: nothing to write")
    return text


def calibration_file(unit: str, st: dict[str, Any]) -> dict[str, Any]:
    """A unit's state as a calibration file (fluxcal.service.io.calfile); FluxcalError when it has no usable calibration
    yet, or corrects effects whose parameters the state does not carry."""
    from fluxcal.service.io.calfile import calibration_to_dict
    from fluxcal.service.numerics.calib.model import ArrayCalibration, ProbeCalibration

    if not st.get("usable") or not st.get("probes"):
        raise FluxcalError(f"fluxcal/{unit} has no usable calibration yet")
    if st.get("effects"):
        raise FluxcalError(f"fluxcal/{unit} corrects effects too ({', '.join(st['effects'])}), whose parameters its "
                           f"state does not carry: take the service's own calibration file ([calibration] file)")

    def se(x: Any, shape: tuple[int, ...]) -> np.ndarray:
        """A standard error from the state: null or -1 (the state's "not determined") -> NaN."""
        a = np.full(shape, np.nan) if x is None else np.array(x, dtype=float).reshape(shape)
        return np.where(a < 0, np.nan, a)

    probes = [ProbeCalibration(str(p["name"]), np.asarray(p["offset_nT"], float), np.asarray(p["matrix"], float),
                               se(p.get("offset_se_nT"), (3,)), se(p.get("matrix_se"), (3, 3)))
              for p in st["probes"]]
    span = st.get("span") or (0.0, 0.0, 0)
    cal = ArrayCalibration(str(st.get("method") or "rls"), st.get("align"), probes, total_nT=st.get("total_nT"),
                           span=(float(span[0]), float(span[1]), int(span[2])),
                           diagnostics={"saved_from": f"fluxcal/{unit} by fluxcal dashboard, cal_id {st.get('cal_id')}"})
    return calibration_to_dict(cal)
