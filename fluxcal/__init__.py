"""fluxcal in Python: calibrate fluxgate gradiometers and magnetic gradient-tensor arrays from a notebook or a
script, with the very functions the command line is built on (docs/python.md).

    read(path | DataFrame)      the data of any input the command line reads (read_arrays: of numpy arrays)
    fit(data, effects=...)      a calibration: the Result `fluxcal fit` prints (.text(), .to_dict(), .to_dataframe(),
                                .calibration)
    diagnose(data)              where the model fails and which effect is missing (.verdict, .diagnosis)
    replay(recording)           a recording through the service's pipeline, compared with what it recorded live
    simulate(out, config=...)   a simulated unit's data and its truth
    load_calibration(path), save_calibration(cal, path), cal.apply(field_nT)
    EffectTerm, register_effect(cls), unregister_effect(name)   an effect of your own (docs/effects.md), from a
                                notebook cell (unregister it before the cell defines its class again)

Each of the names, at work (the functions' own docstrings have more):

>>> import os, tempfile
>>> import fluxcal
>>> data = fluxcal.read("recordings/grad1-sim-30s.mcap")
>>> isinstance(data, fluxcal.Data)
True
>>> cal = fluxcal.fit(data).calibration
>>> isinstance(cal, fluxcal.ArrayCalibration) and cal.probe_names == ["s1", "s2"]
True
>>> path = os.path.join(tempfile.mkdtemp(), "cal.json")
>>> fluxcal.save_calibration(cal, path)
>>> fluxcal.load_calibration(path).apply(data.field_nT).shape
(6000, 2, 3)
>>> "temperature" in fluxcal.known_effects() and issubclass(fluxcal.EffectTerm, object)
True
>>> class Nothing(fluxcal.EffectTerm):
...     name = "nothing-at-all"
...     def param_names(self, view):
...         return []
...     def columns(self, view):
...         return None
>>> fluxcal.register_effect(Nothing)
'nothing-at-all'
>>> fluxcal.unregister_effect("nothing-at-all")
"""

from fluxcal.service.io.calfile import load_calibration, save_calibration
from fluxcal.service.numerics.calib.model import ArrayCalibration
from fluxcal.service.numerics.effects import EffectTerm, known_effects, register_effect, unregister_effect
from fluxcal.service.wiring.api import Data, diagnose, fit, read, read_arrays, replay, simulate

__all__ = ["ArrayCalibration", "Data", "EffectTerm", "diagnose", "fit", "known_effects", "load_calibration", "read",
           "read_arrays", "register_effect", "replay", "save_calibration", "simulate", "unregister_effect"]
