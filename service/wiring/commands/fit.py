"""`fluxcal fit DATA`: a calibration from lab data, as a readable summary, JSON, or a calibration file."""

from __future__ import annotations

import json
import sys
from argparse import Namespace

import numpy as np

from service.io.calfile import save_calibration
from service.io.recordings.labdata import load_data
from service.numerics.calib.coverage import coverage
from service.wiring.fitting import contract_json, fit_array, residual_channels, rms, uncalibrated_channels


def _say(msg: str) -> None:
    if sys.stderr.isatty():
        print(f"\r\033[K{msg}", end="", file=sys.stderr, flush=True)


def load_optional_config(path: str | None):
    if not path:
        return None
    from service.wiring.config import load_config

    return load_config(path)


def configured_total(cfg) -> float | None:
    if cfg is None:
        return None
    if cfg.estimator.total_nT is not None:
        return cfg.estimator.total_nT
    return None


def positions(cfg, n_probes: int):
    if cfg is None or cfg.unit.n_probes != n_probes:
        return None
    pos = np.asarray(cfg.positions_m, float)
    return pos if np.ptp(pos, axis=0).any() else None


def main(args: Namespace) -> int:
    data = load_data(args.data)
    cfg = load_optional_config(args.config)
    cal, total = fit_array(data, method=args.method, align=args.align, configured_total_nT=configured_total(cfg),
                           positions_m=positions(cfg, data.block.n_probes), progress=_say)
    if args.effects:
        from service.numerics.engine import fit_with_effects

        _say(f"fitting effects {', '.join(args.effects)}")
        ef, _ = fit_with_effects(data, args.effects, cal, total_nT=configured_total(cfg),
                                 positions_m=positions(cfg, data.block.n_probes))
        method, align = cal.method, cal.align
        cal = ef.calibration()
        cal.method, cal.align = method, align
        channels = {name: values for name, values in ef.result.channels.as_dict().items()}
    else:
        channels = residual_channels(data, cal, total)
    if sys.stderr.isatty():
        print("\r\033[K", end="", file=sys.stderr)
    before = uncalibrated_channels(data, total)
    cal.diagnostics.update({"rms_before_nT": {k: rms(v) for k, v in before.items()},
                            "rms_after_nT": {k: rms(v) for k, v in channels.items()},
                            "total_field": total.source})
    if args.out:
        save_calibration(cal, args.out)
    result = contract_json(cal, channels, data.probe_names)
    if args.json:
        print(json.dumps(result))
        return 0
    print(_summary(data, cal, channels, before, total.source, result))
    if args.out:
        print(f"calibration written to {args.out}")
    return 0


def _fmt_param(value, se) -> str:
    """A parameter of any shape, with its standard error when there is one: 6 significant digits."""
    def one(v):
        return f"{v:.6g}" if isinstance(v, (int, float)) and not isinstance(v, bool) else str(v)

    def seq(v):
        return "[" + ", ".join(one(x) for x in v) + "]" if isinstance(v, (list, tuple)) else one(v)

    if se is None or (isinstance(se, float) and not np.isfinite(se)):
        return seq(value)
    return f"{seq(value)} ± {seq(se)}"


def _fmt_pm(v: float, se: float, digits: int = 3) -> str:
    w = digits + 7
    return f"{v:{w}.{digits}f} ± {se:.1e}" if np.isfinite(se) else f"{v:{w}.{digits}f} ±     n/a"


def _summary(data, cal, channels, before, total_source, result) -> str:
    b = data.block
    lines = [f"{data.path}: {b.n_samples} samples, {b.n_probes} probe(s), {b.t_s[-1] - b.t_s[0]:.1f} s; "
             f"method {cal.method}, align {cal.align or '-'}, effects {', '.join(cal.effects) or '-'}; "
             f"total field from {total_source}"]
    for k, p in enumerate(cal.probes):
        lines.append(f"\n{p.name}")
        lines.append("  offset nT  " + "  ".join(_fmt_pm(v, s) for v, s in zip(p.offset_nT, p.offset_se_nT)))
        for i in range(3):
            lines.append("  matrix     " + "  ".join(_fmt_pm(v, s, 5) for v, s in zip(p.matrix[i], p.matrix_se[i])))
        for key, val in p.params.items():
            if key in ("offset_nT", "samples", "align") or not isinstance(val, dict):
                continue
            lines.append(f"  {key:10s} {_fmt_param(val.get('value'), val.get('se'))} {val.get('unit', '')}".rstrip())
        cov = coverage(b.field_nT[:, k])
        lines.append(f"  coverage   {cov.fraction:.0%} of directions" + (f" — {cov.reason}" if cov.reason else ""))
        lines.append("  " + cov.text_map.replace("\n", "\n  "))
    if cal.effect_params:
        lines.append("\neffect parameters")
        for eff, params in cal.effect_params.items():
            for name, v in params.items():
                se = v.get("se")
                lines.append(f"  {eff:12s} {name:28s} {v['value']:.6g} ± {se:.3g} {v.get('unit', '')}" if se is not None
                             else f"  {eff:12s} {name:28s} {v['value']:.6g} (undetermined) {v.get('unit', '')}")
    lines.append("\nresidual RMS, nT          before       after")
    for name in channels:
        lines.append(f"  {name:20s} {rms(before[name]):12.2f} {rms(channels[name]):11.3f}")
    lines.append(f"  {'all':20s} {rms(np.concatenate(list(before.values()))):12.2f} {result['rms_nT']:11.3f}")
    return "\n".join(lines)
