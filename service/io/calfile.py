"""The calibration file: versioned JSON that `fit` writes and `diagnose` and the service read.

    {"format": "fluxcal.calibration", "version": 1, "created": "...", "fluxcal": "0.1.0",
     "method": "ellipsoid", "align": "rotation" | null, "total_nT": 52500.0 | null,
     "effects": [...], "effect_params": {...}, "span": {"t0_s": ..., "t1_s": ..., "n_samples": ...},
     "probes": [{"name": "s1", "offset_nT": [3], "matrix": [[3]x3], "offset_se_nT": [3] (null = unknown),
                 "matrix_se": [[3]x3], "params": {...}}, ...],
     "diagnostics": {...},
     "unit": {"name": "grad1", "probes": {"s1": "<serial>", ...}}}     (optional: the unit it was made for; a
                                                                        bare name is read as {"name": ...})

Written atomically (temporary file, then rename). A file of another format or version, or a
damaged one, is refused with a DataError naming the file and the problem.
"""

from __future__ import annotations

import datetime as _dt
import json
import math
import re
from pathlib import Path
from typing import Any

import numpy as np

from fluxcal.drivers.errors import DataError
from fluxcal.drivers.inputs import read_small
from fluxcal.drivers.outputs import replacing
from fluxcal.service.numerics.calib.model import ArrayCalibration, ProbeCalibration

FORMAT = "fluxcal.calibration"
VERSION = 1


