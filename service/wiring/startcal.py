"""The calibration the service starts from: calibration.initial, else the one persisted in calibration.file if it
was learned on this unit and source kind, else none (learn online); and the one check every calibration passes
before the service uses it (apply, reload, calibration.initial)."""

from __future__ import annotations

import errno
import os
from pathlib import Path
from typing import Any, Callable

from fluxcal.drivers.errors import ConfigError, DataError
from fluxcal.service.io.calfile import load_calibration, save_calibration
from fluxcal.service.numerics.calib.plausible import check_calibration

from .config import FluxcalConfig
from .identity import check_identity, judge_on_data, unit_identity


def _open_lock(path: Path) -> Any:
    """The lock file beside calibration.file, read and written without following a symbolic link: a link planted
    there is removed, its target never truncated (drivers.outputs.open_output does the same for outputs)."""
    flags = os.O_RDWR | os.O_CREAT | getattr(os, "O_NOFOLLOW", 0) | getattr(os, "O_CLOEXEC", 0)
    try:
        fd = os.open(path, flags, 0o666)
    except OSError as e:
        if e.errno != errno.ELOOP:
            raise
        os.unlink(path)
        fd = os.open(path, flags | os.O_EXCL, 0o666)
    return os.fdopen(fd, "r+")


def learned_on(cfg: FluxcalConfig) -> dict[str, str]:
    """What a calibration learned by this service is recorded as learned on: the unit and its source kind."""
    return {"unit": cfg.unit.name, "source": str(cfg.source.kind)}


def stamp(cal: Any, cfg: FluxcalConfig, applied: bool) -> None:
    """Before the calibration in use persists: what it was learned on, whether it was applied (reloaded held), and
    the unit it was made for (this one: anything else was refused on its way in)."""
    cal.diagnostics["learned_on"] = learned_on(cfg)
    cal.diagnostics["applied"] = applied
    ours = unit_identity(cfg)
    probes = {**(cal.unit.get("probes") or {}), **ours.get("probes", {})}
    cal.unit = {"name": ours["name"], **({"probes": probes} if probes else {})}


def check_for_unit(cal: Any, cfg: FluxcalConfig) -> None:
    """The one check a calibration passes before the service uses it, by `apply`, reload or calibration.initial:
    made for this unit (fluxcal.service.wiring.identity: its name, its probes' serial numbers), this unit's probes and
    physics (fluxcal.service.numerics.calib.plausible), and no effect terms (the service takes those by `add-effect`,
    refitted on its own window: from a file they would be silently dropped). `apply` is also judged on the data
    (identity.judge_on_data), which only the running service has."""
    check_identity(cal, cfg)
    if cal.effects:
        raise DataError(f"fails the effects check: the calibration carries effect terms ({', '.join(cal.effects)}) "
                        f"that the running service cannot take from a file; use a calibration fitted without "
                        f"--effects, then `add-effect NAME` (refitted on the service's own window), or correct "
                        f"offline with `fluxcal fit --effects`")
    check_calibration(cal, cfg.probe_names, cfg.calibration.limits())


def initial_calibration(cfg: FluxcalConfig, say: Callable[[str], None],
                        refused: Callable[[], None] = lambda: None) -> Any:
    """calibration.initial if given (learned on another source kind: naming it says so; made for another unit:
    refused), else the persisted calibration.file if it reads and was learned on this unit and source kind, else
    None (learn online). `refused()` is called when a persisted calibration is not taken (the summary counts it)."""
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
            refused()
            say(f"ignoring the persisted calibration: {e}; learning online")
        else:
            origin = cal.diagnostics.get("learned_on")
            if isinstance(origin, dict) and origin != learned_on(cfg):
                refused()
                say(f"ignoring the persisted calibration {path}: it was learned on unit {origin.get('unit')} from a "
                    f"{origin.get('source')} source, this is unit {cfg.unit.name} on {learned_on(cfg)['source']}; "
                    f"learning online (to start from it anyway: calibration.initial = \"{path}\")")
            else:
                say(f"reloaded the persisted calibration {path}" + (
                    " (applied by command: held until `reset`)" if cal.diagnostics.get("applied") else ""))
                return cal
    say("no calibration yet: learning online; corrected output starts once it passes the quality gate")
    return None


