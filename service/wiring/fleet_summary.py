"""The summary of a fleet run: one row per recording (what it gave, or why it failed), as text or JSON."""

from __future__ import annotations

from typing import Any


def _num(x: Any, fmt: str = ".3f") -> str:
    return "-" if not isinstance(x, (int, float)) or isinstance(x, bool) else format(x, fmt)


def _why(r: dict[str, Any]) -> str:
    """Why a recording failed: the error that stopped it, else the last failure it said, else its exit status."""
    if r.get("error"):
        return r["error"].splitlines()[0]
    said = [n["text"] for n in r.get("notes") or [] if n.get("level") == "error"]
    return said[-1] if said else f"exit status {r['status']}"


def warnings_of(r: dict[str, Any]) -> list[str]:
    """What a recording's command warned of as it ran (what reading lost, a stored configuration not used, data
    not in nT, ...): its notes of a warning's level, whatever their wording."""
    return [n["text"] for n in r.get("notes") or [] if n.get("level") in ("warning", "loud")]


def figures(command: str, r: dict[str, Any]) -> dict[str, Any]:
    """The few numbers of one recording's result that the table shows (and the JSON names)."""
    res = r.get("result") or {}
    if command == "fit" and res:
        sensors = res.get("sensors") or []
        cov = [s["coverage"]["fraction"] for s in sensors if isinstance(s.get("coverage"), dict)]
        return {"probes": len(sensors), "rms_nT": res.get("rms_nT"),
                "worst_scalar_rms_nT": max((s.get("scalar_rms_nT") or 0.0 for s in sensors), default=None),
                "min_coverage": min(cov) if cov else None, "warnings": len(res.get("warnings") or [])}
    if command == "diagnose" and res:
        v = res.get("verdict") or {}
        return {"verdict": v.get("kind"), "effect": v.get("effect"), "rms_nT": v.get("rms_nT"),
                "floor_nT": v.get("floor_nT"),
                "significant": [c["effect"] for c in res.get("candidates") or [] if c.get("significant")]}
    if command == "replay":
        return {"said": res.get("verdict") or ""}
    return {}


def _status(r: dict[str, Any]) -> str:
    """ok, FAILED, or ok with the count of what it warned about (a lost tail, dropped samples)."""
    n = len(warnings_of(r))
    return ("ok" if r["ok"] else "FAILED") + (f", {n} warning{'s' if n > 1 else ''}" if n else "")


def _row_json(command: str, r: dict[str, Any]) -> dict[str, Any]:
    return {"recording": r["recording"], **({"path": r["path"]} if r.get("path") else {}), "ok": r["ok"],
            "status": r["status"], "seconds": r["seconds"], "peak_rss_mb": r.get("peak_rss_mb"),
            "host": r.get("host"), "fluxcal": r.get("fluxcal"), "read_warnings": warnings_of(r),
            **({"error": _why(r), "failure": r.get("failure", "failed")} if not r["ok"] else {}),
            **({"refused": r["refused"]} if r.get("refused") else {}),
            **figures(command, r), **({"result": r["result"]} if r.get("result") is not None else {})}


def summary_json(command: str, results: list[dict[str, Any]], wall_s: float, where: str,
                 skipped: list[tuple[str, str]] | None = None, fluxcal: str | None = None,
                 workers: list[dict[str, Any]] | None = None) -> dict[str, Any]:
    """The summary for a script (docs/contracts.md): each recording's row, a failed one with its reason and the
    kind of failure; the cluster's workers and their fluxcal, where it ran on one."""
    return {"command": command, "ran_on": where, "wall_s": round(wall_s, 3), "recordings": len(results),
            "failed": sum(not r["ok"] for r in results),
            "with_warnings": sum(bool(warnings_of(r)) for r in results),
            **({"fit_warned": sum(bool(figures(command, r).get("warnings")) for r in results)}
               if command == "fit" else {}),
            "skipped": [{"path": p, "reason": why} for p, why in skipped or []],
            "fluxcal": fluxcal, **({"workers": workers} if workers else {}),
            "results": [_row_json(command, r) for r in results]}


def _head(command: str) -> str:
    if command == "fit":
        return f"{'rms nT':>9} {'worst probe':>11} {'coverage':>8} {'warnings':>8}"
    if command == "diagnose":
        return f"{'verdict':<28} {'rms nT':>8} {'floor nT':>8}  significant"
    return "replay"


