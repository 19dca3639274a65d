"""`fluxcal simulate [--config FILE] --out FILE.csv|FILE.mcap`: write simulated unit data and its truth.

The CSV is the lab format of docs/csv.md (comments first, then t, s<k>_x/y/z, s<k>_temp,
ref_total, seq, flags); the truth JSON beside it (FILE.truth.json) holds every parameter of the world,
each probe's calibration matrix and offset included (fluxcal.drivers.sim.world.World.truth). Both files
appear complete or not at all. Without --config the built-in gradiometer world is used
(configs/sim-gradiometer.toml).
"""

from __future__ import annotations

import argparse
import json
import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from fluxcal.drivers.config import load_section, read_toml
from fluxcal.drivers.errors import ConfigError, DataError
from fluxcal.drivers.outputs import temp_beside
from fluxcal.drivers.sim.config import GRADIOMETER, SimConfig, load_sim_config
from fluxcal.drivers.sim.unit import Unit
from fluxcal.service.wiring.commands.options import CommandHelp
from fluxcal.service.wiring.progress import Progress
from fluxcal.service.wiring.result import Result, Said, stderr_say

BLOCK_SAMPLES = 100_000       # samples formatted per write: bounded memory for long runs
DEFAULT_UNIT_NAME = "grad1"


HELP = CommandHelp("write simulated unit data",
                   "  fluxcal simulate --config configs/sim-gradiometer.toml --out grad.csv\n"
                   "  fluxcal simulate --out capture.bin      # then: fluxcal decode capture.bin --probes 2 --out d.csv\n"
                   "  fluxcal simulate --out bus.log          # then: fluxcal decode bus.log --can --probes 2 --out d.csv")


def add_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--config", metavar="FILE",
                   help="the [sim] section to simulate (default: a built-in gradiometer). Hide an effect by giving "
                        "its keys: [[sim.probes]] temp_offset_nT_per_C, eddy_s, lag_s, nonlin_quadratic_per_nT, "
                        "drift_offset_nT_per_h, pink_nT_rtHz (1/f noise); [sim.field] gradient_nT_m, "
                        "variation_nT (ambient change); [sim.temperature] ramp_C_per_h, amplitude_C; [sim.motion] "
                        "kind (turntable, tumble, grid, static). configs/sim-gradiometer.toml lists them all with "
                        "units. Neither output carries the platform's attitude (the truth file holds the motion), so a "
                        "hidden site gradient cannot be diagnosed from them")
    p.add_argument("--out", required=True, metavar="FILE.csv|FILE.mcap|FILE.bin|FILE.log",
                   help="where to write (allowed: .csv lab data, with angle_deg and turn for a turntable; .mcap a "
                        "recording; .bin the unit's serial bytes; .log a candump log of its CAN frames); a "
                        ".truth.json with every simulated parameter goes beside it")


def truth_path(out: Path) -> Path:
    """FILE.csv -> FILE.truth.json."""
    return out.with_name(out.stem + ".truth.json")


def free_truth_path(out: Path) -> Path:
    """truth_path(out), unless that file holds the truth of another data file that is still beside it (run.csv
    written before run.mcap): then FILE.<suffix>.truth.json, so that neither truth is lost."""
    path = truth_path(out)
    try:
        other = json.loads(path.read_text(encoding="utf-8")).get("data_file")
    except (OSError, ValueError, AttributeError):
        return path
    if isinstance(other, str) and other != out.name and (out.parent / other).exists():
        return out.with_name(out.name + ".truth.json")
    return path


def _say_faults(said: Said, unit: Unit, names: list[str], suffix: str) -> None:
    """How many samples the run saturated or marked temperature-invalid, and how the output carries them (a CSV
    and a recording as NaN with the flag, the unit's own bytes as the rails' counts with the flag)."""
    cfg = unit.config
    limit = f"range_nT {cfg.range_nT:g} nT" if cfg.range_nT is not None else "the int32 rails"
    decoded = suffix in (".csv", ".mcap")
    for name, k in zip(names, unit.saturated_samples.tolist()):
        if k:
            said("saturated", f"{name}: {k} samples saturated (beyond {limit}): "
                              f"{'NaN in the output' if decoded else 'the rail counts in the frames'}, flag bit0 set",
                 level="say")
    if unit.temp_invalid_samples:
        said("temp-invalid", f"{unit.temp_invalid_samples} samples with the temperature marked invalid "
                             f"(flag bit1{'; NaN in a CSV' if suffix == '.csv' else ''})", level="say")


