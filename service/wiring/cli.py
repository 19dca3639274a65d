"""The `fluxcal` command line (CONTRACTS.md section 2): argument parsing and exit statuses.

Each subcommand's work lives in `service.wiring.commands.<name>`, imported only when that command runs.
Exit status: 0 success, 2 bad input or usage, 1 any other failure; the message is one line on
stderr that says what to do.
"""

from __future__ import annotations

import argparse
import importlib
import signal
import sys
from typing import Sequence

from drivers.errors import CalibrationRefused, ConfigError, DataError, FluxcalError

EXIT_OK, EXIT_FAILURE, EXIT_USAGE = 0, 1, 2


def _effects(text: str) -> list[str]:
    return [e.strip() for e in text.split(",") if e.strip()]


def _int_auto(text: str) -> int:
    return int(text, 0)


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="fluxcal", description="Calibration service for fluxgate gradiometers "
                                "and magnetic gradient-tensor arrays.", allow_abbrev=False)
    sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND")

    fit = sub.add_parser("fit", help="fit a calibration to lab data (CSV or MCAP)", allow_abbrev=False)
    fit.add_argument("data", metavar="DATA")
    fit.add_argument("--config", metavar="FILE")
    fit.add_argument("--method", default="ellipsoid", metavar="M",
                     choices=["ellipsoid", "tmi", "sinefit", "two-step", "rls"])
    fit.add_argument("--align", default=None, metavar="A", choices=["regression", "rotation", "pca"])
    fit.add_argument("--effects", type=_effects, default=[], metavar="E,..")
    fit.add_argument("--site", metavar="LAT,LON,ALT_M[,DATE]",
                     help="the site: its total field from the World Magnetic Model, for methods that need a known "
                          "total field when no ref_total was logged")
    fit.add_argument("--out", metavar="CAL.json")
    fit.add_argument("--json", action="store_true")

    dia = sub.add_parser("diagnose", help="compare model and measurement; find the missing effect",
                         allow_abbrev=False)
    dia.add_argument("data", metavar="DATA")
    dia.add_argument("--config", metavar="FILE")
    dia.add_argument("--calibration", metavar="CAL.json")
    dia.add_argument("--effects", type=_effects, default=[], metavar="E,..")
    dia.add_argument("--site", metavar="LAT,LON,ALT_M[,DATE]",
                     help="the site: its total field from the World Magnetic Model (when no ref_total was logged)")
    dia.add_argument("--report", metavar="DIR")
    dia.add_argument("--json", action="store_true")

    run = sub.add_parser("run", help="run the service: source -> calibration -> Zenoh and MCAP",
                         allow_abbrev=False)
    run.add_argument("--config", required=True, metavar="FILE")

    rep = sub.add_parser("replay", help="run a recording through the same pipeline", allow_abbrev=False)
    rep.add_argument("recording", metavar="REC.mcap")
    rep.add_argument("--config", metavar="FILE")
    rep.add_argument("--out", metavar="OUT.mcap")

    sim = sub.add_parser("simulate", help="write simulated unit data", allow_abbrev=False)
    sim.add_argument("--config", metavar="FILE")
    sim.add_argument("--out", required=True, metavar="FILE.mcap|FILE.csv")

    dec = sub.add_parser("decode", help="turn a serial capture or CAN log into data", allow_abbrev=False)
    dec.add_argument("capture", metavar="CAPTURE")
    dec.add_argument("--probes", type=int, required=True, metavar="N")
    dec.add_argument("--can", action="store_true")
    dec.add_argument("--lsb-nT", dest="lsb_nT", type=float, default=0.001, metavar="X")
    dec.add_argument("--base-id", dest="base_id", type=_int_auto, default=0x200, metavar="ID")
    dec.add_argument("--out", required=True, metavar="FILE.csv|FILE.mcap")

    watch = sub.add_parser("watch", help="terminal dashboard of a running service", allow_abbrev=False)
    watch.add_argument("--config", metavar="FILE")
    watch.add_argument("--connect", metavar="ENDPOINT", help="e.g. tcp/127.0.0.1:7447")
    watch.add_argument("--unit", metavar="NAME")
    watch.add_argument("--seconds", type=float, default=None, help="stop after this long")
    watch.add_argument("--ca", metavar="CA.pem", help="TLS: the site's certificate authority")
    watch.add_argument("--cert", metavar="CERT.pem", help="TLS: this dashboard's certificate")
    watch.add_argument("--key", metavar="KEY.pem", help="TLS: this dashboard's private key")
    return p


def _sigterm_to_keyboard_interrupt(signum: int, frame: object) -> None:
    raise KeyboardInterrupt


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    signal.signal(signal.SIGTERM, _sigterm_to_keyboard_interrupt)
    module = importlib.import_module(f"service.wiring.commands.{args.command.replace('-', '_')}")
    try:
        return int(module.main(args) or 0)
    except (ConfigError, DataError, CalibrationRefused) as e:
        print(f"fluxcal {args.command}: {e}", file=sys.stderr)
        return EXIT_USAGE
    except FluxcalError as e:
        print(f"fluxcal {args.command}: {e}", file=sys.stderr)
        return EXIT_FAILURE
    except KeyboardInterrupt:
        return 130
    except BrokenPipeError:
        return EXIT_FAILURE


if __name__ == "__main__":
    sys.exit(main())
