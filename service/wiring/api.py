"""The Python API (`import fluxcal`, docs/python.md): read any input the command line reads into one data object, fit
and diagnose it, replay a recording, simulate a unit, and get back the very Results the commands print; the command
line is built on these functions (`fluxcal fit FILE` is `fit(FILE, ...)`), never beside them.

    >>> import fluxcal
    >>> data = fluxcal.read("recordings/grad1-sim-30s.mcap")
    >>> data.probe_names, data.n_samples
    (['s1', 's2'], 6000)
    >>> result = fluxcal.fit(data)
    >>> round(result.rms_nT, 3) < 1.0 and result.calibration.probes[0].offset_nT.shape == (3,)
    True

Inputs: a path (a lab CSV, an MCAP recording, a ROS 2 bag, a PX4 ULog, an ArduPilot DataFlash log), a pandas
DataFrame with the columns of docs/csv.md, or arrays (read_arrays). Every table goes through the one reader of lab
tables (fluxcal.service.io.recordings.labdata.lab_table), so a DataFrame fits to the same parameters as the CSV written from
it. Wiring: it joins the readers (I/O) and the commands' runs (which join the numerics).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from fluxcal.drivers.errors import DataError
from fluxcal.service.io.recordings.labdata import LabData, lab_table
from fluxcal.service.wiring.prepare import Prepared, prepare
from fluxcal.service.wiring.result import Said

#: the options of read() (they choose what the data are): fit() and diagnose() take them only with a path
READ_OPTIONS = ("config", "site", "skip", "topics", "mags")


class Data:
    """One recording's samples, ready for fit and diagnose (what read() gives): the commands' prepared input, with
    what reading said in `notes`."""

    def __init__(self, prepared: Prepared, notes: list[Any]) -> None:
        self._prepared = prepared
        self.notes = list(notes)

    def prepared(self) -> Prepared:
        """A Prepared of its own for one consumer (a diagnosis lets go of the samples it takes: never of these)."""
        return dataclasses.replace(self._prepared)

    @property
    def source(self) -> str:
        return self._prepared.source

    @property
    def lab(self) -> LabData:
        return self._prepared.data

    @property
    def probe_names(self) -> list[str]:
        return list(self.lab.probe_names)

    @property
    def n_samples(self) -> int:
        return int(self.lab.block.n_samples)

    @property
    def t_s(self) -> np.ndarray:
        """(N,) time, s."""
        return self.lab.block.t_s

    @property
    def field_nT(self) -> np.ndarray:
        """(N, P, 3) each probe's raw field, nT (NaN where saturated)."""
        return self.lab.block.field_nT

    @property
    def temp_C(self) -> np.ndarray:
        """(N, P) each probe's temperature, degC (NaN where not logged)."""
        return self.lab.block.temp_C

    @property
    def columns(self) -> dict[str, np.ndarray]:
        """The other logged columns (currents, voltages, the attitude, ref_total ...), by name."""
        return dict(self.lab.block.extras)

    def to_dataframe(self) -> Any:
        """The samples as a pandas DataFrame with the columns of docs/csv.md (t, s1_x, ..., s1_temp, the columns);
        read() of it gives the same data."""
        import pandas as pd

        return pd.DataFrame(_table(self.lab))

    def __repr__(self) -> str:
        b = self.lab.block
        span = float(b.t_s[-1] - b.t_s[0]) if b.n_samples else 0.0
        return (f"Data({self.source!r}: {b.n_samples:,} samples over {span:.1f} s, probes "
                f"{', '.join(self.probe_names)}; columns {', '.join(b.extras) or 'none'})")


def _table(lab: LabData) -> dict[str, np.ndarray]:
    """The columns of docs/csv.md of a LabData, in their order."""
    b = lab.block
    out: dict[str, np.ndarray] = {"t": b.t_s}
    for k in range(b.n_probes):
        for a, axis in enumerate("xyz"):
            out[f"s{k + 1}_{axis}"] = b.field_nT[:, k, a]
        if np.isfinite(b.temp_C[:, k]).any():
            out[f"s{k + 1}_temp"] = b.temp_C[:, k]
    out.update(b.extras)
    return out


