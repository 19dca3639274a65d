"""One preparation of the input for `fit`, `diagnose` and their fleets: the data read, what reading lost said, the
stretches --skip names left out, a rotated file given alone said, a logger's held samples left out, the total field
and probe positions taken from --config or else from the configuration a service recording stores (said in the
header line), --site's World Magnetic Model field, and the model along the track where the data carry a position.

    prepare(source, said, config=..., site=..., skip=..., max_samples=..., max_probe_samples=...) -> Prepared

One semantics whichever command asks: the configuration's probe positions must be as many as the data's probes
(ConfigError otherwise), positions all at one point tell no probes apart (None), --site's field replaces a
configured total, and every note goes through `said` (fluxcal.service.wiring.result.Said) as data.
"""

from __future__ import annotations

import dataclasses
import json
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from fluxcal.drivers.config import load_section, read_toml
from fluxcal.drivers.errors import ConfigError, DataError
from fluxcal.service.io.recordings.labdata import LabData
from fluxcal.service.io.recordings.load import load_data
from fluxcal.service.numerics.calib.site import SiteField, site_from_text

from .result import Said


@dataclass
class Prepared:
    """The input of one recording, ready for a fit or a diagnosis."""

    source: str                                   # the path as given
    data: LabData
    positions_m: np.ndarray | None = None         # (P, 3) m, None: none given, or all at one point
    total_nT: float | None = None                 # the total field given (config or site); a ref_total column is data
    origin: str | None = None                     # where positions and total came from: FROM_RECORDING, "configuration
                                                  # from FILE", or None (the data alone)
    site: SiteField | None = None
    skipped: list[tuple[float, float]] = field(default_factory=list)
    part_of_run: str | None = None                # a rotated file given alone: what it is part of
    config_warning: str | None = None             # a stored configuration that could not be used, and why
    track: str | None = None                      # the model whose field along the track is the data's ref_total
    holds: Any = None                             # fluxcal.service.numerics.holds.Holds: the logger's held samples left out
    held: Any = None                              # a linear calibration to hold fixed (--calibration), or None
    held_effects: list[str] = field(default_factory=list)     # the effects the held calibration's file names

    def take_data(self) -> LabData:
        """The data, let go of here: a consumer that turns them into another form (diagnose's EffectData) holds
        them once, not twice (hours of samples)."""
        data, self.data = self.data, None
        if data is None:
            raise ValueError(f"{self.source}: the prepared data were already taken")
        return data

    @property
    def given_total_source(self) -> str:
        """Where the total field a diagnosis compares with comes from, for the data's scale note: the track, the
        site, the configuration, or "given"."""
        if self.track is not None:
            return self.total_source or "given"
        if self.site is not None:
            return f"the site ({self.site.model})"                   # as fit says it
        return self.origin or "given"

    @property
    def total_source(self) -> str | None:
        """What the given total field is, for a sentence: the track, the site, the configuration, or None."""
        if self.track is not None:
            return f"the reference field along the track ({self.track})"
        if self.site is not None:
            return f"the site ({self.site.model})"
        if self.total_nT is not None:
            return self.origin
        return None


def prepare(source: str, said: Said, *, config: str | None = None, site: str | None = None,
            skip: Sequence[tuple[float, float]] | None = None, max_samples: int | None = None,
            max_probe_samples: int | None = None, topics: dict[str, str | None] | None = None,
            mags: Sequence[int] | None = None, calibration: str | None = None) -> Prepared:
    """Read `source` and gather what the fits need beside the samples (module docstring). topics, mags: another
    ecosystem's log, which topics (a ROS 2 bag) or compass instances (PX4, ArduPilot) become what. calibration: a
    calibration file whose linear part is to be held fixed (held_calibration)."""
    mapping = log_mapping(source, topics, mags)
    data = load_data(source, max_samples=max_samples, max_probe_samples=max_probe_samples, mapping=mapping)
    say_read_warnings(said, source, data.warnings, repairable=data.metadata.get("format") not in FOREIGN)
    for note in data.notes:                       # how another ecosystem's topics were matched into samples
        said("format", note, level="note")
    return prepared_from(data, said, config=config, site=site, skip=skip, calibration=calibration, source=source)