def load_simulation(path: str | None) -> tuple[SimConfig, str]:
    """The [sim] world and the unit name of a configuration file (validated as the service does), or the
    built-in gradiometer."""
    if path is None:
        return load_sim_config(GRADIOMETER), DEFAULT_UNIT_NAME
    raw = read_toml(path)
    if "sim" not in raw:
        raise ConfigError(f"{path}: no [sim] section: `fluxcal simulate` needs the simulated world "
                          f"(see configs/sim-gradiometer.toml)")
    try:
        from fluxcal.service.wiring.config import config_from_dict

        cfg = config_from_dict(raw, str(path))             # every section, as `fluxcal run` checks it
        sim, unit = cfg.sim, cfg.unit
    except ModuleNotFoundError as e:
        if not (e.name or "").startswith("service."):
            raise
        # a part of the service that validates another section is not installed: check ours
        from fluxcal.service.wiring.config import UnitConfig

        try:
            unit = load_section(UnitConfig, raw.get("unit", {}), "unit")
            sim = load_sim_config(raw["sim"])
        except ConfigError as err:
            raise ConfigError(f"{path}: {err}") from None
        if sim.n_probes != unit.n_probes:
            raise ConfigError(f"{path}: sim.probes: {sim.n_probes} simulated probes but unit.n_probes = "
                              f"{unit.n_probes}")
    if not math.isclose(unit.lsb_nT, sim.lsb_nT, rel_tol=1e-12):
        raise ConfigError(f"{path}: sim.lsb_nT: {sim.lsb_nT!r} differs from unit.lsb_nT = {unit.lsb_nT!r}")
    return sim, unit.name


def _decimals(step: float) -> int:
    """Decimals that print multiples of `step` exactly (0.001 -> 3)."""
    return max(0, min(12, math.ceil(-math.log10(step) - 1e-9)))


def write_csv(path: Path, unit: Unit, unit_name: str, truth_file: str, progress: Any = None) -> int:
    """Write the run as a lab CSV to `path` (the caller renames it into place). Returns samples."""
    cfg = unit.config
    n = unit.n_samples
    assert n is not None
    p = cfg.n_probes
    names = [f"s{k + 1}" for k in range(p)]
    header = ["t"] + [f"{s}_{a}" for s in names for a in "xyz"] + [f"{s}_temp" for s in names]
    # a turntable run carries what its controller logs: the angle (for sinefit) and the turn (for two-step)
    table = getattr(unit.world.motion, "table", None)
    ref = cfg.reference.enabled
    if ref:
        header.append("ref_total")
    header += ["seq", "flags"]
    dec = _decimals(cfg.lsb_nT)
    fmt = ["%.6f"] + [f"%.{dec}f"] * (3 * p) + ["%.2f"] * p + ([f"%.{max(dec, 4)}f"] if ref else []) + ["%d", "%d"]
    if table is not None:
        header += ["angle_deg", "turn"]
        fmt += ["%.6f", "%d"]
    track = unit.world.track                  # [sim.track]: where the platform is, as a GNSS receiver logs it
    if track is not None:
        header += ["lat_deg", "lon_deg", "alt_m"]
        fmt += ["%.7f", "%.7f", "%.3f"]
    f = cfg.field
    probes_text = ", ".join(f"{pr.name} at {pr.position_m} m" for pr in cfg.probes)
    comments = [
        f"fluxcal simulate: simulated unit {unit_name!r}, {p} probe(s), {cfg.rate_hz:g} Hz, {cfg.duration_s:g} s, "
        f"seed {cfg.seed}",
        f"truth: {truth_file} (every parameter; per-probe matrix and offset_nT: matrix (raw - offset) = B_platform)",
        f"field: {f.total_nT:g} nT, inclination {f.inclination_deg:g} deg, declination {f.declination_deg:g} deg "
        f"(NED); motion: {cfg.motion.kind}; effects: {', '.join(unit.world.active_effects) or 'none'}",
        f"probes (platform frame): {probes_text}",
        f"columns: t s (unit clock), s<k>_x/y/z nT (counts x lsb_nT {cfg.lsb_nT:g}; nan: saturated), "
        f"s<k>_temp degC (nan: invalid)"
        + (", ref_total nT (scalar reference at the platform origin)" if ref else "")
        + ", seq (sample counter, unwrapped), flags (ICD: bit0 saturated, bit1 temperature invalid)"
        + (", angle_deg (turntable angle), turn (0/1/2: about body x/y/z, -1: dwell)" if table is not None else "")
        + (", lat_deg, lon_deg, alt_m (the platform's position: [sim.track])" if track is not None else ""),
    ]
    with open(path, "w", encoding="utf-8", newline="\n") as fh:
        for c in comments:
            fh.write(f"# {c}\n")
        fh.write(",".join(header) + "\n")
        for start in range(0, n, BLOCK_SAMPLES):
            stop = min(n, start + BLOCK_SAMPLES)
            s = unit.digitise(start, stop)
            # as a decoder of the frames has them: a saturated axis and an invalid temperature are NaN (with
            # the flags beside them), never the rails' numbers (2147483.647 nT at 0.001 nT) a fit would take
            b = s.to_block()
            cols = [s.t_us / 1e6, b.field_nT.reshape(len(s), -1), b.temp_C]
            if ref:
                cols.append(s.ref_total_nT)
            cols += [s.seq, s.flags]
            if table is not None:
                cols += list(table(np.arange(start, stop) / cfg.rate_hz))
            if track is not None:
                pos = track.position(np.arange(start, stop) / cfg.rate_hz)
                cols += [pos["lat_deg"], pos["lon_deg"], pos["alt_m"]]
            rows = np.column_stack([np.asarray(c, dtype=np.float64).reshape(len(s), -1) for c in cols])
            np.savetxt(fh, rows, fmt=fmt, delimiter=",")
            if progress is not None:
                progress(stop)
    return n