def _said(said: Said | None, command: str) -> Said:
    return said if said is not None else Said(command)


def read(source: Any, *, config: str | None = None, site: str | None = None,
         skip: Sequence[tuple[float, float]] | None = None, topics: dict[str, str | None] | None = None,
         mags: Sequence[int] | None = None, calibration: str | None = None, max_samples: int | None = None,
         max_probe_samples: int | None = None, said: Said | None = None) -> Data:
    """The data of `source`: a path (any file the command line reads), a pandas DataFrame with the columns of
    docs/csv.md, or a LabData. config: a service configuration (the total field and the probe positions); site:
    'lat,lon,alt_m' for the World Magnetic Model's field; skip: (start, end) spans in s to leave out; topics, mags:
    another ecosystem's log, which topics or compasses become what; calibration: a calibration file to hold fixed in
    a diagnosis. What reading says is in Data.notes (and handed to `said`).

    >>> d = read("recordings/grad3-pump.mcap")
    >>> d.field_nT.shape, round(float(d.t_s[-1] - d.t_s[0]), 2)
    ((4000, 3, 3), 159.96)
    """
    said = _said(said, "read")
    if isinstance(source, (str, Path)):
        prep = prepare(str(source), said, config=config, site=site, skip=skip, topics=topics, mags=mags,
                       calibration=calibration, max_samples=max_samples, max_probe_samples=max_probe_samples)
        return Data(prep, said.notes)
    if isinstance(source, LabData):
        lab = source
    elif hasattr(source, "columns") and hasattr(source, "to_numpy"):        # a pandas DataFrame
        names = [_name("read", c) for c in source.columns]
        lab = lab_table("<DataFrame>", names, np.column_stack([_numbers("read", f"column {n!r}", source[c].to_numpy())
                                                               for n, c in zip(names, source.columns)]))
    else:
        raise DataError(f"read: expected a path, a pandas DataFrame or LabData, got {type(source).__name__} (for "
                        f"arrays: read_arrays)")
    return Data(_prepared_from(lab, said, config=config, site=site, skip=skip, calibration=calibration), said.notes)


def read_arrays(t_s: Any, field_nT: Any, *, temp_C: Any = None, columns: dict[str, Any] | None = None,
                config: str | None = None, site: str | None = None, said: Said | None = None) -> Data:
    """The data of arrays: t_s (N,) s, field_nT (N, 3) or (N, P, 3) nT, temp_C (N,) or (N, P) degC, columns: other
    logged columns by name (a current, ref_total ...). Read as the table of docs/csv.md they make, checked as a CSV is.

    >>> t = np.arange(100) / 10.0
    >>> d = read_arrays(t, np.tile([20000.0, 0.0, 45000.0], (100, 1)), columns={"heater_A": np.zeros(100)})
    >>> d.probe_names, sorted(d.columns), d.to_dataframe().columns[:4].tolist()
    (['s1'], ['heater_A'], ['t', 's1_x', 's1_y', 's1_z'])
    """
    t = _numbers("read_arrays", "t_s", t_s)
    f = _numbers("read_arrays", "field_nT", field_nT)
    f = f[:, None, :] if f.ndim == 2 else f
    if f.ndim != 3 or f.shape[2] != 3 or f.shape[0] != t.shape[0]:
        raise DataError(f"read_arrays: field_nT: expected shape (N={t.shape[0]}, 3) or (N, P, 3), got "
                        f"{np.shape(field_nT)}")
    header, cols = ["t"], [t]
    for k in range(f.shape[1]):
        header += [f"s{k + 1}_{a}" for a in "xyz"]
        cols += [f[:, k, a] for a in range(3)]
    n, p = t.shape[0], f.shape[1]
    if temp_C is not None:
        temps = _numbers("read_arrays", "temp_C", temp_C)
        if temps.shape not in ((n,), (n, p)):
            raise DataError(f"read_arrays: temp_C: expected shape (N={n},) or (N, P={p}), got {temps.shape}")
        temps = temps.reshape(n, -1)
        header += [f"s{k + 1}_temp" for k in range(temps.shape[1])]
        cols += [temps[:, k] for k in range(temps.shape[1])]
    for name, values in (columns or {}).items():
        name = _name("read_arrays", name)
        v = _numbers("read_arrays", f"columns[{name!r}]", values)
        if v.shape != (n,):
            raise DataError(f"read_arrays: columns[{name!r}]: expected shape (N={n},), got {v.shape}")
        header.append(name)
        cols.append(v)
    lab = lab_table("<arrays>", header, np.column_stack(cols))
    said = _said(said, "read")
    return Data(_prepared_from(lab, said, config=config, site=site), said.notes)


