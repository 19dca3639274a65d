"""What the web dashboard knows of one unit, updated from bus messages and state replies, and served to
the page as JSON. No I/O here: the hub feeds it, the HTTP server reads it (under the hub's lock).
"""

from __future__ import annotations

import math
import time
from collections import deque
from collections.abc import Callable
from typing import Any

import numpy as np

from fluxcal.service.io.bus import Message
from fluxcal.service.numerics.calib.coverage import BIN_CENTRES, BIN_LABELS, coverage
from fluxcal.service.numerics.decimate import RmsMeans, VectorMeans
from fluxcal.service.numerics.outputs import CorrectedBlock

from ..commands.client import DATA_STREAMS, flow
from .history import HISTORY, PERIOD_S, WINDOW_S, Floors, RawKeep, Ring, WindowMeans, corrected_columns, corrected_row

#: a unit that sent nothing for this long is shown as silent
#: field directions kept for the coverage sphere (10 Hz means: ten minutes)
COVERAGE_POINTS = 6000
#: directions of the trail drawn on the sphere
TRAIL = 200
#: fault events kept (the health channel carries the newest ten; this page keeps more)
FAULT_EVENTS = 100


def _interval_start(t_s: float) -> float:
    """The start of the 0.1-s interval of unit time that holds t_s: where the page plots its mean."""
    return math.floor(t_s / PERIOD_S + 1e-9) * PERIOD_S


def sensor_scales(probe: dict[str, Any]) -> tuple[list[float] | None, str]:
    """(the sensor's scale factor per axis, where it comes from) of one probe of a unit's state: "scale" means the
    sensor's (1.021 where it reads 2.1 % high), as `fit` prints it, never the correction matrix's diagonal (0.979).
    The calibration's params["scale"] where it has one; else fluxcal.service.numerics.calib.model.sensor_scale of its
    matrix (the row norms of M⁻¹, whatever rotation an alignment put in M).

    >>> m = [[1 / 1.021, 0.001, 0.0], [0.0, 1 / 0.99, 0.0], [0.0, 0.0, 1.0]]
    >>> [round(c, 4) for c in sensor_scales({"matrix": m})[0]], sensor_scales({"matrix": m})[1]
    ([1.021, 0.99, 1.0], 'from the matrix')
    """
    from fluxcal.service.numerics.calib.model import sensor_scale

    sc = (probe.get("params") or {}).get("scale")
    if isinstance(sc, dict) and np.size(sc.get("value")) == 3:
        return [float(x) for x in np.ravel(sc["value"])], "the calibration's"
    try:
        scale = sensor_scale(np.asarray(probe.get("matrix"), dtype=np.float64).reshape(3, 3))
        return [float(c) for c in scale], "from the matrix"
    except (TypeError, ValueError, np.linalg.LinAlgError):
        return None, "not determined"