def write_serial_capture(path: Path, unit: Unit, progress: Any = None) -> int:
    """The run as the bytes the unit sends on its serial port (ICD frames, the configured faults
    included): what `fluxcal decode CAPTURE --probes N` reads."""
    n = unit.n_samples
    assert n is not None
    with open(path, "wb") as fh:
        for start in range(0, n, BLOCK_SAMPLES):
            stop = min(n, start + BLOCK_SAMPLES)
            fh.write(unit.serial_bytes(start, stop))
            if progress is not None:
                progress(stop)
    return n


def write_can_log(path: Path, unit: Unit, progress: Any = None) -> int:
    """The run as a candump log of the unit's CAN frames (`(time) can0 ID#DATA`, times from the sample
    instants): what `fluxcal decode LOG --can --probes N` reads, and python-can's logger writes."""
    n = unit.n_samples
    assert n is not None
    rate = unit.config.rate_hz
    with open(path, "w", encoding="ascii", newline="\n") as fh:
        for start in range(0, n, BLOCK_SAMPLES):
            stop = min(n, start + BLOCK_SAMPLES)
            ids, payloads, sample_of = unit.can_frames(start, stop)
            t = 1.7e9 + sample_of / rate                   # an epoch-like time base, as candump writes
            fh.writelines(f"({ts:.6f}) can0 {cid:03X}#{data.tobytes().hex().upper()}\n"
                          for ts, cid, data in zip(t.tolist(), ids.tolist(), payloads))
            if progress is not None:
                progress(stop)
    return n


#: output suffix -> what is written
WRITERS = (".csv", ".mcap", ".bin", ".log")


def _tmp(path: Path) -> Path:
    # a new file under a name nobody could plant a link at; same suffix, so writers that look at it still see
    # .csv / .mcap / .json
    return temp_beside(path)


def _mcap_writer(out: Path) -> Any:
    """fluxcal.service.io.recordings.writer.write_recording(path, blocks, unit=, probe_names=, truth=), or a clear error."""
    from fluxcal.service.io.recordings.writer import write_recording

    return write_recording


