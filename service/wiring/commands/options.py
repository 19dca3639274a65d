"""What the commands' options share: argument types, the help of the data, config, effects, site and skip
options, the fleet's options and a Zenoh client's options. Light: `fluxcal --help` imports it and nothing heavy."""

from __future__ import annotations

import argparse
import textwrap
from dataclasses import dataclass

METHODS = ("ellipsoid", "tmi", "sinefit", "two-step", "rls")
ALIGNS = ("regression", "rotation", "pca")
#: the catalogue of effects (fluxcal.service.numerics.effects.EFFECTS), named here so --help needs no numerics import
EFFECT_NAMES = ("temperature, thermal, eddy, lag, nonlinearity, drift, gradient, crossfield, hysteresis, platform, "
                "column, ambient")
SITE = "LAT,LON[,ALT_M[,DATE]]"
#: the options whose value may begin with '-' and a digit without being a plain number (a southern or western site):
#: argparse would take `--site -75,120` for a missing value, so the command line joins them (`--site=-75,120`)
SIGNED_VALUE_OPTIONS = ("--site",)
#: the metadata of an options dataclass's field that names a file or folder, or holds --effects items (a fleet
#: sends them to its workers absolute: fleet_cli.absolute_paths)
PATH = {"names": "path"}
EFFECT_SPECS = {"names": "effects"}

DATA_HELP = ("a lab CSV, an MCAP recording of fluxcal, a PX4 log (.ulg), an ArduPilot log (.bin) or a ROS 2 bag "
             "(.mcap, a rosbag2 directory, .db3; `fluxcal inspect FILE` shows what each stream becomes). CSV columns: t (s), s1_x, s1_y, s1_z, s2_x, ... (nT); "
             "optional: s<k>_temp (degC, for temperature), ref_total (nT, a scalar reference: without it and "
             "without --site or the config's total field, the total field is estimated and an overall scale "
             "cannot be seen), heel_deg, pitch_deg, azimuth_deg (attitude, for gradient), any other column "
             "(diagnose tests what the residual follows); docs/csv.md")
CONFIG_HELP = "a fluxcal TOML configuration (configs/ has examples): probe positions, total field, site"
OWN_EFFECT = "or FILE.py:ClassName / package.module:ClassName for an effect of your own, docs/effects.md"
EFFECTS_HELP = f"effect terms, comma-separated (allowed: {EFFECT_NAMES}; {OWN_EFFECT}); default: none"
SITE_HELP = (f"the site as {SITE} (degrees north, degrees east: negative south and west, e.g. -33.9,18.4; metres "
             f"above the ellipsoid, 0 if left out: the field changes by about -0.01 to -0.03 nT a metre of height, "
             f"0.06 %% a km at most, within the model's 0.1-1 %%; DATE as YYYY-MM-DD, 2010 to 2030, default today): "
             f"the total field from the World Magnetic Model of that date, when no ref_total was logged")
SKIP_HELP = ("leave out these stretches of time (seconds of the data's own time t, ends included; several: "
             "10-20,95.5-140): a disturbance no term follows, such as diagnose names")


@dataclass(frozen=True)
class CommandHelp:
    """What `fluxcal COMMAND --help` says besides the options: the summary, the examples, and more."""

    summary: str
    examples: str
    more: str = ""

    def add_to(self, sub, name: str) -> argparse.ArgumentParser:
        text = self.summary[0].upper() + self.summary[1:] + "." + (" " + self.more.strip() if self.more else "")
        return sub.add_parser(name, help=self.short, description=textwrap.fill(text, 100),
                              epilog="examples:\n" + self.examples,
                              formatter_class=argparse.RawDescriptionHelpFormatter, allow_abbrev=False)

    @property
    def short(self) -> str:
        return self.summary.split(": ")[0] if len(self.summary) > 70 else self.summary


def effect_names(text: str) -> list[str]:
    return [e.strip() for e in text.split(",") if e.strip()]


def max_samples(text: str) -> int:
    try:
        n = int(text.replace("_", "").replace(",", ""))
    except ValueError:
        n = -1
    if n < 0 or (0 < n < 1000):
        raise argparse.ArgumentTypeError(f"{text!r}: a whole number of samples, at least 1000 (0: all samples)")
    return n


def time_spans(text: str) -> list[tuple[float, float]]:
    from fluxcal.service.wiring.commands.notes import parse_spans

    return parse_spans(text)