def _finite(x: Any) -> Any:
    if isinstance(x, float) and not math.isfinite(x):
        return None
    if isinstance(x, dict):
        return {k: _finite(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_finite(v) for v in x]
    return x


class UnitView:
    """One unit: decimated history of its products, coverage, calibration and its history, health, the
    gate's reasons, the commands sent from this dashboard, the last diagnosis."""

    def __init__(self, unit: str, clock: Callable[[], float] = time.monotonic) -> None:
        self.unit = unit
        self.clock = clock
        self.alive: bool | None = None
        self.last_msg_t: float | None = None
        self.last_data_t: float | None = None     # the newest samples (DATA_STREAMS): what says the input flows
        self.n_messages = 0
        self.probe_names: list[str] = []
        self.means = VectorMeans(PERIOD_S)
        self.raw_means = VectorMeans(PERIOD_S)
        self.error_means = RmsMeans(PERIOD_S)
        self.series: Ring | None = None
        self.raw_series: Ring | None = None
        self.error = Ring(["t_s"], HISTORY)
        self.error_names: list[str] = []
        self.error_window = WindowMeans(WINDOW_S)                  # mean squares of the error over WINDOW_S
        self.diff_window = WindowMeans(WINDOW_S)                   # mean difference components over WINDOW_S
        self.floors = Floors()
        self.raw_keep = RawKeep()
        self.directions: deque[np.ndarray] = deque(maxlen=COVERAGE_POINTS)   # (P, 3) raw means
        self.state: dict[str, Any] = {}
        self.cal_history: list[dict[str, Any]] = []
        self.events: deque[dict[str, Any]] = deque(maxlen=50)
        self.commands: deque[dict[str, Any]] = deque(maxlen=50)
        self.health: dict[str, Any] = {}
        self.fault_events: deque[dict[str, Any]] = deque(maxlen=FAULT_EVENTS)   # losses and faults the service said
        self._fault_n = 0                 # the newest fault event kept (numbered by the service)
        self.diagnosis: dict[str, Any] = {"status": "none"}
        self._coverage: dict[str, Any] | None = None
        self._coverage_t = -math.inf

    # --- updates ------------------------------------------------------------------------------

    def _names(self, n: int) -> list[str]:
        return self.probe_names if len(self.probe_names) == n else [f"s{k + 1}" for k in range(n)]

    def update(self, msg: Message) -> None:
        self.last_msg_t = self.clock()
        if msg.stream in DATA_STREAMS:
            self.last_data_t = self.last_msg_t
        self.n_messages += 1
        v = msg.value
        if msg.stream == "corrected":
            self._corrected(v)
        elif msg.stream == "raw":
            self._raw(v)
        elif msg.stream == "error":
            t, n = v.get("t_s"), v.get("n")
            if not isinstance(t, (int, float)):              # a service that sends none: the newest interval's
                t = self.means.bin * PERIOD_S
            for rec in self.error_means.add(v.get("rms_nT") or {}, t_s=float(t), seq=v.get("seq"),
                                            n=int(n) if isinstance(n, int) else 1):
                rms = rec["rms_nT"]
                if list(rms) != self.error_names:
                    self.error_names = list(rms)
                    self.error = Ring(["t_s", *self.error_names], HISTORY)
                values = np.array([rms[c] for c in self.error_names], dtype=np.float64)
                self.error.append(_interval_start(rec["t_s"]), values)
                self.error_window.add(rec["t_s"], rec.get("n", 1), values ** 2,
                                      key=(tuple(self.error_names), self.state.get("cal_id")))
        elif msg.stream == "health":
            self.health = v
            self._faults(v.get("faults"))
        elif msg.stream == "calibration":
            ev = {k: v.get(k) for k in ("kind", "seq", "t_s", "time_unix_s", "reasons", "command", "ok", "error",
                                        "cal_id") if k in v}
            self.events.append(ev)
            if isinstance(v.get("state"), dict):
                self.update_state(v["state"])

    def _corrected(self, block: Any) -> None:
        names = self._names(block.n_probes)
        for rec in self.means.add(block):
            norm = None
            if rec["diff"] is not None:
                m = self.diff_window.add(rec["t_s"], rec["n"], rec["diff"][0].ravel(), key=rec["cal_id"])
                norm = np.linalg.norm(m.reshape(-1, 3), axis=1)
            row = corrected_row(rec, norm)
            if self.series is None or len(self.series.columns) != row.size + 1:
                self.series = Ring(["t_s", *corrected_columns(names, rec)])
            self.series.append(_interval_start(rec["t_s"]), row)
        self.floors.add(block, names)

    def _raw(self, block: Any) -> None:
        self.raw_keep.add(block)
        # the raw vectors through the same interval means (as a block of "corrected" vectors, calibration 0)
        as_vectors = CorrectedBlock(block.t_s, block.seq, block.field_nT, None, None, None, 0)
        for rec in self.raw_means.add(as_vectors):
            if self.raw_series is None or len(self.raw_series.columns) != rec["mean"].size + 1:
                names = self._names(rec["mean"].shape[0])
                self.raw_series = Ring(["t_s", *[f"{p}.{a}" for p in names for a in "xyz"]])
                self.directions.clear()
            self.raw_series.append(_interval_start(rec["t_s"]), rec["mean"].ravel())
            self.directions.append(rec["mean"])

    def update_state(self, st: dict[str, Any]) -> None:
        prev = self.state.get("cal_id")
        self.state = {**self.state, **st}
        names = st.get("probe_names") or [p.get("name") for p in st.get("probes") or [] if isinstance(p, dict)]
        if names and all(isinstance(n, str) for n in names):
            self.probe_names = list(names)
        if isinstance(st.get("health"), dict) and not self.health:
            self.health = {"counters": st["health"]}
        self._faults(st.get("faults"))
        if st.get("probes") and st.get("cal_id") != prev:
            self.cal_history.append({"time_unix_s": time.time(), "cal_id": st.get("cal_id"),
                                     "offset_nT": [p.get("offset_nT") for p in st["probes"]],
                                     "offset_se_nT": [p.get("offset_se_nT") for p in st["probes"]]})
            del self.cal_history[:-200]

    def _faults(self, faults: Any) -> None:
        """Keep the fault events of a health message (or a state reply) not kept yet: the service numbers them,
        and a service that started again numbers from 1."""
        if not isinstance(faults, dict):
            return
        n_events = faults.get("n_events")
        if isinstance(n_events, int) and n_events < self._fault_n:
            self._fault_n = 0                 # the service started again
        for ev in faults.get("events") or []:
            n = ev.get("n") if isinstance(ev, dict) else None
            if isinstance(n, int) and n > self._fault_n:
                self.fault_events.append({k: ev.get(k) for k in ("n", "kind", "phase", "count", "text", "time_unix_s")})
                self._fault_n = n

    def faults_view(self) -> dict[str, Any]:
        """The faults panel: what goes on now, every kind's total, the events (newest last), the summary at stop."""
        f = (self.health or {}).get("faults")
        if not isinstance(f, dict):
            f = self.state.get("faults") if isinstance(self.state.get("faults"), dict) else {}
        return {"active": list(f.get("active") or []), "totals": dict(f.get("totals") or {}),
                "events": list(self.fault_events), "summary": list(f.get("summary") or [])}

    # --- what the page reads --------------------------------------------------------------------

    def status(self) -> tuple[str, str]:
        """(kind, sentence): live, silent (the service heard, its samples not: the active faults said), stopped (token
        gone), waiting (never heard); as `fluxcal watch` says it (commands.client.flow)."""
        return flow(self.unit, self.clock(), self.last_msg_t, self.last_data_t, self.alive, self.health)

    def coverage_view(self, every_s: float = 2.0) -> dict[str, Any] | None:
        """Per probe: the 26 direction bins' counts, the share seen, what is missing and which turn fills it;
        directions of the raw 10 Hz means about the calibration's offsets (zero before one is usable)."""
        now = self.clock()
        if now - self._coverage_t < every_s or not self.directions:
            return self._coverage
        self._coverage_t = now
        d = np.array(self.directions)                                          # (M, P, 3)
        offsets = [p.get("offset_nT") for p in self.state.get("probes") or []]
        probes = []
        for k, name in enumerate(self._names(d.shape[1])):
            off = np.asarray(offsets[k], float) if k < len(offsets) and offsets[k] is not None else None
            cov = coverage(d[:, k, :], centre_nT=off)
            u = d[-TRAIL:, k, :] - (0.0 if off is None else off)
            u = u / np.maximum(np.linalg.norm(u, axis=1, keepdims=True), 1e-12)
            probes.append({"name": name, "fraction": cov.fraction, "counts": cov.counts.tolist(),
                           "min_count": cov.min_count, "missing": cov.missing, "advice": cov.advice(),
                           "usable": cov.usable, "reason": cov.reason, "trail": np.round(u, 3).tolist()})
        self._coverage = {"bins": np.round(BIN_CENTRES, 4).tolist(), "labels": BIN_LABELS,
                          "frame": "probe frame, raw field about the calibration's offsets",
                          "n_directions": int(d.shape[0]), "probes": probes}
        return self._coverage

    def windows(self) -> dict[str, Any]:
        """The error table's figures: each channel's RMS over the last WINDOW_S of unit time (the root of the mean
        square, weighted by samples), and the unit time each average covers now."""
        ms = self.error_window.mean()
        rms = {} if ms is None else {c: float(np.sqrt(x)) for c, x in zip(self.error_names, ms)}
        return {"window_s": WINDOW_S, "error_rms_nT": rms, "error_span_s": round(self.error_window.span_s, 2),
                "diff_span_s": round(self.diff_window.span_s, 2)}

    def view(self, since: dict[str, int]) -> dict[str, Any]:
        """The JSON the page polls: rows of each history after the numbers it already has, and the rest whole."""
        kind, sentence = self.status()
        series = self.series.since(since.get("series", 0)) if self.series else None
        raw = self.raw_series.since(since.get("raw", 0)) if self.raw_series else None
        return _finite({
            "unit": self.unit, "status": kind, "status_text": sentence, "n_messages": self.n_messages,
            "probe_names": self.probe_names, "series": series, "raw": raw,
            "error": self.error.since(since.get("error", 0)), "floors": self.floors.floors(),
            "coverage": self.coverage_view(), "state": self.state, "cal_history": self.cal_history,
            "events": list(self.events), "commands": list(self.commands), "health": self.health,
            "faults": self.faults_view(),
            "diagnosis": self.diagnosis, "raw_kept": {"samples": self.raw_keep.n}, "windows": self.windows(),
            "sensor_scales": [{"name": p.get("name"), "scale": sc, "source": src}
                              for p in self.state.get("probes") or [] if isinstance(p, dict)
                              for sc, src in [sensor_scales(p)]],
        })
