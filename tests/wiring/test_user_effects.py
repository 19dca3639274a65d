"""Effects users add without editing the package (issue 14): `--effects file.py:ClassName`,
`package.module:ClassName`, the `fluxcal.effects` entry-point group; each bad one refused with what is
wrong, never a traceback."""

from __future__ import annotations

import textwrap
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from fluxcal.drivers.errors import ConfigError
from fluxcal.service.numerics.effects import EFFECTS, EffectTerm, known_effects
from fluxcal.service.wiring import user_effects
from fluxcal.service.wiring.cli import main
from fluxcal.service.wiring.user_effects import load_installed_effects, resolve_effects

GOOD = textwrap.dedent('''
    import numpy as np
    from fluxcal.service.numerics.effects import EffectTerm

    class Bump(EffectTerm):
        name = "bump"
        frame = "corrected"
        def param_names(self, view):
            return [f"{view.name}.bump {a} nT" for a in "xyz"]
        def columns(self, view):
            t = view.data.t_s
            on = ((t - t[0]) > 0.5 * (t[-1] - t[0])).astype(float)
            cols = np.zeros((t.size, 3, 3))
            for a in range(3):
                cols[:, a, a] = on
            return cols
''')


pytestmark = pytest.mark.usefixtures("clean_registry")      # tests/conftest.py
ROOT = Path(__file__).resolve().parents[2]
SIM = str(ROOT / "recordings" / "grad1-sim-30s.mcap")


def test_a_file_effect_is_registered_and_named(tmp_path):
    f = tmp_path / "mine.py"
    f.write_text(GOOD)
    assert resolve_effects(["temperature", f"{f}:Bump"]) == ["temperature", "bump"]
    assert "bump" in known_effects() and list(known_effects())[:len(EFFECTS)] == list(EFFECTS)   # catalogue first
    assert resolve_effects([f"{f}:Bump"]) == ["bump"]                 # twice: the same class, no clash


@pytest.mark.parametrize("text, cls, msg", [
    ("x = 1\n", "Bump", "defines no 'Bump'"),
    ("raise RuntimeError('broken on purpose')\n", "Bump", "RuntimeError: broken on purpose"),
    ("class Bump:\n    name = 'bump'\n", "Bump", "subclass of fluxcal.service.numerics.effects.EffectTerm"),
    ("from fluxcal.service.numerics.effects import EffectTerm\nclass Bump(EffectTerm):\n    name = 'Bad Name'\n",
     "Bump", "is not allowed"),
    ("from fluxcal.service.numerics.effects import EffectTerm\nclass Bump(EffectTerm):\n    name = 'temperature'\n"
     "    def columns(self, view):\n        return None\n", "Bump", "is taken by"),
    ("from fluxcal.service.numerics.effects import EffectTerm\nclass Bump(EffectTerm):\n    name = 'bump'\n",
     "Bump", "defines neither columns()"),
])
def test_a_bad_effect_is_refused_with_what_is_wrong(tmp_path, text, cls, msg):
    f = tmp_path / "bad.py"
    f.write_text(text)
    with pytest.raises(ConfigError, match="--effects") as e:
        resolve_effects([f"{f}:{cls}"])
    assert msg in str(e.value)


def test_a_missing_file_or_module_is_named(tmp_path):
    with pytest.raises(ConfigError, match="no such file"):
        resolve_effects([f"{tmp_path / 'nope.py'}:X"])
    with pytest.raises(ConfigError, match="ModuleNotFoundError"):
        resolve_effects(["no_such_package.effects:X"])
    with pytest.raises(ConfigError, match="allowed: an effect name"):
        resolve_effects(["mine.py:"])


def test_an_installed_effect_is_a_candidate_of_diagnose(monkeypatch):
    class Wobble(EffectTerm):
        name = "wobble"

        def param_names(self, view):
            return [f"{view.name}.wobble {a} nT" for a in "xyz"]

        def columns(self, view):
            s = np.sin(2 * np.pi * 0.7 * view.data.t_s)
            cols = np.zeros((s.size, 3, 3))
            for a in range(3):
                cols[:, a, a] = s
            return cols

    ep = SimpleNamespace(name="wobble", value="pkg:Wobble", module="pkg", load=lambda: Wobble)
    monkeypatch.setattr(user_effects, "entry_points", lambda group: [ep] if group == "fluxcal.effects" else [])
    assert load_installed_effects() == ["wobble"]
    from test_diagnose import TUMBLE, data_of, probe, sim_block

    from fluxcal.service.numerics.diagnose import diagnose

    probes = [probe(0), probe(1)]
    d = diagnose(data_of(sim_block(probes, n=3000, rate=50.0, motion=TUMBLE, seed=2), probes))
    wobble = next(c for c in d.candidates if c.effect == "wobble")
    assert wobble.testable and not wobble.significant             # tried like the catalogue's, nothing there