TOPICS_HELP = ("another ecosystem's log: which streams become what, comma-separated NAME=TOPIC. A ROS 2 bag: a probe "
               "(s1=/imu/mag), a probe's temperature (temp.s1=/imu/temperature), imu=, gps= (NavSatFix), battery= "
               "(BatteryState), each TOPIC or none (default: every MagneticField topic a probe, in topic order; the "
               "others taken where there is one of their kind). A PX4 or ArduPilot log: imu=none, gps=none, "
               "battery=none leave out its attitude, position or battery current (and the rows they lack); a PX4 "
               "log's mag=vehicle_magnetometer takes the probes from PX4's output after its own calibration "
               "instead of sensor_mag. "
               "`fluxcal inspect FILE` shows the mapping")
MAGS_HELP = ("a PX4 or ArduPilot log: the compass instances to take as probes, in order, e.g. 0,2 (default: every "
             "one)")


def topics(text: str) -> dict[str, str | None]:
    """--topics' value: {name: topic or None}; argparse type (ArgumentTypeError says what is allowed)."""
    out: dict[str, str | None] = {}
    for part in text.split(","):
        name, sep, topic = part.strip().partition("=")
        ok_name = name in ("imu", "gps", "battery") or (name.startswith("temp.") and len(name) > 5) or \
            (name and name.replace("_", "").isalnum() and not name.startswith("temp."))
        if not sep or not ok_name or not topic.strip() or name in out:
            raise argparse.ArgumentTypeError(f"{part.strip()!r}: NAME=TOPIC (allowed NAME: a probe name, temp.<probe>, "
                                             f"imu, gps, battery, each once; TOPIC a topic or none)")
        out[name] = None if topic.strip() == "none" else topic.strip()
    return out


def mags(text: str) -> tuple[int, ...]:
    """--mags' value: compass instances, e.g. 0,2."""
    try:
        got = tuple(int(x) for x in text.split(","))
    except ValueError:
        got = ()
    if not got or any(k < 0 for k in got) or len(set(got)) != len(got):
        raise argparse.ArgumentTypeError(f"{text!r}: compass instances, e.g. 0,2 (allowed: whole numbers from 0, each "
                                         f"once)")
    return got


def int_auto(text: str) -> int:
    return int(text, 0)


def fleet_help(outputs: str, json_flag: bool = True) -> str:
    """The data argument's help for several recordings: what this command's output options become."""
    return ("; several (paths, folders, glob patterns such as 'survey/*.mcap') run on all cores, one summary table "
            + ("(--json: JSON) " if json_flag else "") + "of each recording's result or failure"
            + (f", {outputs} then name{'s' if ' and ' not in outputs else ''} folders" if outputs else ""))


def fleet_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--jobs", type=int, default=None, metavar="N",
                   help="several recordings: processes to run them on (default: one per core)")
    p.add_argument("--scheduler", metavar="ADDRESS",
                   help="several recordings: run them on this Dask distributed cluster instead, e.g. "
                        "tcp://10.0.0.9:8786 (its scheduler and workers need this fluxcal version and the same "
                        "files at the same paths: docs/cli.md)")


def data_options(p: argparse.ArgumentParser) -> None:
    """What `prepare` takes beside the data (fit, diagnose): the site, stretches to skip, another ecosystem's
    topics and magnetometers."""
    p.add_argument("--site", metavar=SITE, help=SITE_HELP)
    p.add_argument("--skip", type=time_spans, default=None, metavar="T0-T1,..", help=SKIP_HELP)
    p.add_argument("--topics", type=topics, default=None, metavar="NAME=TOPIC,..", help=TOPICS_HELP)
    p.add_argument("--mags", type=mags, default=None, metavar="I,..", help=MAGS_HELP)


def connection_options(p: argparse.ArgumentParser, who: str,
                       connect: str = "the service's endpoint, e.g. tcp/127.0.0.1:7447") -> None:
    """--config, --connect and TLS: how a client (watch, command, dashboard, bridge) reaches the units."""
    p.add_argument("--config", metavar="FILE", help="take the endpoints, unit and TLS from this configuration")
    p.add_argument("--connect", metavar="ENDPOINT", help=f"{connect} (default: tcp/127.0.0.1:7447)")
    p.add_argument("--ca", metavar="CA.pem", help="TLS: the site's certificate authority")
    p.add_argument("--cert", metavar="CERT.pem", help=f"TLS: this {who}'s certificate")
    p.add_argument("--key", metavar="KEY.pem", help=f"TLS: this {who}'s private key")


def client_options(p: argparse.ArgumentParser, who: str) -> None:
    """The connection, --unit (repeatable) and --seconds, for the dashboard and the bridge."""
    connection_options(p, who, "the units' endpoint or router, e.g. tcp/127.0.0.1:7447")
    p.add_argument("--unit", metavar="NAME", action="append",
                   help="a unit to show; repeat for several (default: every unit found)")
    p.add_argument("--seconds", type=float, default=None, help="stop after this long (default: until Ctrl-C)")
