"""The `fluxcal` command line (docs/contracts.md section 2): argument parsing and exit statuses.

Each command is a module of fluxcal.service.wiring.commands that declares its own options and runs from `main(args)`; the
parser is a loop over fluxcal.service.wiring.commands.COMMANDS, and only the module of the command that runs is imported.
Exit status: 0 success, 2 bad input or usage, 1 any other failure; the message is one line on stderr that says
what to do.
"""

from __future__ import annotations

import argparse
import importlib
import json
import re
import signal
import sys
from typing import Sequence

from fluxcal.drivers.errors import CalibrationRefused, ConfigError, DataError, FluxcalError
from fluxcal.service.wiring.commands import COMMANDS, FLEET_COMMANDS
from fluxcal.service.wiring.commands.options import SIGNED_VALUE_OPTIONS

EXIT_OK, EXIT_FAILURE, EXIT_USAGE = 0, 1, 2

DESCRIPTION = ("Calibration service for fluxgate gradiometers and magnetic gradient-tensor arrays. `fluxcal COMMAND "
               "--help` shows each command's options, defaults and examples.")
EPILOG = ("The example configurations are in configs/ of the fluxcal repository: copy one beside your data and edit it "
          "(paths in a configuration are relative to its own file). A workflow: simulate -> fit -> diagnose -> fit "
          "--effects ... -> run -> watch / command -> replay; decode turns captures into data, repair finishes a cut "
          "recording. Exit status: 0 success, 2 bad input or usage, 1 any other failure (a command the service "
          "refused, replayed output that differs).")


def _version() -> str:
    try:
        from importlib.metadata import version

        return version("fluxcal")
    except Exception:                     # noqa: BLE001 - not installed: running from a checkout
        return "unknown (not installed)"


def command_module(name: str):
    return importlib.import_module(f"fluxcal.service.wiring.commands.{name.replace('-', '_')}")


def build_parser(only: str | None = None) -> argparse.ArgumentParser:
    """The parser of every command (each module declares its own options); with `only`, that command's options
    alone are built and its module alone imported, the others listed by name for --help."""
    p = argparse.ArgumentParser(prog="fluxcal", description=DESCRIPTION, epilog=EPILOG, allow_abbrev=False)
    p.add_argument("--version", action="version", version=f"fluxcal {_version()}")
    sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name, short in COMMANDS.items():
        if only is None or name == only:
            module = command_module(name)
            module.add_options(module.HELP.add_to(sub, name))
        else:
            sub.add_parser(name, help=short)
    return p


def _sigterm_to_keyboard_interrupt(signum: int, frame: object) -> None:
    raise KeyboardInterrupt("SIGTERM")          # Ctrl-C's has no argument: main says which stopped it


def _parse(parser: argparse.ArgumentParser, argv: list[str]) -> argparse.Namespace:
    """The parsed arguments; a usage error (exit status 2) of a command asked for --json is said on stderr as argparse
    says it, and as the refusal JSON on stdout (docs/contracts.md), the input unknown (file null)."""
    if "--json" not in argv:
        return parser.parse_args(argv)
    import contextlib
    import io

    said = io.StringIO()
    try:
        with contextlib.redirect_stderr(said):
            return parser.parse_args(argv)
    except SystemExit as e:
        text = said.getvalue()
        sys.stderr.write(text)
        if e.code == 2:
            from fluxcal.service.wiring.result import refusal

            lines = [ln for ln in text.strip().splitlines() if ln.strip()]
            error = ConfigError(lines[-1].split(" error: ", 1)[-1] if lines else "usage error")
            asked = next((a for a in argv if a in COMMANDS), "")
            error.advice = f"`fluxcal {asked} --help` lists the options and what each allows".replace("  ", " ")
            print(json.dumps(refusal(error, None)), flush=True)
        raise


def _signed_values_joined(argv: list[str]) -> list[str]:
    """`--site -75,120` as `--site=-75,120`: argparse takes a value beginning with '-' for an option (unless it is a
    plain number), so an option of SIGNED_VALUE_OPTIONS is joined to a value that begins with '-' and a digit."""
    out: list[str] = []
    for a in argv:
        if out and out[-1] in SIGNED_VALUE_OPTIONS and re.match(r"-\.?\d", a):
            out[-1] = f"{out[-1]}={a}"
        else:
            out.append(a)
    return out


def _say_interrupted(args: argparse.Namespace, by: str) -> None:
    """One line for a command stopped by Ctrl-C or SIGTERM (exit status 130): which, what it was working on."""
    data = next((getattr(args, k) for k in ("data", "recording", "file", "capture") if getattr(args, k, None)), None)
    data = data[0] if isinstance(data, list) and len(data) == 1 else data
    on = "" if data is None else f" ({len(data)} recordings)" if isinstance(data, list) else f" on {data}"
    try:
        print(f"fluxcal {args.command}: interrupted by {by}{on} before it finished", file=sys.stderr, flush=True)
    except (OSError, ValueError):                 # stderr gone with the terminal that sent the signal
        pass


def main(argv: Sequence[str] | None = None, *, install_signals: bool = True) -> int:
    argv = _signed_values_joined(list(sys.argv[1:] if argv is None else argv))
    asked = next((a for a in argv if not a.startswith("-")), None)
    args = _parse(build_parser(asked if asked in COMMANDS else None), argv)
    if install_signals:
        signal.signal(signal.SIGTERM, _sigterm_to_keyboard_interrupt)
    try:
        if args.command in FLEET_COMMANDS:
            from fluxcal.service.wiring.fleet_cli import dispatch

            fleet = dispatch(args)
            if fleet is not None:
                return fleet
        return int(command_module(args.command).main(args) or 0)
    except (ConfigError, DataError, CalibrationRefused) as e:
        print(f"fluxcal {args.command}: {e}", file=sys.stderr)
        if getattr(args, "json", False):      # a script reads JSON on stdout whatever happened (docs/contracts.md)
            from fluxcal.service.wiring.result import refusal

            print(json.dumps(refusal(e, getattr(args, "data", None) or getattr(args, "file", None))), flush=True)
        return EXIT_USAGE
    except FluxcalError as e:
        print(f"fluxcal {args.command}: {e}", file=sys.stderr)
        return EXIT_FAILURE
    except KeyboardInterrupt as e:
        _say_interrupted(args, str(e) or "Ctrl-C")
        return 130
    except BrokenPipeError:
        return EXIT_FAILURE
    except OSError as e:                  # a file that could not be read or written: said, never a traceback
        where = f"{e.filename}: " if e.filename else ""
        print(f"fluxcal {args.command}: {where}{e.strerror or e}", file=sys.stderr)
        return EXIT_FAILURE


if __name__ == "__main__":
    sys.exit(main())