def _row(command: str, r: dict[str, Any], width: int, ok_width: int) -> str:
    f = figures(command, r)
    row = f"{r['recording']:<{width}}  {_status(r):<{ok_width}} {_num(r['seconds'], '.1f'):>7}  "
    if not r["ok"] and not (command == "replay" and r["status"] == 1 and f.get("said")):
        return row + _why(r)
    if command == "fit":
        return row + (f"{_num(f.get('rms_nT')):>9} {_num(f.get('worst_scalar_rms_nT')):>11} "
                      f"{_num(f.get('min_coverage'), '.0%'):>8} {f.get('warnings', 0):>8}")
    if command == "diagnose":
        verdict = (f.get("verdict") or "-") + (f" by {f['effect']}" if f.get("effect") else "")
        return row + (f"{verdict:<28} {_num(f.get('rms_nT')):>8} {_num(f.get('floor_nT')):>8}  "
                      f"{', '.join(f.get('significant') or []) or '-'}")
    return row + f.get("said", "")


def _about_workers(results: list[dict[str, Any]], fluxcal: str | None,
                   workers: list[dict[str, Any]] | None) -> list[str]:
    """What a person needs to know of the cluster's workers: those with another fluxcal (given no recording), the
    recordings a worker could not see, the recordings run by another fluxcal all the same (a worker that joined
    later, when every worker with this version had gone)."""
    lines = []
    other = [w for w in workers or [] if not w["same"]]
    if other:
        lines.append(f"\nworkers with another fluxcal than this one ({fluxcal}): sent no recording; install fluxcal "
                     f"{fluxcal} there")
        lines += [f"  {w['address']} on {w['host']}: fluxcal {w['fluxcal']}" for w in other]
    unseen = [r for r in results if r.get("failure") == "missing"]
    if unseen:
        hosts = ", ".join(sorted({r.get("host") or "?" for r in unseen}))
        lines.append(f"\n{len(unseen)} recording(s) not found where the workers run ({hosts}): a worker reads the "
                     f"path named here, made absolute, so the workers need the same files at the same paths (a "
                     f"folder shared at the same mount point, or the files copied there)")
    ran_other = [r["recording"] for r in results if fluxcal and r.get("fluxcal") not in (None, fluxcal)]
    if ran_other:
        lines.append(f"\n{len(ran_other)} recording(s) run by another fluxcal than this one ({fluxcal}): "
                     + ", ".join(ran_other))
    return lines


def summary_table(command: str, results: list[dict[str, Any]], wall_s: float, where: str,
                  skipped: list[tuple[str, str]] | None = None, fluxcal: str | None = None,
                  workers: list[dict[str, Any]] | None = None) -> str:
    width = max([len("recording")] + [len(r["recording"]) for r in results])
    ok_width = max([6] + [len(_status(r)) for r in results])
    lines = [f"{'recording':<{width}}  {'ok':<{ok_width}} {'s':>7}  {_head(command)}"]
    lines += [_row(command, r, width, ok_width) for r in results]
    warned = [r for r in results if warnings_of(r)]
    if warned:
        lines.append("\nwarnings (said on stderr; each recording was used without what they name)")
        lines += [f"  {w}" if w.startswith((r["recording"], r.get("path") or r["recording"]))
                  else f"  {r['recording']}: {w}" for r in warned for w in warnings_of(r)]
    if skipped:
        lines.append("\nskipped")
        lines += [f"  {p}: {why}" for p, why in skipped]
    lines += _about_workers(results, fluxcal, workers)
    failed = sum(not r["ok"] for r in results)
    busy = sum(r["seconds"] or 0.0 for r in results)
    fit_warned = sum(bool(figures(command, r).get("warnings")) for r in results) if command == "fit" else 0
    said = (f"{fit_warned} whose fit warns (the warnings column; --json lists them), " if command == "fit" else "")
    lines.append(f"{len(results)} recording(s), {failed} failed, {said}{len(warned)} read with warnings"
                 f"{' (above)' if warned else ''}, {len(skipped or [])} path(s) skipped; {wall_s:.1f} s on {where} "
                 f"({busy:.1f} s of work: {busy / wall_s if wall_s > 0 else 0:.2f}x one at a time)")
    return "\n".join(lines)
