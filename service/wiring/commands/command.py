"""`fluxcal command VERB [PAYLOAD]`: the running service's commands (and its state) from a shell, no Python.

VERB is `state` or one of the service's commands (freeze, unfreeze, reset, apply, add-effect). The
answer is printed as JSON; a command the service refused exits 1 with its reason on stderr.
"""

from __future__ import annotations

import json
import sys
from argparse import Namespace
from pathlib import Path

from drivers.errors import ConfigError, DataError, FluxcalError
from service.io.bus import COMMANDS, MAX_COMMAND_PAYLOAD_BYTES, BusClient, ZenohConfig, discover_units, open_session
from service.io.calfile import calibration_from_json
from service.wiring.commands.watch import _resolve

VERBS = ("state", *COMMANDS)


def main(args: Namespace) -> int:
    if args.verb not in VERBS:
        raise ConfigError(f"VERB: {args.verb!r} is not allowed (allowed: {', '.join(VERBS)})")
    if args.verb != "state" and COMMANDS[args.verb] is not None and not args.payload:
        raise ConfigError(f"{args.verb}: needs a payload: {COMMANDS[args.verb]}")
    args.seconds = None
    endpoints, unit, tls = _resolve(args)
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
    print(json.dumps(answer))
    if args.verb != "state" and not answer.get("ok", False):
        print(f"fluxcal command: {args.verb} not applied by unit {unit}: {answer.get('error', 'no reason given')}",
              file=sys.stderr)
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
