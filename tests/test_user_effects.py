"""Effects users add without editing the package (issue 14): `--effects file.py:ClassName`,
`package.module:ClassName`, the `fluxcal.effects` entry-point group; each bad one refused with what is
wrong, never a traceback."""

from __future__ import annotations

import textwrap
from types import SimpleNamespace

import numpy as np
import pytest

from drivers.errors import ConfigError
from service.numerics.effects import _REGISTERED, EFFECTS, EffectTerm, known_effects
from service.wiring import user_effects
from service.wiring.cli import main
from service.wiring.user_effects import load_installed_effects, resolve_effects

GOOD = textwrap.dedent('''
    import numpy as np
    from service.numerics.effects import EffectTerm

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


@pytest.fixture(autouse=True)
def clean_registry():
    before = dict(_REGISTERED)
    yield
    _REGISTERED.clear()
    _REGISTERED.update(before)


def test_a_file_effect_is_registered_and_named(tmp_path):
    f = tmp_path / "mine.py"
    f.write_text(GOOD)
    assert resolve_effects(["temperature", f"{f}:Bump"]) == ["temperature", "bump"]
    assert "bump" in known_effects() and list(known_effects())[:len(EFFECTS)] == list(EFFECTS)   # catalogue first
    assert resolve_effects([f"{f}:Bump"]) == ["bump"]                 # twice: the same class, no clash


@pytest.mark.parametrize("text, cls, msg", [
    ("x = 1\n", "Bump", "defines no 'Bump'"),
    ("raise RuntimeError('broken on purpose')\n", "Bump", "RuntimeError: broken on purpose"),
    ("class Bump:\n    name = 'bump'\n", "Bump", "subclass of service.numerics.effects.EffectTerm"),
    ("from service.numerics.effects import EffectTerm\nclass Bump(EffectTerm):\n    name = 'Bad Name'\n",
     "Bump", "is not allowed"),
    ("from service.numerics.effects import EffectTerm\nclass Bump(EffectTerm):\n    name = 'temperature'\n"
     "    def columns(self, view):\n        return None\n", "Bump", "is taken by"),
    ("from service.numerics.effects import EffectTerm\nclass Bump(EffectTerm):\n    name = 'bump'\n",
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

    from service.numerics.diagnose import diagnose

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
    from service.wiring.config import load_config
    from service.wiring.daemon import build_pipeline
    from service.wiring.live_effects import LiveEffects

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
