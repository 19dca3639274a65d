"""The calibration file: versioned JSON that `fit` writes and `diagnose` and the service read.

    {"format": "fluxcal.calibration", "version": 1, "created": "...", "fluxcal": "0.1.0",
     "method": "ellipsoid", "align": "rotation" | null, "total_nT": 52500.0 | null,
     "effects": [...], "effect_params": {...}, "span": {"t0_s": ..., "t1_s": ..., "n_samples": ...},
     "probes": [{"name": "s1", "offset_nT": [3], "matrix": [[3]x3], "offset_se_nT": [3] (null = unknown),
                 "matrix_se": [[3]x3], "params": {...}}, ...],
     "diagnostics": {...}}

Written atomically (temporary file, then rename). A file of another format or version, or a
damaged one, is refused with a DataError naming the file and the problem.
"""

from __future__ import annotations

import datetime as _dt
import json
import math
import os
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

from drivers.errors import DataError
from service.numerics.calib.model import ArrayCalibration, ProbeCalibration

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
    })


def save_calibration(cal: ArrayCalibration, path: str | Path) -> None:
    """Write `cal` to `path` atomically: a temporary file in the same directory, fsync, rename; a
    crash leaves the old file or the new one, never half of one."""
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    text = json.dumps(calibration_to_dict(cal), indent=1, allow_nan=False)
    fd, tmp = tempfile.mkstemp(prefix=p.name + ".", suffix=".tmp", dir=p.parent)
    try:
        with os.fdopen(fd, "w") as f:
            f.write(text + "\n")
            f.flush()
            os.fsync(f.fileno())
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)     # as any file the user writes (mkstemp makes it 0600)
        os.replace(tmp, p)
    except BaseException:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        raise


def load_calibration(path: str | Path) -> ArrayCalibration:
    """Read a calibration file; DataError naming the file and the problem (missing, another format or
    version, not JSON, a missing key, a wrong shape, a NaN)."""
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise DataError(f"{p}: calibration file not found") from None
    except (OSError, UnicodeDecodeError) as e:
        raise DataError(f"{p}: cannot read the calibration file: {e}") from None
    return calibration_from_json(text, origin=str(p))


def calibration_from_json(text: str, origin: str = "<calibration>") -> ArrayCalibration:
    """The ArrayCalibration of a calibration file's text. Text that is not JSON at all (a CSV given by
    mistake) is refused as not a calibration, quoting only the start of its first line."""
    if text.strip() and not text.lstrip().startswith("{"):      # empty: a truncated file, "damaged" below
        raise DataError(f"{origin}: not a calibration file: expected a calibration JSON written by "
                        f"`fluxcal fit --out`; it begins {excerpt(text)}")
    try:
        d = json.loads(text)
    except json.JSONDecodeError as e:
        raise DataError(f"{origin}: damaged calibration file (not JSON: {e.msg} at line {e.lineno})") from None
    return calibration_from_dict(d, origin)


def excerpt(text: str, limit: int = 60) -> str:
    """The start of `text` quoted for a message: its first line, at most `limit` characters, and `...`
    when there is more; a message never carries a whole payload.

    >>> excerpt("t,s1_x,s1_y\\n0,1,2")
    "'t,s1_x,s1_y' ..."
    """
    body = text.strip()
    first = body.split("\n", 1)[0][:limit]
    return repr(first) + (" ..." if len(first) < len(body) else "")


def _array(v: Any, shape: tuple[int, ...], key: str, origin: str, allow_null: bool = False) -> np.ndarray:
    try:
        a = np.array(v if not allow_null else _nulls(v), dtype=float)
    except (TypeError, ValueError):
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


def calibration_from_dict(d: Any, origin: str = "<calibration>") -> ArrayCalibration:
    """The ArrayCalibration of a parsed calibration file; DataError naming `origin` and the problem."""
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
            probes.append(ProbeCalibration(
                str(pd["name"]), _array(pd["offset_nT"], (3,), f"{key}.offset_nT", origin),
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
        span = d.get("span") or {}
        return ArrayCalibration(method=str(d["method"]), align=align, probes=probes,
                                total_nT=_total(d.get("total_nT"), origin), effects=list(d.get("effects") or []),
                                effect_params=dict(d.get("effect_params") or {}),
                                diagnostics=dict(d.get("diagnostics") or {}),
                                span=(float(span.get("t0_s", 0.0)), float(span.get("t1_s", 0.0)),
                                      int(span.get("n_samples", 0))))
    except (KeyError, TypeError, ValueError, AttributeError) as e:
        if isinstance(e, DataError):
            raise
        raise DataError(f"{origin}: damaged calibration file (missing or malformed {e})") from None