def calibration_from_payload(payload: Any, cfg: FluxcalConfig | None = None):
    """The calibration an `apply` carries: its JSON content, never a path (a command from the network reads
    no file on this host: anything that is not a JSON object is refused before any filesystem access, with
    the same answer whether or not such a file exists). Bounded in size and depth; checked against this unit
    and physics (fluxcal.service.numerics.calib.plausible) when `cfg` is given; effect terms are refused (the running
    service takes effects by `add-effect`, refitted on its own window)."""
    from fluxcal.service.io.calfile import MAX_CALIBRATION_BYTES, calibration_from_json, excerpt

    if isinstance(payload, (bytes, bytearray)):
        try:
            payload = bytes(payload).decode("utf-8")
        except UnicodeDecodeError:
            raise DataError("apply: the payload is not UTF-8 text; expected a calibration's JSON content") from None
    if not isinstance(payload, str):
        raise DataError(f"apply: expected a calibration's JSON content, got {type(payload).__name__}")
    text = payload.strip()
    if len(text) > MAX_CALIBRATION_BYTES:
        raise DataError(f"apply: the payload ({len(text):,} characters) is too large for a calibration (at most "
                        f"{MAX_CALIBRATION_BYTES:,})")
    if not text.startswith("{"):
        raise DataError(f"apply: the payload ({len(text):,} characters) is not a calibration's JSON content; apply "
                        f"takes the content of a file written by `fluxcal fit --out`, never a path (the service "
                        f"reads no file a command names: `fluxcal command apply FILE` sends the file's content); it "
                        f"begins {excerpt(text, 24)}")
    cal = calibration_from_json(text, origin="apply payload")
    if cfg is not None:
        try:
            check_for_unit(cal, cfg)
        except DataError as e:
            raise DataError(f"apply: {e}; nothing was applied") from None
    return cal


class Keeper:
    """The running service's calibrations beyond the pipeline: `apply`'s calibration checked (calibration_from_payload)
    and judged on the service's own data (identity.judge_on_data), the one in use saved (stamp), and what was
    refused or could not be saved counted (health: calibrations_refused, persist_failures; FaultWatch says them
    with their counts and in the summary at stop). A save's failure is said once for each reason, not at every
    check of the gate."""

    def __init__(self, cfg: FluxcalConfig, say: Callable[[str], None]) -> None:
        self.cfg, self.say = cfg, say
        self.calibrations_refused = 0       # by apply, or the persisted one at start
        self.persist_failures = 0
        self.doubted = 0                    # calibrations in use that failed the data check once data came
        self._said = ""
        self._lock: Any = None              # calibration.file's lock while the service runs (claim)

    def counts(self) -> dict[str, int]:
        return {"calibrations_refused": self.calibrations_refused, "persist_failures": self.persist_failures,
                "calibrations_doubted": self.doubted}

    def claim(self) -> None:
        """Hold calibration.file for this service while it runs (a lock beside it), or ConfigError where another
        running service holds it: two services given one file reloaded each other's calibration at their restart,
        or overwrote it, without a word (a field trial). Where no lock can be taken (a read-only folder), none is:
        the saves say what fails."""
        import fcntl

        path = Path(self.cfg.calibration.file)
        lock = path.with_name(path.name + ".lock")
        try:
            lock.parent.mkdir(parents=True, exist_ok=True)
            fh = _open_lock(lock)
        except OSError:
            return
        try:
            fcntl.flock(fh, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            fh.seek(0)
            holder = fh.read(200).strip() or "another process"
            fh.close()
            raise ConfigError(f"calibration.file = {str(path)!r} is held by another running service ({holder}): "
                              f"give each service its own calibration.file") from None
        fh.seek(0)
        fh.truncate()
        fh.write(f"unit {self.cfg.unit.name}, process {os.getpid()}")
        fh.flush()
        self._lock = fh

    def release(self) -> None:
        """Let calibration.file go (the service stops)."""
        fh, self._lock = self._lock, None
        if fh is not None:
            fh.close()

    def refused(self) -> None:
        self.calibrations_refused += 1

    def to_apply(self, payload: Any, pipeline: Any) -> Any:
        """apply's calibration, or a DataError saying why not (counted)."""
        try:
            cal = calibration_from_payload(payload, self.cfg)
            try:
                judge_on_data(cal, pipeline, self.cfg)
            except DataError as e:
                raise DataError(f"apply: {e}; nothing was applied") from None
        except DataError:
            self.calibrations_refused += 1
            raise
        return cal

    def persist(self, cal: Any, applied: bool) -> None:
        """Save the calibration in use (reloaded at the next start; held again if applied)."""
        path = Path(self.cfg.calibration.file)
        try:
            stamp(cal, self.cfg, applied)
            save_calibration(cal, path)
        except OSError as e:
            self.persist_failures += 1
            why = f"could not persist the calibration to {path}: {e}"
            if why != self._said:
                self._said = why
                self.say(f"{why}; it stays in use, but a restart would not reload it (health: persist_failures)")