def test_a_broken_entry_point_is_named(monkeypatch):
    def boom():
        raise ImportError("no module named pkg")

    ep = SimpleNamespace(name="bad", value="pkg:Bad", module="pkg", load=boom)
    monkeypatch.setattr(user_effects, "entry_points", lambda group: [ep])
    with pytest.raises(ConfigError, match="entry point fluxcal.effects bad = 'pkg:Bad'"):
        load_installed_effects()


def test_fit_with_a_file_effect_finds_its_step(tmp_path, capsys):
    # simulate, then add a 3 nT field on s1 halfway through: the user's Bump finds it
    csv = tmp_path / "d.csv"
    assert main(["simulate", "--out", str(csv)]) == 0
    lines = csv.read_text().splitlines()
    head = [i for i, ln in enumerate(lines) if not ln.startswith("#")][0]
    cols = lines[head].split(",")
    rows = [ln.split(",") for ln in lines[head + 1:]]
    t = np.array([float(r[0]) for r in rows])
    late = (t - t[0]) > 0.5 * (t[-1] - t[0])
    ix = cols.index("s1_x")
    for r, on in zip(rows, late):
        if on:
            r[ix] = f"{float(r[ix]) + 3.0:.3f}"
    csv.write_text("\n".join(lines[:head + 1] + [",".join(r) for r in rows]) + "\n")
    f = tmp_path / "mine.py"
    f.write_text(GOOD)
    capsys.readouterr()
    assert main(["fit", str(csv), "--effects", f"{f}:Bump", "--json"]) == 0
    import json

    out = json.loads(capsys.readouterr().out)
    assert main(["fit", str(csv), "--effects", "nosuch.py:Bump"]) == 2
    assert "no such file" in capsys.readouterr().err
    bump = out["effect_params"]["bump"]
    assert out["effects"] == ["bump"] and set(bump) == {f"s{k}.bump {a} nT" for k in (1, 2) for a in "xyz"}
    # the 3 nT step on s1's raw x axis, seen through its matrix in the aligned frame: |step| within 5 %
    s1 = np.array([bump[f"s1.bump {a} nT"]["value"] for a in "xyz"])
    assert abs(np.linalg.norm(s1) - 3.0) < 0.15 and bump["s1.bump x nT"]["se"] < 0.1
    assert np.linalg.norm([bump[f"s2.bump {a} nT"]["value"] for a in "xyz"]) < 0.2


def test_the_service_loads_the_plugins_its_configuration_names(tmp_path):
    from fluxcal.service.wiring.config import load_config
    from fluxcal.service.wiring.daemon import build_pipeline
    from fluxcal.service.wiring.live_effects import LiveEffects

    (tmp_path / "fx").mkdir()
    (tmp_path / "fx" / "mine.py").write_text(GOOD.replace('name = "bump"', 'name = "bump"\n    per_sample = True'))
    cfg_dir = tmp_path / "cfg"
    cfg_dir.mkdir()
    text = ('[unit]\nn_probes = 1\n[source]\nkind = "replay"\npath = "x.mcap"\nrate_hz = 10.0\n'
            '[effects]\nplugins = ["../fx/mine.py:Bump"]\n')
    (cfg_dir / "c.toml").write_text(text)
    cfg = load_config(cfg_dir / "c.toml")
    assert cfg.effects.plugins == [f"{tmp_path / 'fx' / 'mine.py'}:Bump"]       # relative to the config
    assert "bump" not in LiveEffects.allowed()
    build_pipeline(cfg)
    assert "bump" in LiveEffects.allowed() and "temperature" in LiveEffects.allowed()
    assert "eddy" not in LiveEffects.allowed()
    (cfg_dir / "bad.toml").write_text(text.replace("../fx/mine.py", "../fx/nope.py"))
    with pytest.raises(ConfigError, match="effects.plugins: .*no such file"):
        build_pipeline(load_config(cfg_dir / "bad.toml"))
    (cfg_dir / "typo.toml").write_text(text.replace("plugins", "plugin"))
    with pytest.raises(ConfigError, match="plugin"):
        load_config(cfg_dir / "typo.toml")


WARM = textwrap.dedent('''
    import numpy as np
    from fluxcal.service.numerics.effects import EffectTerm

    class Warm(EffectTerm):
        name = "warm"
        frame = "raw"
        def param_names(self, view):
            return [f"{view.name}.{a} nT/degC" for a in "xyz"]
        def constants(self, view):
            self.columns(view)
            return {f"{view.name} T0": (view.cache["ref:warm_t0"], "degC")}
        def columns(self, view):
            t = view.data.temperature(view.k)
            t0 = view.cache.setdefault("ref:warm_t0", float(np.mean(t)))
            cols = np.zeros((t.size, 3, 3))
            for a in range(3):
                cols[:, a, a] = t - t0
            return cols
''')