def prepared_from(data: LabData, said: Said, *, config: str | None = None, site: str | None = None,
                  skip: Sequence[tuple[float, float]] | None = None, calibration: str | None = None,
                  source: str | None = None) -> Prepared:
    """The rest of prepare() on data already read (`source`: the file they came from, or None for a table in memory:
    fluxcal.service.wiring.api): --skip's stretches, a logger's held samples, a rotated file given alone, the calibration
    held, the geometry of --config or of the stored configuration, --site, the track."""
    data = skip_spans(said, source or data.path, data, skip)
    data, holds = _without_holds(said, data)
    part = part_of_run(said, source) if source is not None else None
    source = data.path if source is None else source
    n_probes = data.block.n_probes
    with refusing(calibration):
        held, held_effects = held_calibration(calibration, n_probes) if calibration else (None, [])
    if config:
        with refusing(config):
            positions, total = config_geometry(config, n_probes)
        origin, warning = f"configuration from {config}", None
    else:                                         # the configuration a service recording stores, said
        given = stored_config(data.metadata, str(source), n_probes)
        positions, total, origin, warning = given.positions_m, given.total_nT, given.origin, given.warning
        if warning:
            said("config", warning)
    the_site = site_from_text(site) if site else None
    if the_site is not None:
        total = the_site.total_nT
    data, track = _along_the_track(said, data, the_site)
    return Prepared(source=str(source), data=data, positions_m=spread(positions), total_nT=total, origin=origin,
                    site=the_site, skipped=list(skip or []), part_of_run=part, config_warning=warning, track=track,
                    holds=holds, held=held, held_effects=held_effects)


@contextmanager
def refusing(path: str | None):
    """A file given beside the data (--config, --calibration) that cannot be used refuses that file: the error's
    `file` is it, and the refusal (result.refusal) names it, not the data."""
    try:
        yield
    except (ConfigError, DataError) as e:
        if path is not None:
            e.file = str(path)
        raise


def held_calibration(path: str, n_probes: int) -> tuple[Any, list[str]]:
    """A calibration file to hold fixed: the calibration file of `fit --out` (fluxcal.service.io.calfile), or the JSON of
    `fit --json`, read and checked as `load_calibration` reads it. Returns the linear part and the names of the effects
    the file carries (a report's effects too: only the linear part is held); DataError for a file that is neither."""
    from fluxcal.service.io.calfile import (
        calibration_from_json,
        calibration_from_report,
        is_report,
        parse_json,
        read_calibration_text,
    )
    from fluxcal.service.numerics.engine import LinearCalibration

    p = Path(path)
    text = read_calibration_text(p)                       # bounded; DataError for what cannot be read
    obj = parse_json(text, str(p)) if text.lstrip().startswith("{") else None
    if is_report(obj):
        cal = calibration_from_report(obj, str(p), linear_part=True)
        return LinearCalibration.from_any(cal, n_probes), [str(e) for e in obj.get("effects") or []]
    cal = calibration_from_json(text, origin=str(p))
    return LinearCalibration.from_any(cal, n_probes), list(cal.effects)


@dataclass
class EffectInput:
    """The prepared data as the effect models take them (fluxcal.service.numerics.effects.base.EffectData), with the notes
    a diagnosis says before its own: where the geometry came from, the data's scale, what thinning cost."""

    data: Any                                     # EffectData
    notes: list[str]
    thinned: dict[str, Any] | None = None         # `thinning`'s figures, None when every sample was kept


def effect_input(prep: Prepared, said: Said, *, budget: str, centres_nT: Any = None) -> EffectInput:
    """The prepared data let go of (Prepared.take_data) into EffectData, said: the thinning `budget` (the words
    of what limited the samples) imposed, and the data's scale against the total field given (field_scale_notes).
    The samples then live in the EffectData alone (hours of them)."""
    from fluxcal.service.numerics.effects.base import EffectData
    from fluxcal.service.wiring.scale_notes import field_scale_notes

    lab = prep.take_data()
    thinned = thinning(lab, budget)
    total, positions = prep.total_nT, prep.positions_m
    taken = (([f"total field {total:,.0f} nT (estimator.total_nT)"] if total is not None and prep.site is None
              else []) + ([f"probe positions of {len(positions)} probes"] if positions is not None else []))
    data = EffectData.from_block(lab.block, lab.probe_names, total_nT=total, positions_m=positions)
    del lab
    ref = data.ref_total_nT                       # the reference the fits use before a configured total
    # the data's size about the determinacy gate's centres (`centres_nT`), as fit says it; else about a sphere
    scale = field_scale_notes(said, prep.source, data.raw_nT, data.probe_names, centres_nT=centres_nT,
                              total_nT=ref if ref is not None else total,
                              total_source=prep.given_total_source if ref is None or prep.track is not None
                              else "the ref_total column")
    notes = (([f"{prep.origin}: {'; '.join(taken)}"] if prep.origin and taken else [])
             + scale + ([thinned[1]] if thinned is not None else []))
    return EffectInput(data, notes, thinned[0] if thinned is not None else None)