def _numbers(who: str, what: str, values: Any) -> np.ndarray:
    """values as float64, or a DataError naming what and its first value that is no number (numpy's and pandas' own
    error named neither: "could not convert string to float: 'hover'")."""
    try:
        return np.asarray(values, dtype=np.float64)
    except (TypeError, ValueError):
        held = np.asarray(values, dtype=object)
        flat = held.ravel()
        bad = next((i for i, v in enumerate(flat) if not _is_number(v)), 0)
        row = int(np.unravel_index(bad, held.shape)[0]) + 1 if held.ndim else 1      # the sample, whatever its axes
        raise DataError(f"{who}: {what}: {flat[bad]!r} (row {row}) is not a number; fluxcal reads numbers only "
                        f"(docs/csv.md): leave text out (DataFrame.select_dtypes('number')) or map it to numbers "
                        f"first") from None


def _is_number(v: Any) -> bool:
    try:
        float(v)
        return True
    except (TypeError, ValueError):
        return False


def _name(who: str, name: Any) -> str:
    """A column's name as a CSV header can hold it (the table is the one docs/csv.md reads), else a DataError."""
    text = str(name).strip()
    if not text or any(c in text for c in ',"\n\r'):
        raise DataError(f"{who}: column name {text!r}: a column's name is not empty and holds no comma, quote or line "
                        f"break (it is a CSV header, docs/csv.md)")
    return text


def _prepared_from(lab: LabData, said: Said, **options: Any) -> Prepared:
    """A Prepared of data already in memory, through prepare's own steps (prepare.prepared_from)."""
    from fluxcal.service.wiring.prepare import prepared_from

    return prepared_from(lab, said, **{k: v for k, v in options.items() if v is not None})


def _input(data: Any, said: Said, read_options: dict[str, Any], **limits: Any) -> Prepared:
    """The Prepared a command runs on: a path read here (with the read options and the command's limits on the
    samples, kept as it reads), else the Data's own (the same limits applied to them)."""
    from fluxcal.service.io.recordings.load import thinned

    given = {k: v for k, v in read_options.items() if v is not None}
    if isinstance(data, (str, Path)):
        return prepare(str(data), said, **given, **limits)
    if isinstance(data, Data):
        if given:
            raise DataError(f"{', '.join(sorted(given))}: options of read(), which made these data: give them there")
        prep = data.prepared()
    else:
        prep = read(data, said=said, **given).prepared()
    if limits:
        prep.data = thinned(prep.data, **limits)
    return prep


def _effects(effects: Sequence[str] | str) -> list[str]:
    """The effects asked for: a list of names, or one text of them as --effects takes it ("temperature,drift": a
    text is not split into its letters)."""
    if isinstance(effects, str):
        return [e.strip() for e in effects.split(",") if e.strip()]
    return list(effects)


