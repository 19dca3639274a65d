"""The `fluxcal` command line (CONTRACTS.md section 2): argument parsing and exit statuses.

Each subcommand's work lives in `service.wiring.commands.<name>`, imported only when that command runs.
Exit status: 0 success, 2 bad input or usage, 1 any other failure; the message is one line on
stderr that says what to do.
"""

from __future__ import annotations

import argparse
import textwrap
import importlib
import signal
import sys
from typing import Sequence

from drivers.errors import CalibrationRefused, ConfigError, DataError, FluxcalError

EXIT_OK, EXIT_FAILURE, EXIT_USAGE = 0, 1, 2


def _effects(text: str) -> list[str]:
    return [e.strip() for e in text.split(",") if e.strip()]


def _max_samples(text: str) -> int:
    try:
        n = int(text.replace("_", "").replace(",", ""))
    except ValueError:
        n = -1
    if n < 0 or (0 < n < 1000):
        raise argparse.ArgumentTypeError(f"{text!r}: a whole number of samples, at least 1000 (0: all samples)")
    return n


def parse_spans(text: str) -> list[tuple[float, float]]:
    from service.wiring.commands.notes import parse_spans as parse

    return parse(text)


def _int_auto(text: str) -> int:
    return int(text, 0)


METHODS = ("ellipsoid", "tmi", "sinefit", "two-step", "rls")
ALIGNS = ("regression", "rotation", "pca")
#: the catalogue of effects (service.numerics.effects.EFFECTS), named here so --help needs no numerics import
EFFECT_NAMES = ("temperature, thermal, eddy, lag, nonlinearity, drift, gradient, crossfield, hysteresis, platform, "
                "column, ambient")
SITE = "LAT,LON,ALT_M[,DATE]"


def _version() -> str:
    try:
        from importlib.metadata import version

        return version("fluxcal")
    except Exception:                     # noqa: BLE001 - not installed: running from a checkout
        return "unknown (not installed)"