def thinning(lab: Any, budget: str) -> tuple[dict[str, Any], str] | None:
    """What keeping every k-th sample (LabData.every) costs, for the JSON and a note; None when all were kept."""
    k, n_read, t = lab.every, lab.n_read, lab.block.t_s
    if k <= 1 or n_read is None:
        return None
    used = lab.block.n_samples
    dt = float(np.median(np.diff(t))) if used > 1 else float("nan")
    rate = 1.0 / dt if dt > 0 else float("nan")
    info = {"every": k, "n_used": used, "n_read": n_read, "rate_hz": rate, "limit": budget}
    text = (f"thinned: one sample in {k} diagnosed ({used:,} of {n_read:,}; {rate:.3g} Hz, {k} x the recorded "
            f"interval) to stay within {budget}. Motion and effects faster than {rate / 2:.3g} Hz are not seen; the "
            f"standard errors are those of the samples used, up to {np.sqrt(k):.1f} x the whole recording's under "
            f"white noise (less under 1/f noise, whose slow wander thinning does not lose)")
    return info, text


def log_mapping(source: str, topics: dict[str, str | None] | None, mags: Sequence[int] | None) -> Any:
    """The reader's options of another ecosystem's log from --topics and --mags (None: the reader's defaults);
    ConfigError for an option the file's format does not take."""
    if not topics and not mags:
        return None
    from fluxcal.service.io.recordings.formats import detect_format

    fmt = detect_format(source)
    if topics and fmt not in ("ros2-mcap", "ros2-bag", *FLIGHT_LOGS):
        raise ConfigError(f"--topics: {source} is not a ROS 2 bag, PX4 or ArduPilot log ({fmt}): --topics names "
                          f"what such a log's streams become")
    if mags and fmt not in FLIGHT_LOGS:
        raise ConfigError(f"--mags: {source} is not a PX4 or ArduPilot log ({fmt})")
    if fmt in FLIGHT_LOGS:
        from fluxcal.service.io.recordings.ardupilot import ArduPilotMapping
        from fluxcal.service.io.recordings.px4 import Px4Mapping

        mapping = Px4Mapping if fmt == "px4-ulog" else ArduPilotMapping
        return mapping(mags=tuple(mags) if mags else None, **_flight_options(source, fmt, topics or {}))
    from fluxcal.service.io.recordings.ros2 import AUTO, Ros2Mapping

    probes = {k: v for k, v in topics.items() if k not in ("imu", "gps", "battery") and not k.startswith("temp.")}
    temps = {k[5:]: v for k, v in topics.items() if k.startswith("temp.") and v is not None}
    return Ros2Mapping(probes={k: v for k, v in probes.items() if v is not None} or None,
                       temperatures=temps or None, imu=topics.get("imu", AUTO),
                       navsatfix=topics.get("gps", AUTO), battery=topics.get("battery", AUTO))


#: the flight logs' formats (their streams are messages, chosen by the reader) and their names for a person
FLIGHT_LOGS = {"px4-ulog": "a PX4 log", "ardupilot-bin": "an ArduPilot log"}
#: what `--topics NAME=none` leaves out of a flight log's mapping (its Px4Mapping or ArduPilotMapping switch)
LEFT_OUT = {"imu": "attitude", "gps": "position", "battery": "currents"}


#: a PX4 log's topics `--topics mag=TOPIC` may take the probes from (px4.COMPASS_TOPICS; sensor_mag by default)
PX4_MAG = "mag"


