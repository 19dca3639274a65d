"""The commands of `fluxcal`, one module each. Every module declares its own options (`HELP`, `add_options(p)`) and
runs from `main(args) -> int`; the batch commands (fit, diagnose, replay) also give `execute(source, options, said)
-> Result` (fluxcal.service.wiring.result), which the command line formats and a fleet ships.

COMMANDS lists them in the order `fluxcal --help` shows them, with the line it shows for each (the module's
`HELP.short`; tests/wiring/test_cli_help.py holds the two together): the command line imports only the module of the
command it runs.
"""

COMMANDS: dict[str, str] = {
    "fit": "fit a calibration to lab data (CSV, MCAP, a PX4 or ArduPilot log, a ROS 2 bag)",
    "diagnose": "compare model and measurement; find the missing effect",
    "run": "run the service: source -> calibration -> Zenoh and MCAP",
    "replay": "run a recording through the same pipeline and compare with its output",
    "inspect": "list what a recording holds and how fit and diagnose would map it",
    "repair": "copy a recording cut by a killed writer (or damaged) into a finished one",
    "simulate": "write simulated unit data",
    "decode": "turn a serial capture or CAN log into data (CSV or MCAP) for fit and diagnose",
    "command": "send the running service a command, or ask its state",
    "watch": "terminal view of a running service",
    "dashboard": "web dashboard of running units",
    "foxglove": "live bridge for the Foxglove app",
}

#: the commands that take several recordings (a fleet: fluxcal.service.wiring.fleet)
FLEET_COMMANDS = ("fit", "diagnose", "replay")