def test_a_fixed_reference_is_printed_as_fixed_with_its_value(tmp_path, capsys):
    """A user effect's T0 (its constants()) was printed "22 (undetermined) degC": held, never fitted, it is
    fixed, and says so in the text, the JSON, the calibration file and the report's table."""
    import json

    from fluxcal.service.io.calfile import load_calibration
    from fluxcal.service.numerics.calib.param_table import effect_rows

    cfg = tmp_path / "warm.toml"
    cfg.write_text('[unit]\nn_probes = 1\n[sim]\nduration_s = 20\n[sim.temperature]\nstart_C = 18.5\n'
                   'amplitude_C = 2.0\nperiod_s = 10.0\n[sim.motion]\nkind = "tumble"\nrate_deg_s = 30.0\n'
                   '[sim.reference]\nenabled = true\n[[sim.probes]]\noffset_nT = [100.0, -50.0, 20.0]\n'
                   'temp_offset_nT_per_C = [3.0, -2.0, 1.0]\n')            # what Warm describes: fit gives only
                                                                             # an effect the data show
    csv = tmp_path / "warm.csv"
    assert main(["simulate", "--config", str(cfg), "--out", str(csv)]) == 0
    f = tmp_path / "warm.py"
    f.write_text(WARM)
    cal = tmp_path / "cal.json"
    capsys.readouterr()
    assert main(["fit", str(csv), "--effects", f"{f}:Warm", "--out", str(cal)]) == 0
    text = capsys.readouterr().out
    line = next(ln for ln in text.splitlines() if "s1 T0" in ln)
    t0 = float(line.split("s1 T0")[1].split()[0])
    assert abs(t0 - 18.5) < 0.3 and "(fixed: " in line and "undetermined" not in line       # the mean temperature
    # the fitted coefficients keep their errors: the sim's, within 4 of them
    lines = [ln for ln in text.splitlines() if "nT/degC" in ln]
    assert len(lines) == 3, text
    for ln, want in zip(lines, (3.0, -2.0, 1.0)):
        value, se = float(ln.split()[3]), float(ln.split()[5])
        assert "±" in ln and abs(value - want) < 4 * se, ln
    assert main(["fit", str(csv), "--effects", f"{f}:Warm", "--json"]) == 0
    entry = json.loads(capsys.readouterr().out)["effect_params"]["warm"]["s1 T0"]
    assert entry["fixed"] is True and entry["se"] is None and entry["value"] == pytest.approx(t0, abs=1e-5)
    saved = load_calibration(cal).effect_params["warm"]
    assert saved["s1 T0"]["fixed"] is True
    rows = {r.name: r for r in effect_rows({"warm": saved})}
    assert rows["s1 T0"].note.startswith("fixed: ") and rows["s1 T0"].warning == ""
    assert rows["s1.x nT/degC"].se is not None


BROKEN = textwrap.dedent('''
    import numpy as np
    from fluxcal.service.numerics.effects import EffectTerm

    class Broken(EffectTerm):
        name = "broken"
        frame = FRAME
        def param_names(self, view):
            return [f"{view.name}.broken {a} nT" for a in "xy"]
        def columns(self, view):
            n = view.data.n_samples
            return BODY
''')


@pytest.mark.parametrize("frame, body, said", [
    ("'raw'", "view.data.extras['heater_B']", "columns() raised KeyError: 'heater_B'"),
    ("'raw'", "np.ones((n, 3))", "columns() returned (6000, 3) where (6000, 3, 2) is asked"),
    ("'raw'", "np.ones((n, 3, 3))", "columns() returned (6000, 3, 3) where (6000, 3, 2) is asked"),
    ("'raw'", "np.full((n, 3, 2), np.nan)", "columns() returned 36,000 NaN or infinite value(s)"),
    ("'rwa'", "np.ones((n, 3, 2))", "Broken.frame = 'rwa' is not allowed (allowed: raw, corrected)"),
])
def test_an_effect_whose_methods_fail_is_said_by_name_never_a_traceback(tmp_path, capsys, frame, body, said):
    """A new user's own effects (columns of the wrong shape, a parameter count that is not the columns', NaN
    columns, a column the data lack, a misspelt frame): each was a traceback from deep in the fit, or (the frame)
    taken silently with a held-out error below its in-sample one. Now fit and diagnose stop with the effect's name,
    where it came from and what is wrong (service/numerics/effects/guard.py)."""
    from fluxcal.service.numerics.effects.guard import FRAMES

    assert FRAMES == ("raw", "corrected")
    f = tmp_path / "broken.py"
    f.write_text(BROKEN.replace("FRAME", frame).replace("BODY", body))
    for command in ("fit", "diagnose"):
        capsys.readouterr()
        assert main([command, SIM, "--effects", f"{f}:Broken"]) == 2
        err = capsys.readouterr().err
        assert said in err and "Traceback" not in err, err
        if frame == "'raw'":
            assert f"effect 'broken' ({f}:Broken)" in err, err