def _flight_options(source: str, fmt: str, topics: dict[str, str | None]) -> dict[str, Any]:
    """The options of a flight log's mapping that --topics sets: NAME=none of LEFT_OUT turns that stream off, and a
    PX4 log's mag=TOPIC chooses the topic its probes come from; ConfigError for any other (a flight log's messages are
    read as docs/px4.md and docs/ardupilot.md say)."""
    from fluxcal.service.io.recordings.px4 import COMPASS_TOPICS

    px4 = fmt == "px4-ulog"
    mag = topics.get(PX4_MAG) if px4 else None
    bad = [f"{k}={v or 'none'}" for k, v in topics.items()
           if not (k in LEFT_OUT and v is None) and not (px4 and k == PX4_MAG and v in COMPASS_TOPICS)]
    if bad:
        also = f", mag={' or mag='.join(COMPASS_TOPICS)} the topic the probes come from" if px4 else ""
        raise ConfigError(f"--topics: {', '.join(bad)} is not allowed for {source} ({FLIGHT_LOGS[fmt]}: its streams "
                          f"are the messages fluxcal reads, not topics to choose; allowed: imu=none, gps=none, "
                          f"battery=none, each leaving that stream out{also}; --mags chooses the compasses)")
    out: dict[str, Any] = {LEFT_OUT[k]: False for k in topics if k in LEFT_OUT}
    if mag is not None:
        out["compass"] = mag
    return out


#: the formats of other ecosystems' logs (not fluxcal's recordings: `fluxcal repair` does not mend them)
FOREIGN = ("ros2", "px4", "ardupilot")


def _without_holds(said: Said, data: LabData) -> tuple[LabData, Any]:
    """The data without the samples a logger repeated when no new one came (fluxcal.service.numerics.holds), said."""
    from fluxcal.service.numerics.holds import without_holds

    block, holds = without_holds(data.block, data.probe_names)
    for note in holds.notes:
        said("holds", note, level="warning" if holds.held.any() and "left out" in note else "note")
    return (dataclasses.replace(data, block=block) if block is not data.block else data), holds


def _along_the_track(said: Said, data: LabData, site: SiteField | None) -> tuple[LabData, str | None]:
    """Where the data carry a position (lat_deg, lon_deg, alt_m), the World Magnetic Model's field at every sample
    (fluxcal.service.numerics.calib.track) as the reference: said, with what it replaces."""
    from fluxcal.service.numerics.calib.track import track_reference

    t0 = data.metadata.get("t0_unix_s")
    year = None
    if site is not None and site.year is not None:
        year = site.year
    track = track_reference(data.block, t0_unix_s=float(t0) if t0 is not None else None, year=year)
    if track is None:
        return data, None
    said("track", track.note, level="note")
    for note in track.notes:
        said("track", note)
    return dataclasses.replace(data, block=track.block), track.model


#: the header's words for a configuration taken from the recording
FROM_RECORDING = "configuration from the recording"


@dataclass(frozen=True)
class DataConfig:
    """What fit and diagnose take from a configuration; `origin` None: there was none."""

    total_nT: float | None = None
    positions_m: np.ndarray | None = None
    origin: str | None = None           # FROM_RECORDING, or "configuration from FILE" (--config)
    warning: str | None = None          # a stored configuration that could not be used, and why


def geometry(raw: dict[str, Any], n_probes: int) -> tuple[np.ndarray | None, float | None]:
    """Probe positions (P, 3) and the total field of a raw configuration. The sections used are validated
    strictly ([unit], [[probes]], [estimator], [sim]); the others need not describe a runnable source, but
    unknown section names are still errors (ConfigError, without the file's name)."""
    from fluxcal.service.wiring.config import _SECTIONS, EstimatorConfig, ProbeConfig, UnitConfig

    for key in raw:
        if key not in _SECTIONS:
            raise ConfigError(f"{key}: unknown section (allowed: {', '.join(_SECTIONS)})")
    unit = load_section(UnitConfig, raw.get("unit", {}), "unit")
    total = load_section(EstimatorConfig, raw.get("estimator", {}), "estimator").total_nT
    tables = raw.get("probes", [])
    if not isinstance(tables, list):
        raise ConfigError("probes: expected an array of tables [[probes]]")
    probes = [load_section(ProbeConfig, t, f"probes[{i}]") for i, t in enumerate(tables)]
    positions = None
    if probes:
        if "unit" in raw and len(probes) != unit.n_probes:
            raise ConfigError(f"probes: {len(probes)} [[probes]] tables but unit.n_probes = {unit.n_probes}")
        positions = np.array([p.position_m for p in probes], dtype=np.float64)
    elif "sim" in raw:
        from fluxcal.drivers.sim.config import load_sim_config

        positions = np.array([p.position_m for p in load_sim_config(raw["sim"]).probes], dtype=np.float64)
    if positions is not None and positions.shape[0] != n_probes:
        raise ConfigError(f"probes: {positions.shape[0]} probe positions but the data have {n_probes} probes")
    return positions, total


