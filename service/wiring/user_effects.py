"""Effects users add without editing the package (docs/effects.md).

- `--effects path/to/file.py:ClassName` (or `package.module:ClassName`): the class is imported and
  registered beside the catalogue under its `name`, and that name stands in the model;
- installed packages declare effects in the entry-point group `fluxcal.effects`
  (`[project.entry-points."fluxcal.effects"] myeffect = "mypkg.effects:MyEffect"`); they are registered
  when fit or diagnose starts, so diagnose tries them as candidates like the catalogue's own.

Wiring: it imports code named on the command line; the numerics only see a registered class.
"""

from __future__ import annotations

import importlib
import importlib.util
import sys
from importlib.metadata import entry_points
from pathlib import Path

from fluxcal.drivers.errors import ConfigError
from fluxcal.service.numerics.effects import known_effects, register_effect

GROUP = "fluxcal.effects"


def _load_class(spec: str) -> object:
    where, _, cls_name = spec.rpartition(":")
    if not where or not cls_name.isidentifier():
        raise ConfigError(f"--effects: {spec!r} is not allowed (allowed: an effect name, file.py:ClassName or "
                          f"package.module:ClassName)")
    if where.endswith(".py"):
        path = Path(where).expanduser()
        if not path.is_file():
            raise ConfigError(f"--effects: {spec!r}: no such file {str(path)!r}")
        mod_name = f"fluxcal_user_effect_{abs(hash(str(path.resolve())))}"
        module = sys.modules.get(mod_name)
        if module is None:
            loader_spec = importlib.util.spec_from_file_location(mod_name, path)
            if loader_spec is None or loader_spec.loader is None:
                raise ConfigError(f"--effects: {spec!r}: cannot load {str(path)!r} as Python")
            module = importlib.util.module_from_spec(loader_spec)
            sys.modules[mod_name] = module
            try:
                loader_spec.loader.exec_module(module)
            except Exception as e:                     # noqa: BLE001 - the user's code: say what it raised
                del sys.modules[mod_name]
                raise ConfigError(f"--effects: {spec!r}: importing {str(path)!r} raised "
                                  f"{type(e).__name__}: {e}") from None
    else:
        try:
            module = importlib.import_module(where)
        except Exception as e:                         # noqa: BLE001
            raise ConfigError(f"--effects: {spec!r}: importing {where!r} raised {type(e).__name__}: {e}") from None
    cls = getattr(module, cls_name, None)
    if cls is None:
        raise ConfigError(f"--effects: {spec!r}: {where} defines no {cls_name!r}")
    return cls


def effect_spec_here(spec: str) -> str:
    """An --effects item with its FILE.py made absolute from this process's working folder (a fleet's worker may
    run in another); names and package.module:Class as they are."""
    where, _, cls_name = spec.rpartition(":")
    if not where.endswith(".py"):
        return spec
    return f"{Path(where).expanduser().absolute()}:{cls_name}"


def resolve_effects(specs: list[str]) -> list[str]:
    """Effect names for the model: catalogue and registered names pass; FILE.py:Class and module:Class are
    loaded and registered first, each preceded by the catalogue effects its class says it was found `beside` (a
    module diagnose --write-effect wrote: it alone gives the figure it was written from); each name once."""
    names: list[str] = []
    for spec in specs:
        if ":" in spec:
            name = register_effect(_load_class(spec), spec)
            names += [b for b in getattr(known_effects()[name], "beside", ()) if b not in names]
        else:
            name = spec
        if name not in names:
            names.append(name)
    return names


def load_installed_effects() -> list[str]:
    """Register every effect of the entry-point group; a broken one is an error that names it."""
    names = []
    for ep in entry_points(group=GROUP):
        if ep.name in known_effects() and known_effects()[ep.name].__module__ == ep.module:
            names.append(ep.name)
            continue
        try:
            cls = ep.load()
        except Exception as e:                         # noqa: BLE001
            raise ConfigError(f"entry point {GROUP} {ep.name} = {ep.value!r}: loading it raised "
                              f"{type(e).__name__}: {e}") from None
        names.append(register_effect(cls, f"entry point {ep.name} = {ep.value}"))
    return names
