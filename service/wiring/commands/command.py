"""`fluxcal command VERB [PAYLOAD]`: the running service's commands (and its state) from a shell, no Python.

VERB is `state` or one of the service's commands (freeze, unfreeze, reset, apply, add-effect). The
answer is printed for a person (`state`: the calibration in use, the quality gate's latest verdict, each
probe's offsets and matrix, the input's health, the recording), or as the service's JSON with `--json`; a
command the service refused exits 1 with its reason on stderr.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from argparse import Namespace
from pathlib import Path
from typing import Any

from fluxcal.drivers.errors import ConfigError, DataError, FluxcalError
from fluxcal.drivers.text import printable, printable_json
from fluxcal.service.io.bus import (
    COMMANDS,
    MAX_COMMAND_PAYLOAD_BYTES,
    BusClient,
    ZenohConfig,
    discover_units,
    open_session,
)
from fluxcal.service.io.calfile import calibration_from_json
from fluxcal.service.wiring.commands.client import counter_words, is_flow, resolve
from fluxcal.service.wiring.commands.options import CommandHelp, connection_options

VERBS = ("state", *COMMANDS)


HELP = CommandHelp("send the running service a command, or ask its state",
                   "  fluxcal command state --connect tcp/127.0.0.1:7447\n  fluxcal command freeze --unit grad1\n"
                   "  fluxcal command add-effect temperature\n  fluxcal command apply cal.json")


def add_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("verb", metavar="VERB", help="state, freeze, unfreeze, reset (forget what was learned), apply "
                                               "(payload: a calibration file), add-effect (payload: temperature, "
                                               "drift or nonlinearity, the effects a running service takes, or one "
                                               "of your own from the configuration's [effects] plugins). A "
                                               "refused command exits with 1 and says why")
    p.add_argument("payload", metavar="PAYLOAD", nargs="?", default=None,
                   help="what the command needs (apply: a calibration file; add-effect: an effect name)")
    connection_options(p, "client")
    p.add_argument("--unit", metavar="NAME", help="the unit (default: the first one found)")
    p.add_argument("--timeout", type=float, default=5.0, help="seconds to wait for the answer (default: %(default)s)")
    p.add_argument("--json", action="store_true", help="print the service's answer as JSON (default: text for a "
                                                      "person)")


def main(args: Namespace) -> int:
    if args.verb not in VERBS:
        raise ConfigError(f"VERB: {args.verb!r} is not allowed (allowed: {', '.join(VERBS)})")
    if args.verb != "state" and COMMANDS[args.verb] is not None and not args.payload:
        raise ConfigError(f"{args.verb}: needs a payload: {COMMANDS[args.verb]}")
    args.seconds = None
    endpoints, unit, tls = resolve(args)
    payload = args.payload or ""
    inline = payload.lstrip().startswith("{")          # a calibration's JSON text itself, not a path
    if args.verb == "apply" and not inline and _is_file(payload):
        payload = _calibration_text(Path(payload))    # the service may run on another host: send the file itself
    elif args.verb == "apply" and not inline:
        raise ConfigError(f"apply: {payload!r} is not a file here; apply sends a calibration's content (a file on "
                          f"this host, or its JSON text): the service reads no file a command names")
    with open_session(ZenohConfig.client(*endpoints, tls=tls)) as session:
        if unit is None:
            units = discover_units(session, timeout=min(2.0, args.timeout))
            if not units:
                raise FluxcalError(f"no running unit answers at {', '.join(endpoints)}: is `fluxcal run` running "
                                   f"there? (give --connect or --config)")
            unit = sorted(units)[0]
        with BusClient(session, unit, streams=[]) as client:
            answer = (client.query_state(timeout=args.timeout) if args.verb == "state"
                      else client.command(args.verb, payload, timeout=args.timeout))
    if answer.get("warning"):                     # several services answered: each took the command
        print(printable(f"fluxcal command: WARNING: {answer['warning']}"), file=sys.stderr)
    if getattr(args, "json", False):
        print(json.dumps(answer))
    elif args.verb == "state":
        print(state_text(printable_json(answer)))     # the service's words: shown, never acting on the terminal
    elif answer.get("ok", False):
        print(f"{args.verb}: done by unit {unit}" + (f"; calibration {answer['cal_id']} in use"
                                                     if answer.get("cal_id") else "; no calibration in use yet"))
    if args.verb != "state" and not answer.get("ok", False):
        print(printable(f"fluxcal command: {args.verb} not applied by unit {unit}: "
                        f"{answer.get('error', 'no reason given')}"), file=sys.stderr)
        return 1
    return 0


def _is_file(text: str) -> bool:
    """Whether text names a file here (False for what cannot be a path: too long a name, a NUL)."""
    try:
        return Path(text).is_file()
    except (OSError, ValueError):
        return False


def _calibration_text(path: Path) -> str:
    """The text of a calibration file to send with `apply`, checked here first: a wrong file (a CSV, a
    recording) is refused naming it and what was expected, and is never sent, read whole or printed."""
    try:
        with path.open("rb") as f:
            head = f.read(MAX_COMMAND_PAYLOAD_BYTES + 1)
    except OSError as e:
        raise DataError(f"{path}: cannot read the calibration file: {e}") from None
    text = head.decode("utf-8", errors="replace")
    if len(head) > MAX_COMMAND_PAYLOAD_BYTES and text.lstrip().startswith("{"):
        raise DataError(f"{path}: more than {MAX_COMMAND_PAYLOAD_BYTES:,} bytes: too large for a calibration "
                        f"file (one written by `fluxcal fit --out` is a few kB)")
    calibration_from_json(text, origin=str(path))    # DataError naming the file, quoting at most a line's start
    return text


# --- the state for a person ------------------------------------------------------------------------------


def _n(x: Any, fmt: str = ".4g", unit: str = "") -> str:
    """A number as text; "n/a" for a missing or non-finite one (and for the -1 the state gives a missing error)."""
    if isinstance(x, bool) or not isinstance(x, (int, float)) or not math.isfinite(x):
        return "n/a"
    return format(x, fmt) + (f" {unit}" if unit else "")


def state_text(st: dict[str, Any]) -> str:
    """The service's state (`fluxcal command state`) as lines a person reads: what it is, then the unit."""
    lines = []
    unit = st.get("unit", "?")
    if st.get("usable"):
        head = f"unit {unit}: calibration {st.get('cal_id')} in use (method {st.get('method') or '-'}, align " \
               f"{st.get('align') or '-'}"
        head += f", total field {_n(st.get('total_nT'), '.1f', 'nT')})" if st.get("total_nT") else ", total field " \
                "estimated)"
    else:
        head = f"unit {unit}: no calibration in use yet (learning online; corrected output starts once a candidate " \
               f"passes the quality gate)"
    lines.append(head)
    span = st.get("span")
    if st.get("usable") and isinstance(span, list) and len(span) == 3:
        lines.append(f"  fitted to {int(span[2]):,} samples, unit time {_n(span[0], '.3f')} to {_n(span[1], '.3f')} s")
    mode = [("frozen: the online estimate no longer changes what is used" if st.get("frozen") else
             "learning online"),
            "held: an applied calibration, kept until reset" if st.get("held") else ""]
    lines.append("  " + "; ".join(m for m in mode if m) + f"; effects: {', '.join(st.get('effects') or []) or 'none'}"
                 + (f"; {st['samples_seen']:,} samples seen per probe" if isinstance(st.get("samples_seen"), int)
                    else ""))
    names = st.get("probe_names") or [p.get("name") for p in st.get("probes") or []]
    gate = st.get("gate")
    if not gate:
        lines.append("quality gate: no verdict yet (too few samples since the start or the last reset)")
    else:
        rms = gate.get("rms_nT")
        words = ["passed" if gate.get("usable") else "refused"]
        if isinstance(gate.get("coverage"), (int, float)) and math.isfinite(gate["coverage"]):
            words.append(f"coverage {gate['coverage']:.0%} of the 26 direction bins in its window")
        if isinstance(gate.get("condition"), (int, float)) and math.isfinite(gate["condition"]):
            words.append(f"condition {gate['condition']:.3g}")
        if rms:
            words.append("scalar residual RMS " + ", ".join(
                f"{name} {_n(r, '.3f', 'nT')}" for name, r in zip(names or [f"s{k + 1}" for k in range(len(rms))],
                                                                  rms)))
        elif rms == []:                      # the pipeline's mark of a check that found no candidate
            words.append("no candidate to judge, so no residual yet")
        lines.append("quality gate, latest online candidate: " + "; ".join(words) +
                     (" (the calibration in use stays)" if st.get("usable") and not gate.get("usable") else ""))
        lines += [f"  {r}" for r in gate.get("reasons") or []]
    for p in st.get("probes") or []:
        lines.append(f"probe {p.get('name')}")
        off, se = p.get("offset_nT") or [], p.get("offset_se_nT") or []
        lines.append("  offset nT   " + "  ".join(
            f"{_n(v, '10.3f')} ± {_n(e, '.2g') if isinstance(e, (int, float)) and e >= 0 else 'n/a'}"
            for v, e in zip(off, se + [None] * (len(off) - len(se)))))
        for i, row in enumerate(p.get("matrix") or []):
            lines.append(("  matrix     " if i == 0 else "             ") + "  ".join(_n(v, '10.5f') for v in row))
        params = p.get("params") or {}
        for key, label in (("scale", "scale"), ("nonorth_deg", "nonorth"), ("misalign_deg", "misalign")):
            entry = params.get(key)
            if isinstance(entry, dict) and isinstance(entry.get("value"), list):
                unit = str(entry.get("unit") or "")
                lines.append(f"  {label:10s} " + ", ".join(_n(v, '.5g') for v in entry["value"]) +
                             (f" {unit}" if unit else ""))
    health = st.get("health") or {}
    if health:
        about = counter_words(st)                                 # what the source's own counters count
        counted = {k: v for k, v in health.items() if isinstance(v, (int, float))}
        flows = [f"{v:,} {k.replace('_', ' ')}" for k, v in counted.items() if is_flow(k, about)]
        bad = [f"{k.replace('_', ' ')} {v:,}" for k, v in counted.items() if v and not is_flow(k, about)]
        lines.append(f"input: {', '.join(flows) or 'n/a'}; {', '.join(bad) or 'no error counted'}")
    rec = st.get("recording")
    if rec:
        trouble = [f"{k} {rec[k]:,}" for k in ("dropped", "errors") if rec.get(k)]
        lines.append(f"recording: {rec.get('current') or '-'} ({rec.get('files', 0)} file(s), "
                     f"{rec.get('messages_written', 0):,} messages written, "
                     f"{(rec.get('bytes_written') or 0) / 1e6:.1f} MB)" +
                     (f"; {', '.join(trouble)}" if trouble else "") +
                     (f"; last error: {rec['last_error']}" if rec.get("last_error") else ""))
    if st.get("stale"):
        lines.append(f"(this state is {_n(st.get('state_age_s'), '.0f')} s old: the service is busy, e.g. reconnecting "
                     f"its input)")
    lines.append("(--json: the service's state as JSON)")
    return "\n".join(lines)