def stored_config(metadata: dict[str, str], where: str, n_probes: int) -> DataConfig:
    """The total field and probe positions of the configuration a service recording stores (its "fluxcal"
    metadata record's `config`). None of it when the recording stores none (a CSV, `simulate`'s recordings);
    a stored configuration that cannot be read is a warning saying so (the caller says it and counts it), and
    the data are then used as without one."""
    text = metadata.get("config")
    if not text:
        return DataConfig()
    try:
        raw = json.loads(text)
        if not isinstance(raw, dict):
            raise ConfigError(f"expected a table, got {type(raw).__name__}")
        positions, total = geometry(raw, n_probes)
    except (ValueError, ConfigError) as e:
        return DataConfig(warning=f"{where}: its stored configuration cannot be used ({e}): the total field and "
                                  f"probe positions are not taken from it; give them with --config FILE")
    return DataConfig(total, positions, FROM_RECORDING)


def spread(positions_m: Any) -> np.ndarray | None:
    """Probe positions that tell the probes apart (None when there are none, or all are at one point)."""
    if positions_m is None:
        return None
    pos = np.asarray(positions_m, float)
    return pos if np.ptp(pos, axis=0).any() else None


def config_geometry(path: str, n_probes: int) -> tuple[np.ndarray | None, float | None]:
    """Probe positions (P, 3) and the total field from a configuration file (geometry: the
    sections used validated strictly, unknown section names errors), naming the file in any error."""
    from fluxcal.service.wiring.config import require_content

    raw = read_toml(path)
    require_content(raw, path)
    try:
        return geometry(raw, n_probes)
    except ConfigError as e:
        raise ConfigError(f"{path}: {e}") from None


def say_read_warnings(said: Said, source: str, warnings: Sequence[str], repairable: bool = True) -> None:
    """One note per thing reading lost or skipped (a cut tail, a damaged record), then how to mend a recording of
    fluxcal's (`repair` does not mend another ecosystem's log)."""
    for w in warnings:
        said("read", w)
    if warnings and repairable:
        said("read", f"the data above were read without what is listed; `fluxcal repair {source} FIXED.mcap` writes "
                     f"a finished copy of what is readable", level="say")


def part_of_run(said: Said, source: str) -> str | None:
    """A file the service rotated out of a longer run, given alone: said, with the folder that holds the whole run
    (fit and diagnose then use only this file's samples; replay says more, commands/replay.continuation)."""
    from fluxcal.service.io.recordings.runs import runs_of

    p = Path(source)
    if p.is_dir() or p.suffix != ".mcap":
        return None
    run = next((r for r in runs_of(sorted(p.parent.glob("*.mcap"))) if p.name in {f.name for f in r}), [])
    if len(run) < 2:
        return None
    k = [f.name for f in run].index(p.name) + 1
    note = (f"{p.name} is file {k} of {len(run)} of one run the service rotated ({run[0].name} ... {run[-1].name}); "
            f"this uses its samples alone: `fluxcal {said.command} {p.parent}` takes the whole run")
    said("part-of-run", note, level="note")
    return note


def skip_spans(said: Said, source: str, lab: Any, spans: Sequence[tuple[float, float]] | None) -> Any:
    """The data without the samples in the stretches --skip names (ends included), said with how many samples
    each left out; a stretch that holds no sample is said too, and one that leaves nothing is refused."""
    if not spans:
        return lab
    t = lab.block.t_s
    out = np.zeros(t.shape, dtype=bool)
    counts, held = [], []
    for lo, hi in spans:
        inside = (t >= lo) & (t <= hi)
        counts.append(f"{lo:g}-{hi:g} s: {int(np.count_nonzero(inside & ~out)):,}")     # not counted twice
        held.append(bool(inside.any()))
        out |= inside
    if out.all():
        raise DataError(f"--skip {','.join(f'{lo:g}-{hi:g}' for lo, hi in spans)}: leaves no sample of {source} "
                        f"(its time runs {float(np.nanmin(t)):g}-{float(np.nanmax(t)):g} s)")
    said("skip", f"--skip left out {int(out.sum()):,} of {t.size:,} samples ({'; '.join(counts)})", level="note")
    if not all(held):
        said("skip", f"a --skip stretch holds no sample of {source} (its time runs {float(np.nanmin(t)):g}-"
                     f"{float(np.nanmax(t)):g} s)")
    return dataclasses.replace(lab, block=lab.block.rows(~out))


__all__ = ["FROM_RECORDING", "EffectInput", "Prepared", "config_geometry", "effect_input", "part_of_run", "prepare",
           "say_read_warnings", "skip_spans", "thinning"]