def fit(data: Any, *, method: str = "ellipsoid", align: str | None = None, effects: Sequence[str] | str = (),
        out: str | None = None, report: str | None = None, said: Said | None = None, **read_options: Any) -> Any:
    """Fit a calibration to `data` (a Data, or anything read() takes, with read()'s options): the FitResult the
    command `fluxcal fit` prints (`.text()`, `.to_dict()`, `.to_dataframe()`, `.calibration`). out: write the
    calibration file; report: an HTML report's folder.

    >>> r = fit("recordings/grad1-hidden-effect.mcap", effects=["temperature"])
    >>> r.to_dict()["effects"], round(r.rms_nT, 3)
    (['temperature'], 0.896)
    """
    from fluxcal.service.wiring.commands import fit as command

    said = _said(said, "fit")
    opts = command.FitOptions(method=method, align=align, effects=_effects(effects), out=out, report=report)
    opts = command.checked(opts, str(data) if isinstance(data, (str, Path)) else None)
    return command.run(_input(data, said, _read_options(read_options)), opts, said)


def diagnose(data: Any, *, effects: Sequence[str] | str = (), report: str | None = None, write_effect: str | None = None,
             max_samples: int | None = None, calibration: str | None = None, said: Said | None = None,
             progress: bool = False, **read_options: Any) -> Any:
    """Compare the model (the linear calibration and `effects`) with `data`, find where it fails and which effect is
    missing, beyond the catalogue too: the DiagnoseResult `fluxcal diagnose` prints (`.diagnosis` holds every figure).
    write_effect: a .py file for what discovery found; report: an HTML report's folder; max_samples: the samples
    diagnosed at most (None: the command's budget of probe-samples); calibration: a calibration file whose linear
    part is held fixed (with a path; read() takes it for Data); progress: a progress bar on stderr.

    >>> d = diagnose("recordings/grad1-hidden-effect.mcap")
    >>> d.verdict["kind"], d.verdict["effect"]
    ('explained', 'temperature')
    """
    from fluxcal.service.wiring.commands import diagnose as command

    said = _said(said, "diagnose")
    source = str(data) if isinstance(data, (str, Path)) else None
    if source is None and calibration is not None:
        raise DataError("calibration: an option of read(), which makes the data: give it there")
    opts = command.checked(command.DiagnoseOptions(effects=_effects(effects), calibration=calibration, report=report,
                                                   write_effect=write_effect, max_samples=max_samples), source)
    prep = _input(data, said, {**_read_options(read_options), "calibration": calibration},
                  **command.read_limits(opts))
    return command.run(prep, command.with_held_effects(prep, opts), said, progress=progress)


def _read_options(options: dict[str, Any]) -> dict[str, Any]:
    unknown = sorted(set(options) - set(READ_OPTIONS))
    if unknown:
        raise TypeError(f"unexpected option(s) {', '.join(unknown)} (allowed besides the command's own: "
                        f"{', '.join(READ_OPTIONS)})")
    return {k: options.get(k) for k in READ_OPTIONS}


def replay(recording: str | Path, *, config: str | None = None, out: str | None = None, ros2_out: str | None = None,
           said: Said | None = None) -> Any:
    """Replay a recording through the pipeline of the service and compare with what it recorded live: the
    ReplayResult `fluxcal replay` prints.

    >>> r = replay("recordings/grad1-sim-30s.mcap")
    >>> r.status, r.compared, r.identical
    (0, 2000, 2000)
    """
    from fluxcal.service.wiring.commands import replay as command

    return command.execute(str(recording), command.ReplayOptions(config=config, out=out, ros2_out=ros2_out),
                           _said(said, "replay"))


def simulate(out: str | Path, *, config: str | None = None, said: Said | None = None) -> Any:
    """A simulated unit's data written to `out` (.csv, .mcap, a serial capture or a CAN log) and its truth beside
    it: the SimulateResult `fluxcal simulate` gives; read(out) reads the data.

    >>> import os, tempfile
    >>> out = os.path.join(tempfile.mkdtemp(), "grad.csv")
    >>> simulate(out, config="configs/sim-gradiometer.toml").samples, read(out).probe_names
    (12000, ['s1', 's2'])
    """
    from fluxcal.service.wiring.commands import simulate as command

    return command.execute(command.SimulateOptions(out=str(out), config=config), _said(said, "simulate"))
