"""What the service opens from its configuration besides the source: the calibration it starts from, the
MCAP logger, and what is said about the bus."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Callable

from drivers.errors import ConfigError, DataError
from service.io.calfile import calibration_to_dict, load_calibration
from service.numerics.calib.plausible import check_calibration
from service.io.recordings.writer import McapLogger

from .config import FluxcalConfig


def learned_on(cfg: FluxcalConfig) -> dict[str, str]:
    """What a calibration learned by this service is recorded as learned on: the unit and its source kind."""
    return {"unit": cfg.unit.name, "source": str(getattr(cfg.source, "kind", "sim"))}


def check_for_unit(cal: Any, cfg: FluxcalConfig) -> None:
    """The one check a calibration passes before the service uses it, by `apply`, reload or calibration.initial:
    this unit's probes and physics (service.numerics.calib.plausible), and no effect terms (the service takes
    those by `add-effect`, refitted on its own window: from a file they would be silently dropped)."""
    if cal.effects:
        raise DataError(f"fails the effects check: the calibration carries effect terms ({', '.join(cal.effects)}) "
                        f"that the running service cannot take from a file; use a calibration fitted without "
                        f"--effects, then `add-effect NAME` (refitted on the service's own window), or correct "
                        f"offline with `fluxcal fit --effects`")
    check_calibration(cal, cfg.probe_names, cfg.calibration.limits())


def initial_calibration(cfg: FluxcalConfig, say: Callable[[str], None]) -> Any:
    """calibration.initial if given (whatever it was learned on: naming it says so), else the persisted
    calibration.file if it reads and was learned on this unit and source kind, else None (learn online)."""
    c = cfg.calibration
    if c.initial:
        try:
            cal = load_calibration(c.initial)
            check_for_unit(cal, cfg)
        except (DataError, OSError) as e:
            raise ConfigError(f"calibration.initial: {e}") from None
        origin = cal.diagnostics.get("learned_on")
        foreign = f" (learned on unit {origin.get('unit')}, source {origin.get('source')})" \
            if isinstance(origin, dict) and origin != learned_on(cfg) else ""
        say(f"starting from calibration {c.initial}{foreign}")
        persisted = Path(c.file)
        if persisted.exists() and persisted.resolve() != Path(c.initial).resolve():
            try:
                if load_calibration(persisted).diagnostics.get("applied"):
                    say(f"the calibration applied by command and persisted in {persisted} is not used: "
                        f"calibration.initial names another (remove the key to reload the applied one)")
            except DataError:
                pass
        return cal
    path = Path(c.file)
    if path.exists():
        try:
            cal = load_calibration(path)
            check_for_unit(cal, cfg)
        except DataError as e:
            say(f"ignoring the persisted calibration: {e}; learning online")
        else:
            origin = cal.diagnostics.get("learned_on")
            if isinstance(origin, dict) and origin != learned_on(cfg):
                say(f"ignoring the persisted calibration {path}: it was learned on unit {origin.get('unit')} from a "
                    f"{origin.get('source')} source, this is unit {cfg.unit.name} on {learned_on(cfg)['source']}; "
                    f"learning online (to start from it anyway: calibration.initial = \"{path}\")")
            else:
                say(f"reloaded the persisted calibration {path}" + (
                    " (applied by command: held until `reset`)" if cal.diagnostics.get("applied") else ""))
                return cal
    say("no calibration yet: learning online; corrected output starts once it passes the quality gate")
    return None


def open_logger(cfg: FluxcalConfig, calibration: Any, say: Callable[[str], None]) -> McapLogger | None:
    """The MCAP logger of [mcap] (None when disabled), with the calibration the run starts from as its first
    event; ConfigError naming mcap.dir when nothing can be recorded there."""
    if not cfg.mcap.enabled:
        return None
    logger = McapLogger(cfg.mcap.dir, unit=cfg.unit.name, rotate_mb=cfg.mcap.rotate_mb,
                        rotate_s=cfg.mcap.rotate_s, chunk_size=cfg.mcap.chunk_kb * 1024,
                        flush_interval_s=cfg.mcap.flush_s,
                        metadata={"unit": cfg.unit.name, "n_probes": str(cfg.unit.n_probes),
                                  "lsb_nT": repr(cfg.unit.lsb_nT),
                                  "probe_names": json.dumps(cfg.probe_names),
                                  "positions_m": json.dumps(cfg.positions_m),
                                  "config": json.dumps(cfg.raw)})
    # replay starts from the same calibration, so it reproduces this run bit for bit
    logger.write_event({"kind": "initial", "seq": 0, "calibration":
                        None if calibration is None else calibration_to_dict(calibration)})
    st = logger.status()
    if st["current"] is None:
        logger.close()
        # nothing could be opened: say so now, not after a day of data that went nowhere
        raise ConfigError(f"mcap.dir: {str(cfg.mcap.dir)!r}: cannot record there: {st['last_error']} "
                          f"(allowed: a directory this user can create and write into; or set "
                          f"[mcap] enabled = false to run without recording)")
    say(f"recording to {cfg.mcap.dir}/")
    return logger


def say_bus(cfg: FluxcalConfig, say: Callable[[str], None]) -> None:
    """Where the service publishes, and a warning for every endpoint other hosts reach in clear text."""
    say(f"publishing on zenoh under fluxcal/{cfg.unit.name}/ "
        f"(listen {', '.join(getattr(cfg.zenoh, 'listen', []) or ['-'])}"
        f"{', TLS' if cfg.zenoh.tls.enabled else ''}"
        f"{', access control' if cfg.zenoh.access.enabled else ''})")
    for ep in cfg.zenoh.exposed():
        say(f"warning: {ep} is reachable from other hosts in clear text and without access control: "
            f"anyone on that network can read the streams and send commands (docs/security.md)")