def _jsonable(x: Any) -> Any:
    if isinstance(x, np.ndarray):
        return _jsonable(x.tolist())
    if isinstance(x, (np.floating, float)):
        return None if not math.isfinite(float(x)) else float(x)
    if isinstance(x, np.integer):
        return int(x)
    if isinstance(x, dict):
        return {str(k): _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    return x


def calibration_to_dict(cal: ArrayCalibration) -> dict[str, Any]:
    """The file's JSON object (non-finite numbers become null: "unknown")."""
    try:
        from importlib.metadata import version

        ver = version("fluxcal")
    except Exception:
        ver = "unknown"
    return _jsonable({
        "format": FORMAT, "version": VERSION,
        "created": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
        "fluxcal": ver, "method": cal.method, "align": cal.align, "total_nT": cal.total_nT,
        "effects": list(cal.effects), "effect_params": cal.effect_params,
        "span": {"t0_s": cal.span[0], "t1_s": cal.span[1], "n_samples": cal.span[2]},
        "probes": [{"name": p.name, "offset_nT": p.offset_nT, "matrix": p.matrix, "offset_se_nT": p.offset_se_nT,
                    "matrix_se": p.matrix_se, "params": p.params, "model_order": p.model_order,
                    "warnings": list(p.warnings)} for p in cal.probes],
        "diagnostics": cal.diagnostics,
        **({"unit": cal.unit} if cal.unit else {}),
    })


def save_calibration(cal: ArrayCalibration, path: str | Path) -> None:
    """Write `cal` to `path` atomically: a temporary file in the same directory, fsync, rename; a
    crash leaves the old file or the new one, never half of one."""
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    text = json.dumps(calibration_to_dict(cal), indent=1, allow_nan=False)
    with replacing(p, "w", fsync=True) as f:          # a link at the path replaced, never written through
        f.write(text + "\n")


#: the largest calibration file or payload read (one written by `fit --out` is a few kB; with effects tens of kB)
MAX_CALIBRATION_BYTES = 1 << 20
#: the deepest nesting of arrays and objects taken (a calibration file nests 4 deep)
MAX_JSON_DEPTH = 16


def load_calibration(path: str | Path) -> ArrayCalibration:
    """Read a calibration file (`fit --out`'s, or `fit --json`'s report of a fit without effects); DataError naming
    the file and the problem (missing, not a regular file, too large, another format or version, not JSON, a missing
    key, a wrong shape, a NaN)."""
    return calibration_from_json(read_calibration_text(path), origin=str(Path(path)))


def read_calibration_text(path: str | Path) -> str:
    """The text of a calibration file, bounded: a FIFO, a device or /dev/zero is refused before it is opened
    for reading (nothing waits on it or reads it without end), and so is a file over MAX_CALIBRATION_BYTES."""
    p = Path(path)
    raw = read_small(p, "calibration file", MAX_CALIBRATION_BYTES, DataError,
                     f"more than {MAX_CALIBRATION_BYTES:,} bytes: too large for a calibration file (one written by "
                     f"`fluxcal fit --out` is a few kB)")
    try:
        return raw.decode("utf-8")
    except UnicodeDecodeError as e:
        raise DataError(f"{p}: cannot read the calibration file: not UTF-8 text ({e.reason} at byte {e.start})") \
            from None


_JSON_TOKENS = re.compile(rb'"(?:[^"\\]|\\.)*"|[\[\]{}]')


def json_depth(raw: bytes) -> int:
    """The deepest nesting of arrays and objects in JSON text (strings skipped), found without parsing it:
    text nested thousands deep is refused before json.loads would recurse into it."""
    depth = worst = 0
    for m in _JSON_TOKENS.finditer(raw):
        c = m.group()[0]
        if c in b"[{":
            depth += 1
            worst = max(worst, depth)
        elif c in b"]}":
            depth -= 1
    return worst


def parse_json(text: str, origin: str, *, max_bytes: int = MAX_CALIBRATION_BYTES,
               max_depth: int = MAX_JSON_DEPTH) -> Any:
    """json.loads bounded in size and depth; DataError naming `origin` and the bound (never a RecursionError
    or a MemoryError escaping)."""
    raw = text.encode("utf-8", errors="surrogatepass")
    if len(raw) > max_bytes:
        raise DataError(f"{origin}: {len(raw):,} bytes of JSON (at most {max_bytes:,})")
    depth = json_depth(raw)
    if depth > max_depth:
        raise DataError(f"{origin}: JSON nested {depth} deep (at most {max_depth})")
    try:
        return json.loads(text)
    except json.JSONDecodeError as e:
        raise DataError(f"{origin}: damaged calibration file (not JSON: {e.msg} at line {e.lineno})") from None
    except (RecursionError, MemoryError, ValueError) as e:
        raise DataError(f"{origin}: not readable JSON ({type(e).__name__})") from None


def calibration_from_json(text: str, origin: str = "<calibration>") -> ArrayCalibration:
    """The ArrayCalibration of a calibration file's text. Text that is not JSON at all (a CSV given by
    mistake) is refused as not a calibration, quoting only the start of its first line."""
    if text.strip() and not text.lstrip().startswith("{"):      # empty: a truncated file, "damaged" below
        raise DataError(f"{origin}: not a calibration file: expected a calibration JSON written by "
                        f"`fluxcal fit --out`; it begins {excerpt(text)}")
    return calibration_from_dict(parse_json(text, origin), origin)


def excerpt(text: str, limit: int = 60) -> str:
    """The start of `text` quoted for a message: its first line, at most `limit` characters, and `...`
    when there is more; a message never carries a whole payload.

    >>> excerpt("t,s1_x,s1_y\\n0,1,2")
    "'t,s1_x,s1_y' ..."
    """
    body = text.strip()
    first = body.split("\n", 1)[0][:limit]
    return repr(first) + (" ..." if len(first) < len(body) else "")


def _numbers_only(v: Any, allow_null: bool, depth: int = 0) -> bool:
    """Whether v is numbers (not booleans, not strings: "1e3" and true are no offsets), nested lists of them,
    or null where allowed."""
    if isinstance(v, bool):
        return False
    if isinstance(v, (int, float)):
        return True
    if v is None:
        return allow_null
    return isinstance(v, list) and depth < 3 and all(_numbers_only(x, allow_null, depth + 1) for x in v)


def _array(v: Any, shape: tuple[int, ...], key: str, origin: str, allow_null: bool = False) -> np.ndarray:
    if not allow_null and _numbers_only(v, True) and not _numbers_only(v, False):
        raise DataError(f"{origin}: {key}: holds non-finite values (null)")
    if not _numbers_only(v, allow_null):
        raise DataError(f"{origin}: {key}: expected numbers of shape {shape}" + (" or null" if allow_null else "") +
                        f", got {excerpt(json.dumps(v, default=str)[:200], 40)}")
    try:
        with np.errstate(over="ignore"):
            a = np.array(v if not allow_null else _nulls(v), dtype=float)
    except (TypeError, ValueError, OverflowError):
        raise DataError(f"{origin}: {key}: expected numbers of shape {shape}") from None
    if a.shape != shape:
        raise DataError(f"{origin}: {key}: expected shape {shape}, got {a.shape}")
    if not allow_null and not np.all(np.isfinite(a)):
        raise DataError(f"{origin}: {key}: holds non-finite values")
    return a


def _nulls(v: Any) -> Any:
    if v is None:
        return np.nan
    if isinstance(v, list):
        return [_nulls(x) for x in v]
    return v


def _total(v: Any, origin: str) -> float | None:
    if v is None:
        return None
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v <= 0:
        raise DataError(f"{origin}: total_nT: expected a positive number or null, got {v!r}")
    return float(v)


def _unit(v: Any, origin: str) -> dict[str, Any]:
    """The unit a calibration was made for: "grad1", or {"name": "grad1", "probes": {"s1": "<serial>", ...}}."""
    if v is None:
        return {}
    if isinstance(v, str):
        v = {"name": v}
    probes = v.get("probes", {}) if isinstance(v, dict) else None
    if not isinstance(v, dict) or not isinstance(v.get("name", ""), str) or not isinstance(probes, dict) \
            or not all(isinstance(k, str) and isinstance(s, str) for k, s in probes.items()):
        raise DataError(f"{origin}: damaged calibration file (unit must be a unit's name, or {{\"name\": ..., "
                        f"\"probes\": {{probe: serial}}}})")
    return {"name": v.get("name", ""), "probes": dict(probes)} if probes else {"name": v.get("name", "")}


def is_report(d: Any) -> bool:
    """Whether parsed JSON is `fluxcal fit --json`'s report (sensors, no "format"), not a calibration file."""
    return isinstance(d, dict) and "format" not in d and isinstance(d.get("sensors"), list)


def calibration_from_report(d: dict, origin: str = "<calibration>", *, linear_part: bool = False) -> ArrayCalibration:
    """The calibration a `fluxcal fit --json` report carries (docs/contracts.md: its sensors' names, offsets,
    matrices and their errors), checked as a calibration file is. Its effects' parameters are reported, not stored as
    a calibration applies them: a report with effects is refused unless `linear_part` (the linear part alone asked
    for, as `diagnose --calibration` holds it), where the effects are left out."""
    effects = d.get("effects") or []
    if effects and not linear_part:
        raise DataError(f"{origin}: the `fluxcal fit --json` report of a fit with effects ({', '.join(map(str, effects))}"
                        f"): its effect parameters are reported, not stored as a calibration applies them; write the "
                        f"calibration with `fluxcal fit ... --out FILE`")
    unknown = {"offset_se_nT": [None] * 3, "matrix_se": [[None] * 3] * 3}     # a report written by hand has none
    keys = ("name", "offset_nT", "matrix", "offset_se_nT", "matrix_se", "params", "model_order")
    probes = [{k: s[k] if s.get(k) is not None else unknown.get(k) for k in keys} if isinstance(s, dict) else s
              for s in d["sensors"]]
    return calibration_from_dict({"format": FORMAT, "version": VERSION, "method": d.get("method") or "fit",
                                  "align": d.get("align"), "probes": probes}, origin)


def calibration_from_dict(d: Any, origin: str = "<calibration>") -> ArrayCalibration:
    """The ArrayCalibration of a parsed calibration file, or of `fit --json`'s report (calibration_from_report);
    DataError naming `origin` and the problem."""
    if is_report(d):
        return calibration_from_report(d, origin)
    if not isinstance(d, dict) or d.get("format") != FORMAT:
        raise DataError(f"{origin}: not a fluxcal calibration file (expected \"format\": \"{FORMAT}\")")
    if d.get("version") != VERSION:
        raise DataError(f"{origin}: calibration file version {d.get('version')!r}; this fluxcal reads version "
                        f"{VERSION} — refit with `fluxcal fit` or use the fluxcal that wrote it")
    try:
        if not isinstance(d["probes"], list) or not d["probes"]:
            raise DataError(f"{origin}: damaged calibration file (\"probes\" must be a non-empty list)")
        probes = []
        for i, pd in enumerate(d["probes"]):
            key = f"probes[{i}]"
            if not isinstance(pd, dict):
                raise DataError(f"{origin}: damaged calibration file ({key} is not an object)")
            params = pd.get("params") or {}
            if not isinstance(params, dict):
                raise DataError(f"{origin}: damaged calibration file ({key}.params is not an object)")
            if not isinstance(pd.get("name"), str) or not pd["name"]:
                raise DataError(f"{origin}: damaged calibration file ({key}.name must be a probe's name)")
            probes.append(ProbeCalibration(
                pd["name"], _array(pd["offset_nT"], (3,), f"{key}.offset_nT", origin),
                _array(pd["matrix"], (3, 3), f"{key}.matrix", origin),
                _array(pd.get("offset_se_nT"), (3,), f"{key}.offset_se_nT", origin, True),
                _array(pd.get("matrix_se"), (3, 3), f"{key}.matrix_se", origin, True),
                dict(params), str(pd.get("model_order") or "full"),
                [str(w) for w in pd.get("warnings") or []]))
        for i, pr in enumerate(probes):
            if not np.linalg.cond(pr.matrix) < 1e12:
                raise DataError(f"{origin}: probes[{i}].matrix is singular; the file is damaged")
        names = [p.name for p in probes]
        if len(set(names)) != len(names):
            raise DataError(f"{origin}: damaged calibration file (probe names repeat: {names})")
        align = d.get("align")
        if align is not None and not isinstance(align, str):
            raise DataError(f"{origin}: damaged calibration file (align must be a name or null)")
        effects = d.get("effects") or []
        if not isinstance(effects, list) or not all(isinstance(e, str) for e in effects):
            raise DataError(f"{origin}: damaged calibration file (effects must be a list of effect names)")
        for k in ("effect_params", "diagnostics", "span"):
            if not isinstance(d.get(k) or {}, dict):
                raise DataError(f"{origin}: damaged calibration file ({k} must be an object)")
        span = d.get("span") or {}
        unit = _unit(d.get("unit"), origin)
        return ArrayCalibration(method=str(d["method"]), align=align, probes=probes, unit=unit,
                                total_nT=_total(d.get("total_nT"), origin), effects=list(effects),
                                effect_params=dict(d.get("effect_params") or {}),
                                diagnostics=dict(d.get("diagnostics") or {}),
                                span=(float(span.get("t0_s", 0.0)), float(span.get("t1_s", 0.0)),
                                      int(span.get("n_samples", 0))))
    except (KeyError, TypeError, ValueError, AttributeError) as e:
        if isinstance(e, DataError):
            raise
        raise DataError(f"{origin}: damaged calibration file (missing or malformed {e})") from None