def _command(sub, name: str, summary: str, examples: str, more: str = "") -> argparse.ArgumentParser:
    text = summary[0].upper() + summary[1:] + "." + (" " + more.strip() if more else "")
    short = summary.split(": ")[0] if len(summary) > 70 else summary
    return sub.add_parser(name, help=short, description=textwrap.fill(text, 100),
                          epilog="examples:\n" + examples, formatter_class=argparse.RawDescriptionHelpFormatter,
                          allow_abbrev=False)


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="fluxcal", description="Calibration service for fluxgate gradiometers and magnetic gradient-tensor "
        "arrays. `fluxcal COMMAND --help` shows each command's options, defaults and examples.",
        epilog="The example configurations are in configs/ of the fluxcal repository: copy one beside your data and "
               "edit it (paths in a configuration are relative to its own file). A workflow: simulate -> fit -> "
               "diagnose -> fit --effects ... -> run -> watch / command -> replay; decode turns captures into "
               "data, repair finishes a cut recording. Exit status: 0 success, 2 bad input or usage, 1 any other "
               "failure (a command the service refused, replayed output that differs).", allow_abbrev=False)
    p.add_argument("--version", action="version", version=f"fluxcal {_version()}")
    sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND")
    data_help = ("a lab CSV or an MCAP recording of fluxcal. CSV columns: t (s), s1_x, s1_y, s1_z, s2_x, ... (nT); "
                 "optional: s<k>_temp (degC, for temperature), ref_total (nT, a scalar reference: without it and "
                 "without --site or the config's total field, the total field is estimated and an overall scale "
                 "cannot be seen), heel_deg, pitch_deg, azimuth_deg (attitude, for gradient), any other column "
                 "(diagnose tests what the residual follows); docs/csv.md")
    config_help = "a fluxcal TOML configuration (configs/ has examples): probe positions, total field, site"
    own = "or FILE.py:ClassName / package.module:ClassName for an effect of your own, docs/effects.md"
    effects_help = f"effect terms, comma-separated (allowed: {EFFECT_NAMES}; {own}); default: none"
    site_help = (f"the site as {SITE} (degrees north, degrees east, metres above the ellipsoid; DATE as "
                 f"YYYY-MM-DD, default today): the total field from the World Magnetic Model, when no ref_total "
                 f"was logged")

    skip_help = ("leave out these stretches of time (seconds of the data's own time t, ends included; several: "
                 "10-20,95.5-140): a disturbance no term follows, such as diagnose names")
    fit = _command(sub, "fit", "fit a calibration to lab data (CSV or MCAP)",
                   "  fluxcal fit grad.csv --out cal.json\n  fluxcal fit board.csv --site 46.52,6.63,400 --json\n"
                   "  fluxcal fit grad.csv --effects temperature,drift")
    fit.add_argument("data", metavar="DATA", nargs="+", help=data_help + fleet_help("--out and --report"))
    fit.add_argument("--config", metavar="FILE", help=config_help)
    fit.add_argument("--method", default="ellipsoid", metavar="M", choices=METHODS,
                     help=f"calibration method (allowed: {', '.join(METHODS)}; default: %(default)s)")
    fit.add_argument("--align", default=None, metavar="A", choices=ALIGNS,
                     help=f"how the probes of an array are brought to one frame (allowed: {', '.join(ALIGNS)}; "
                          f"default: regression for arrays)")
    fit.add_argument("--effects", type=_effects, default=[], metavar="E,..", help=effects_help)
    fit.add_argument("--site", metavar=SITE, help=site_help)
    fit.add_argument("--skip", type=parse_spans, default=None, metavar="T0-T1,..", help=skip_help)
    fit.add_argument("--out", metavar="CAL.json", help="write the calibration file here (default: none)")
    fit.add_argument("--json", action="store_true", help="print JSON (docs/contracts.md) instead of the summary")
    _fleet_options(fit)
    fit.add_argument("--report", metavar="DIR",
                     help="also write an HTML report of the calibration here (plots: matplotlib)")

    dia = _command(sub, "diagnose", "compare model and measurement; find the missing effect",
                   "  fluxcal diagnose recordings/grad1-hidden-effect.mcap\n"
                   "  fluxcal diagnose rec.mcap --effects temperature --report report/")
    dia.add_argument("data", metavar="DATA", nargs="+", help=data_help + fleet_help("--report"))
    dia.add_argument("--config", metavar="FILE", help=config_help)
    dia.add_argument("--calibration", metavar="CAL.json",
                     help="hold this calibration fixed (a file of `fit --out`, or `fit --json`); default: refit")
    dia.add_argument("--effects", type=_effects, default=[], metavar="E,..",
                     help=f"the effects already in the model (allowed: {EFFECT_NAMES}; {own}); default: none. "
                          f"Effects installed in the entry-point group fluxcal.effects are tried as candidates too")
    dia.add_argument("--site", metavar=SITE, help=site_help)
    dia.add_argument("--skip", type=parse_spans, default=None, metavar="T0-T1,..", help=skip_help)
    dia.add_argument("--report", metavar="DIR",
                     help="also write an HTML report here (plots: matplotlib; without it the page has the text and "
                          "tables)")
    dia.add_argument("--max-samples", type=_max_samples, default=None, metavar="N",
                     help="diagnose at most N samples: a longer recording is thinned to every k-th sample, and "
                          "the output says so (default: 500,000 probe-samples, e.g. 125,000 samples of 4 probes, "
                          "about 1.5 GB; 0: all)")
    dia.add_argument("--json", action="store_true", help="print JSON (docs/contracts.md) instead of the summary")
    _fleet_options(dia)

    run = _command(sub, "run", "run the service: source -> calibration -> Zenoh and MCAP",
                   "  fluxcal run --config configs/sim-gradiometer.toml   # saves to state/, records to "
                   "recordings/live/\n"
                   "                                                      # (its paths are ../state, ../recordings: "
                   "relative to configs/)",
                   more=(" Paths in the configuration ([calibration] file, [mcap] dir) are relative to the configuration file."
        " It runs until Ctrl-C or SIGTERM (a clean stop: files finished and closed), or for [source] run_s"
        " seconds on the simulated unit. A calibration saved by an earlier run of the same unit and source kind is"
        " reloaded at start (its path is said); delete that file to learn afresh (`fluxcal command reset` makes a"
        " running service forget what it learned). Status lines, gate reasons and commands go to stderr every"
        " [unit] status_s seconds; recordings to [mcap] dir."))

    run.add_argument("--config", required=True, metavar="FILE", help="the service's TOML configuration (required)")
    run.add_argument("--dashboard", nargs="?", const="127.0.0.1:8090", default=None, metavar="HOST:PORT",
                     help="also serve the web dashboard (`fluxcal dashboard`, a process of its own) at HOST:PORT "
                          "(default: 127.0.0.1:8090) and open it in this host's browser if it has one")

    rep = _command(sub, "replay", "run a recording through the same pipeline and compare with its output",
                   "  fluxcal replay recordings/grad1-sim-30s.mcap\n  fluxcal replay rec.mcap --out again.mcap",
                   more=(" It compares the replay's corrected output with the recording's, sample by sample: exit 0 "
                        "when every one equals the live run's (bit for bit where the recording names this machine's "
                        "arithmetic, else within the rounding tolerance of its conditioning, printed with the largest "
                        "difference; or there was none to compare, which it says), 1 when any differs by more or a "
                        "calibration was replaced at other samples. The samples after a hole in a damaged recording "
                        "are not compared, which it says."))
    rep.add_argument("recording", metavar="REC.mcap", nargs="+",
                     help="an MCAP file, or a directory of one run's rotated files"
                     + fleet_help("--out", json_flag=False))
    rep.add_argument("--config", metavar="FILE",
                     help="replay with this configuration (default: the one stored in the recording)")
    rep.add_argument("--out", metavar="OUT.mcap", help="also record the replay here, with the initial calibration and "
                                                      "the commands, so it replays again (default: none)")
    _fleet_options(rep)
    ins = _command(sub, "inspect", "list what a recording holds and how fit and diagnose would map it",
                   "  fluxcal inspect flight.ulg\n  fluxcal inspect robot_bag/ --json")
    ins.add_argument("file", metavar="FILE", help="a ROS 2 bag (.mcap, rosbag2 directory, .db3), a PX4 .ulg, an "
                                                  "ArduPilot .bin, a fluxcal .mcap or a lab .csv")
    ins.add_argument("--json", action="store_true", help="the inspection as JSON")
    fix = _command(sub, "repair", "copy a recording cut by a killed writer (or damaged) into a finished one",
                   "  fluxcal repair recordings/live/grad1-20261124T101500-0003.mcap fixed.mcap\n"
                   "  fluxcal repair recordings/live/ fixed/")
    fix.add_argument("recording", metavar="REC", help="an MCAP file, or a directory of them")
    fix.add_argument("out", metavar="OUT", help="the finished copy (a file, or a directory for a directory)")

    sim = _command(sub, "simulate", "write simulated unit data",
                   "  fluxcal simulate --config configs/sim-gradiometer.toml --out grad.csv\n"
                   "  fluxcal simulate --out capture.bin      # then: fluxcal decode capture.bin --probes 2 --out d.csv\n"
                   "  fluxcal simulate --out bus.log          # then: fluxcal decode bus.log --can --probes 2 --out d.csv")
    sim.add_argument("--config", metavar="FILE",
                     help="the [sim] section to simulate (default: a built-in gradiometer). Hide an effect by giving "
                          "its keys: [[sim.probes]] temp_offset_nT_per_C, eddy_s, lag_s, nonlin_quadratic_per_nT, "
                          "drift_offset_nT_per_h, pink_nT_rtHz (1/f noise); [sim.field] gradient_nT_m, "
                          "variation_nT (ambient change); [sim.temperature] ramp_C_per_h, amplitude_C; [sim.motion] "
                          "kind (turntable, tumble, grid, static). configs/sim-gradiometer.toml lists them all with "
                          "units. Neither output carries the platform's attitude (the truth file holds the motion), so a "
                          "hidden site gradient cannot be diagnosed from them")
    sim.add_argument("--out", required=True, metavar="FILE.csv|FILE.mcap|FILE.bin|FILE.log",
                     help="where to write (allowed: .csv lab data, with angle_deg and turn for a turntable; .mcap a "
                          "recording; .bin the unit's serial bytes; .log a candump log of its CAN frames); a "
                          ".truth.json with every simulated parameter goes beside it")

    dec = _command(sub, "decode", "turn a serial capture or CAN log into data (CSV or MCAP) for fit and diagnose",
                   "  fluxcal decode capture.bin --probes 2 --out data.csv\n"
                   "  fluxcal decode bus.log --can --probes 4 --base-id 0x200 --out data.mcap")
    dec.add_argument("capture", metavar="CAPTURE", help="raw serial bytes, or a CAN log (.log, .asc, .blf) with --can")
    dec.add_argument("--probes", type=int, required=True, metavar="N", help="probes in each frame (1..8; required)")
    dec.add_argument("--can", action="store_true",
                     help="the capture is a CAN log (default: serial bytes). CAN frames carry no unit clock: t is "
                          "the sample counter over the rate estimated from the log's timestamps. Neither carries a "
                          "total field: give fit and diagnose --site or a config's total field")
    dec.add_argument("--lsb-nT", dest="lsb_nT", type=float, default=0.001, metavar="X",
                     help="nT per ADC count (default: %(default)s)")
    dec.add_argument("--base-id", dest="base_id", type=_int_auto, default=0x200, metavar="ID",
                     help="first CAN identifier of the unit (default: 0x200)")
    dec.add_argument("--out", required=True, metavar="FILE.csv|FILE.mcap", help="where to write the data")

    cmd = _command(sub, "command", "send the running service a command, or ask its state",
                   "  fluxcal command state --connect tcp/127.0.0.1:7447\n  fluxcal command freeze --unit grad1\n"
                   "  fluxcal command add-effect temperature\n  fluxcal command apply cal.json")
    cmd.add_argument("verb", metavar="VERB", help="state, freeze, unfreeze, reset (forget what was learned), apply "
                                                 "(payload: a calibration file), add-effect (payload: temperature, "
                                                 "drift or nonlinearity, the effects a running service takes, or one "
                                                 "of your own from the configuration's [effects] plugins). A "
                                                 "refused command exits with 1 and says why")
    cmd.add_argument("payload", metavar="PAYLOAD", nargs="?", default=None,
                     help="what the command needs (apply: a calibration file; add-effect: an effect name)")
    cmd.add_argument("--config", metavar="FILE", help="take the endpoints, unit and TLS from this configuration")
    cmd.add_argument("--connect", metavar="ENDPOINT", help="the service's endpoint (default: tcp/127.0.0.1:7447)")
    cmd.add_argument("--unit", metavar="NAME", help="the unit (default: the first one found)")
    cmd.add_argument("--timeout", type=float, default=5.0, help="seconds to wait for the answer (default: %(default)s)")
    cmd.add_argument("--json", action="store_true", help="print the service's answer as JSON (default: text for a "
                                                        "person)")
    cmd.add_argument("--ca", metavar="CA.pem", help="TLS: the site's certificate authority")
    cmd.add_argument("--cert", metavar="CERT.pem", help="TLS: this client's certificate")
    cmd.add_argument("--key", metavar="KEY.pem", help="TLS: this client's private key")

    watch = _command(sub, "watch", "terminal dashboard of a running service: each probe's field and |B|, the error "
                     "against the noise, cal= the quality gate (usable or not; `fluxcal command state` says why), "
                     "cov= the share of field directions seen; one line a second when not on a terminal",
                     "  fluxcal watch --connect tcp/127.0.0.1:7447\n  fluxcal watch --config configs/sim-gradiometer.toml")
    watch.add_argument("--config", metavar="FILE", help="take the endpoints, unit and TLS from this configuration")
    watch.add_argument("--connect", metavar="ENDPOINT", help="the service's endpoint, e.g. tcp/127.0.0.1:7447 "
                                                            "(default: tcp/127.0.0.1:7447)")
    watch.add_argument("--unit", metavar="NAME", help="the unit to watch (default: the first one found)")
    watch.add_argument("--seconds", type=float, default=None, help="stop after this long (default: until Ctrl-C)")
    watch.add_argument("--ca", metavar="CA.pem", help="TLS: the site's certificate authority")
    watch.add_argument("--cert", metavar="CERT.pem", help="TLS: this dashboard's certificate")
    watch.add_argument("--key", metavar="KEY.pem", help="TLS: this dashboard's private key")

    dash = _command(sub, "dashboard", "web dashboard of running units: live plots with history, coverage, "
                    "calibration, health, diagnosis and commands, served on this host",
                    "  fluxcal dashboard --config configs/sim-gradiometer.toml --open\n"
                    "  fluxcal dashboard --connect tcp/10.0.0.5:7447 --unit grad1 --unit grad2 --listen 0.0.0.0:8090",
                    more=(" It subscribes over Zenoh like `watch` (lossily: it never holds a unit back) and serves a"
                          " page at --listen; the plot code comes from the package, no internet needed. Ctrl-C stops"
                          " it."))
    _client_options(dash, "dashboard")
    dash.add_argument("--listen", default="127.0.0.1:8090", metavar="HOST:PORT",
                      help="where the page is served (default: %(default)s, this host only; port 0: a free one, said "
                           "at start)")
    dash.add_argument("--open", action="store_true", help="open the page in this host's web browser")
    dash.add_argument("--read-only", dest="read_only", action="store_true",
                      help="show, but send no commands and run no diagnosis (for a page served beyond this host)")

    fox = _command(sub, "foxglove", "live bridge for the Foxglove app: a running unit's products on a Foxglove "
                   "WebSocket server",
                   "  fluxcal foxglove --config configs/sim-gradiometer.toml   # then in Foxglove: Open connection, "
                   "ws://127.0.0.1:8765",
                   more=" It subscribes over Zenoh like `watch` and never holds the unit back. Ctrl-C stops it.")
    _client_options(fox, "bridge")
    fox.add_argument("--listen", default="127.0.0.1:8765", metavar="HOST:PORT",
                     help="the Foxglove WebSocket server's address (default: %(default)s; port 0: a free one)")
    return p