def test_a_written_effect_given_data_without_its_column_says_which(tmp_path, capsys):
    """discover's written module follows a logged column: on data that lack it, fit says which column is missing
    (why_unavailable), not KeyError."""
    import sys

    sys.path.insert(0, str(ROOT / "tests"))
    from discovery_worlds import world

    from fluxcal.service.numerics.diagnose import diagnose
    from fluxcal.service.numerics.diagnose.write_effect import effect_source

    d = diagnose(world("lagged heater", 5))
    assert d.discovery.claimed
    f = tmp_path / "found.py"
    f.write_text(effect_source(d.discovery, data_name="a test world"))
    capsys.readouterr()
    main(["fit", SIM, "--effects", f"{f}:Discovered"])
    err = capsys.readouterr().err
    assert "effect 'discovered' cannot be fitted to these data: the data carry no heater_A column" in err, err


def _with_a_bump(path: Path, step_nT: float) -> Path:
    """The hidden-effect recording as a CSV (its temperatures and reference kept) with every axis stepped by
    step_nT over its second half: what GOOD's Bump describes."""
    from fluxcal.service.io.recordings.load import load_data

    b = load_data(ROOT / "recordings" / "grad1-hidden-effect.mcap").block
    field = b.field_nT.copy()
    field[(b.t_s - b.t_s[0]) > 0.5 * (b.t_s[-1] - b.t_s[0])] += step_nT
    cols = [b.t_s, *field.reshape(b.n_samples, -1).T, *b.temp_C.T, b.extras["ref_total"]]
    names = ["t"] + [f"s{k}_{a}" for k in (1, 2) for a in "xyz"] + ["s1_temp", "s2_temp", "ref_total"]
    np.savetxt(path, np.column_stack(cols), delimiter=",", header=",".join(names), comments="", fmt="%.6f")
    return path


def test_advice_names_a_users_effect_as_the_command_line_takes_it(tmp_path, capsys):
    """'try: --effects discovered,nonlinearity' exited 2 ('discovered' is not an effect) where the model held a
    user's effect: the advice gives it as the file.py:Class it came as, so that it runs as written. Only an effect
    the data show: where they do not, fit refuses it, and the advice says so and leaves it out."""
    f = tmp_path / "mine.py"
    f.write_text(GOOD)
    bumped = str(_with_a_bump(tmp_path / "bumped.csv", 40.0))
    capsys.readouterr()
    assert main(["diagnose", bumped, "--effects", f"{f}:Bump"]) == 0
    out = capsys.readouterr().out
    advice = next(ln for ln in out.splitlines() if "try: --effects" in ln)
    spec = advice.split("try: --effects ", 1)[1].split()[0]
    assert spec == f"{f}:Bump,temperature", advice
    assert main(["fit", bumped, "--effects", spec]) == 0                                      # runs
    capsys.readouterr()
    recording = str(ROOT / "recordings" / "grad1-hidden-effect.mcap")                          # no bump in it
    assert main(["diagnose", recording, "--effects", f"{f}:Bump"]) == 0
    out = capsys.readouterr().out
    assert "  bump: these data do not show it (none of its 6 parameters is 3 standard errors" in out, out
    assert "try: --effects temperature" in out
    assert main(["fit", recording, "--effects", f"{f}:Bump"]) == 2                          # as the advice said
    assert "do not show bump" in capsys.readouterr().err


SHARED = textwrap.dedent('''
    import numpy as np
    from fluxcal.service.numerics.effects import EffectTerm

    class Common(EffectTerm):
        name = "common"
        frame = "corrected"
        def shared_names(self, data):
            return ["common x nT", "common y nT"]
        def shared_vcolumns(self, data, k):
            return BODY
''')


@pytest.mark.parametrize("body, said", [
    ("data.extras['pump_A'][:, None, None] * np.ones((1, 3, 2))", "shared_vcolumns() raised KeyError: 'pump_A'"),
    ("np.ones((data.n_samples, 3, 3))", "shared_vcolumns() returned (6000, 3, 3) where (6000, 3, 2) is asked"),
])
def test_a_shared_effect_whose_columns_fail_is_said_by_name(tmp_path, capsys, body, said):
    """The same for an effect with parameters shared by the probes (a written effect common to all probes is one)."""
    f = tmp_path / "common.py"
    f.write_text(SHARED.replace("BODY", body))
    capsys.readouterr()
    assert main(["fit", SIM, "--effects", f"{f}:Common"]) == 2
    err = capsys.readouterr().err
    assert said in err and f"effect 'common' ({f}:Common)" in err and "Traceback" not in err, err
