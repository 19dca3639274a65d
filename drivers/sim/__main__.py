"""Run the simulated unit on a port for another process: `python -m fluxcal.drivers.sim --config F --transport pty`.

--transport (required) names one of the transports the kinds declare that can serve another process
(fluxcal.drivers.registry.transports(), docs/sources.md). Prints the port path (a stable
symlink, see fluxcal.drivers.sim.ports) on the first line of stdout, then streams until the run ends (duration_s), or
until SIGINT/SIGTERM, and prints a one-line summary of what was sent and corrupted on stderr (--record FILE: the
whole fault record, for a test or benchmark that checks every sample). Exit status 0, or 2 on a configuration
error.
"""

from __future__ import annotations

import argparse
import json
import signal
import sys
import threading
from typing import Sequence

from ..config import read_toml
from ..declare import resolve
from ..errors import ConfigError, FluxcalError
from ..outputs import replacing
from ..registry import transports
from .config import GRADIOMETER, load_sim_config
from .unit import Unit


def main(argv: Sequence[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m fluxcal.drivers.sim", description=__doc__.splitlines()[0],
                                allow_abbrev=False)
    p.add_argument("--config", metavar="FILE", help="TOML with a [sim] section (default: the built-in gradiometer)")
    ways = {t.name: t for _, t in transports() if t.process}
    p.add_argument("--transport", choices=list(ways), required=True,
                   help="how the unit reaches the other process: "
                        + "; ".join(f"{name}: {t.doc}" for name, t in ways.items()))
    p.add_argument("--realtime", dest="realtime", action="store_true", default=None, help="pace by the wall clock")
    p.add_argument("--fast", dest="realtime", action="store_false", help="as fast as the reader reads")
    p.add_argument("--duration", type=float, metavar="S", help="override sim.duration_s (0: until stopped)")
    p.add_argument("--link-dir", metavar="DIR", help="where the port symlink goes (default: a temporary dir)")
    p.add_argument("--truth", metavar="FILE", help="also write the truth JSON here")
    p.add_argument("--record", metavar="FILE", help="at the end, write the fault record (every sample index "
                   "corrupted, dropped or not sent, and why) to this .npz file (FaultRecord.load reads it)")
    args = p.parse_args(argv)
    try:
        if args.config:
            raw = read_toml(args.config)
            if "sim" not in raw:
                raise ConfigError(f"{args.config}: no [sim] section")
            table = raw["sim"]
        else:
            table = GRADIOMETER
        if args.duration is not None:
            table = {**table, "duration_s": args.duration}
        cfg = load_sim_config(table)
    except ConfigError as e:
        print(f"fluxcal.drivers.sim: {e}", file=sys.stderr)
        return 2
    unit = Unit(cfg)
    if args.truth:
        with replacing(args.truth, "w") as f:
            json.dump(unit.world.truth(), f, indent=1)
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    emitter, _, _ = resolve(ways[args.transport].link)(unit, realtime=args.realtime, link_dir=args.link_dir,
                                                      close_at_end=True)
    print(emitter.path, flush=True)
    try:
        while not stop.is_set() and not emitter.done.wait(0.1):
            pass
        emitter.wait(0)
    except KeyboardInterrupt:
        pass
    except FluxcalError as e:
        print(f"fluxcal.drivers.sim: {e}", file=sys.stderr)
        return 1
    finally:
        emitter.close()
    if args.record:
        emitter.record.save(args.record, start_index=emitter.start_index, next_index=emitter.next_index,
                            reconnects=emitter.reconnects, n_probes=cfg.n_probes)
    print(f"fluxcal.drivers.sim: sent samples {emitter.start_index}..{emitter.next_index} of {cfg.n_probes} probes; "
          f"faults {json.dumps(emitter.record.as_dict())}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