def fleet_help(outputs: str, json_flag: bool = True) -> str:
    """The data argument's help for several recordings: what this command's output options become."""
    return ("; several (paths, folders, glob patterns such as 'survey/*.mcap') run on all cores, one summary table "
            + ("(--json: JSON) " if json_flag else "") + "of each recording's result or failure"
            + (f", {outputs} then name{'s' if ' and ' not in outputs else ''} folders" if outputs else ""))


def _fleet_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--jobs", type=int, default=None, metavar="N",
                   help="several recordings: processes to run them on (default: one per core)")
    p.add_argument("--scheduler", metavar="ADDRESS",
                   help="several recordings: run them on this Dask distributed cluster instead, e.g. "
                        "tcp://10.0.0.9:8786 (its workers need fluxcal installed)")


def _client_options(p: argparse.ArgumentParser, who: str) -> None:
    """--config/--connect/--unit/--seconds and TLS, as for `watch`; --unit may be given several times."""
    p.add_argument("--config", metavar="FILE", help="take the endpoints, unit and TLS from this configuration")
    p.add_argument("--connect", metavar="ENDPOINT", help="the units' endpoint or router, e.g. tcp/127.0.0.1:7447 "
                                                        "(default: tcp/127.0.0.1:7447)")
    p.add_argument("--unit", metavar="NAME", action="append",
                   help="a unit to show; repeat for several (default: every unit found)")
    p.add_argument("--seconds", type=float, default=None, help="stop after this long (default: until Ctrl-C)")
    p.add_argument("--ca", metavar="CA.pem", help="TLS: the site's certificate authority")
    p.add_argument("--cert", metavar="CERT.pem", help=f"TLS: this {who}'s certificate")
    p.add_argument("--key", metavar="KEY.pem", help=f"TLS: this {who}'s private key")


#: commands that take several recordings
FLEET_COMMANDS = ("fit", "diagnose", "replay")


def _sigterm_to_keyboard_interrupt(signum: int, frame: object) -> None:
    raise KeyboardInterrupt


def main(argv: Sequence[str] | None = None, *, install_signals: bool = True) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    args = build_parser().parse_args(argv)
    if install_signals:
        signal.signal(signal.SIGTERM, _sigterm_to_keyboard_interrupt)
    try:
        if args.command in FLEET_COMMANDS:
            from service.wiring.fleet_cli import dispatch

            fleet = dispatch(args, argv)
            if fleet is not None:
                return fleet
        module = importlib.import_module(f"service.wiring.commands.{args.command.replace('-', '_')}")
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
    except OSError as e:                  # a file that could not be read or written: said, never a traceback
        where = f"{e.filename}: " if e.filename else ""
        print(f"fluxcal {args.command}: {where}{e.strerror or e}", file=sys.stderr)
        return EXIT_FAILURE


if __name__ == "__main__":
    sys.exit(main())