def _write_mcap(writer: Any, path: Path, unit: Unit, unit_name: str, truth: dict[str, Any],
                progress: Any = None) -> int:
    n = unit.n_samples
    assert n is not None

    def blocks() -> Any:
        for a in range(0, n, BLOCK_SAMPLES):
            yield unit.digitise(a, min(n, a + BLOCK_SAMPLES)).to_block()
            if progress is not None:
                progress(min(n, a + BLOCK_SAMPLES))

    writer(path, blocks(), unit=unit_name, probe_names=[p.name for p in unit.config.probes], truth=truth)
    return n


@dataclass
class SimulateOptions:
    out: str
    config: str | None = None             # the [sim] section to simulate (None: the built-in gradiometer)


@dataclass
class SimulateResult(Result):
    """Simulated data written: how many samples, and the truth file beside them."""

    samples: int = 0
    truth: str = ""

    def as_dict(self) -> dict[str, Any]:
        return {**super().as_dict(), "samples": self.samples, "truth": self.truth}


def options(args: Any) -> SimulateOptions:
    return SimulateOptions(out=args.out, config=args.config)


def main(args: Any) -> int:
    """The command line: what was written said on stderr (the data go to --out)."""
    return execute(options(args), Said("simulate", stderr_say("simulate"))).status


def execute(opts: SimulateOptions, said: Said) -> SimulateResult:
    """`fluxcal simulate`: a simulated unit's data and its truth, written atomically."""
    from fluxcal.service.wiring.commands.notes import check_output_file

    out = Path(opts.out)
    check_output_file(out, example="sim.csv")
    suffix = out.suffix.lower()
    if suffix not in WRITERS:
        raise DataError(f"{out}: unknown output type {out.suffix!r} (allowed: {', '.join('FILE' + s for s in WRITERS)}: "
                        f"lab CSV, MCAP recording, the unit's serial bytes, a candump log of its CAN frames)")
    sim, unit_name = load_simulation(opts.config)
    mcap_writer = _mcap_writer(out) if suffix == ".mcap" else None
    if sim.n_samples is None:
        raise ConfigError(f"{opts.config or 'built-in'}: sim.duration_s: 0 means 'until stopped', which cannot be "
                          f"written to a file; give a duration in seconds")
    unit = Unit(sim)
    tpath = free_truth_path(out)
    truth = unit.world.truth()
    truth.update({"unit": unit_name, "data_file": out.name, "probe_names": [p.name for p in sim.probes]})

    bar = Progress(sim.n_samples, "simulate")
    progress = bar.to
    # both files are written beside their targets under temporary names and renamed at the end:
    # an interrupted or failed run leaves neither half-written
    tmp_data, tmp_truth = _tmp(out), _tmp(tpath)
    try:
        with open(tmp_truth, "w", encoding="utf-8") as fh:
            json.dump(truth, fh, indent=1)
            fh.write("\n")
        if suffix == ".csv":
            n = write_csv(tmp_data, unit, unit_name, tpath.name, progress)
        elif suffix == ".mcap":
            n = _write_mcap(mcap_writer, tmp_data, unit, unit_name, truth, progress)
        elif suffix == ".bin":
            n = write_serial_capture(tmp_data, unit, progress)
        else:
            n = write_can_log(tmp_data, unit, progress)
        os.replace(tmp_data, out)
        os.replace(tmp_truth, tpath)
    finally:
        bar.close()
        tmp_data.unlink(missing_ok=True)
        tmp_truth.unlink(missing_ok=True)
    effects = ", ".join(unit.world.active_effects) or "none"
    _say_faults(said, unit, [p.name for p in sim.probes], suffix)
    if tpath != truth_path(out):
        said("truth", f"{truth_path(out).name} describes another data file beside it: this run's truth is "
                      f"{tpath.name}", level="say")
    said("written", f"{n} samples of {sim.n_probes} probe(s) ({n / sim.rate_hz:g} s at {sim.rate_hz:g} Hz, unit "
                    f"{unit_name!r}, motion {sim.motion.kind}, effects: {effects}) -> {out}; truth -> {tpath}",
         level="say")
    return SimulateResult("simulate", opts.config or "built-in", notes=said.notes, written=[str(out), str(tpath)],
                          samples=int(n), truth=str(tpath))
