"""The command line teaches itself: every option says what it does, its default and what is allowed,
every command shows an example, and `--version` answers."""

from __future__ import annotations

import argparse

import pytest

from fluxcal.service.numerics.effects import EFFECTS
from fluxcal.service.wiring import cli
from fluxcal.service.wiring.fitting import ALIGNS, METHODS


def _subparsers() -> dict[str, argparse.ArgumentParser]:
    parser = cli.build_parser()
    action = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return dict(action.choices)


@pytest.mark.parametrize("name", sorted(_subparsers()))
def test_every_option_says_what_it_does_and_every_command_has_an_example(name):
    sub = _subparsers()[name]
    for action in sub._actions:
        if isinstance(action, argparse._HelpAction):
            continue
        assert action.help and action.help != argparse.SUPPRESS, (name, action.dest)
        takes_value = action.nargs != 0 and action.option_strings
        if takes_value and not action.required and action.default not in (None, [], False):
            # an option with a default says it
            assert "default" in action.help, (name, action.dest)
        if action.choices:
            assert "allowed" in action.help and all(str(c) in action.help for c in action.choices), (name, action.dest)
    assert sub.epilog.startswith("examples:") and f"fluxcal {name}" in sub.epilog


def test_the_help_names_what_the_code_allows():
    from fluxcal.service.wiring.commands import options

    assert [e.strip() for e in options.EFFECT_NAMES.split(",")] == list(EFFECTS)
    assert options.METHODS == tuple(METHODS) and options.ALIGNS == tuple(ALIGNS)


def test_each_command_declares_its_options_and_the_list_names_it_as_the_command_does():
    """build_parser is a loop over the commands; the line `fluxcal --help` shows for each is its module's own."""
    from fluxcal.service.wiring.commands import COMMANDS

    for name, short in COMMANDS.items():
        module = cli.command_module(name)
        assert module.HELP.short == short and callable(module.add_options) and callable(module.main), name
    # one command's parser imports that command's module alone
    import subprocess
    import sys

    code = ("import sys; from fluxcal.service.wiring import cli; cli.build_parser('repair'); "
            "print(sorted(m for m in sys.modules if m.startswith('fluxcal.service.wiring.commands.')))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "['fluxcal.service.wiring.commands.options', 'fluxcal.service.wiring.commands.repair']"


def test_version(capsys):
    with pytest.raises(SystemExit) as e:
        cli.main(["--version"])
    assert e.value.code == 0
    out = capsys.readouterr().out
    assert out.startswith("fluxcal ") and out.split()[1][0].isdigit()


def test_the_help_answers_what_a_new_user_had_to_guess():
    # from a trial of the whole workflow with --help alone (the closing note of issue 16)
    subs = _subparsers()
    top = cli.build_parser().format_help()
    assert "configs/ of the fluxcal repository" in top and "relative to its own" in top and "Exit status" in top
    run = " ".join(subs["run"].format_help().split())
    assert "relative to the configuration file" in run and "Ctrl-C" in run and "reloaded at start" in run
    assert "delete that file to learn afresh" in run and "status_s" in run
    sim = " ".join(subs["simulate"].format_help().split()).replace("_ ", "_")
    assert all(k in sim for k in ("temp_offset_nT_per_C", "pink_nT_rtHz", "variation_nT", "configs/sim-gradiometer"))
    cmd = " ".join(subs["command"].format_help().split())
    assert "temperature, drift or nonlinearity" in cmd and "exits with 1" in cmd
    rep = " ".join(subs["replay"].format_help().split())
    assert "exit 0 when every one equals the live run's" in rep and "1 when any differs by more" in rep
    fit = " ".join(subs["fit"].format_help().split())
    assert "ref_total" in fit and "s<k>_temp" in fit and "heel_deg" in fit and "estimated" in fit
    dec = " ".join(subs["decode"].format_help().split())
    assert "no unit clock" in dec and "--site" in dec
    watch = " ".join(subs["watch"].format_help().split())
    assert "cal=" in watch and "cov=" in watch and "not on a terminal" in watch


def test_the_docs_list_every_command_every_reader_and_every_extra():
    """docs/cli.md's list at the top omitted inspect; fit's and diagnose's DATA named CSV and MCAP only, while the
    readers take PX4, ArduPilot and ROS 2 logs; install.md did not list their extras (pyproject.toml)."""
    import re
    import tomllib
    from pathlib import Path

    from fluxcal.service.wiring.commands import COMMANDS
    from fluxcal.service.wiring.commands.options import DATA_HELP

    root = Path(__file__).resolve().parents[2]
    cli_md = (root / "docs/cli.md").read_text()
    top = cli_md.split("\n## ", 1)[0]
    listed = {name for names in re.findall(r"^    fluxcal ([a-z|-]+)", top, re.M) for name in names.split("|")}
    assert set(COMMANDS) <= listed, set(COMMANDS) - listed
    data_md = cli_md.split("## Data: DATA", 1)[1].split("\n## ", 1)[0]
    for reader in ("CSV", "MCAP", "PX4", ".ulg", "ArduPilot", ".bin", "ROS 2 bag"):
        assert reader in DATA_HELP and reader in data_md, reader
    for name in ("fit", "diagnose"):
        sub = _subparsers()[name]
        assert next(a for a in sub._actions if a.dest == "data").help.startswith(DATA_HELP)
    extras = tomllib.loads((root / "pyproject.toml").read_text())["project"]["optional-dependencies"]
    install = (root / "docs/install.md").read_text()
    assert all(f"'.[{extra}]'" in install for extra in extras), [e for e in extras if f"'.[{e}]'" not in install]
