"""fluxcal in Python: calibrate fluxgate gradiometers and magnetic gradient-tensor arrays from a notebook or a
script, with the very functions the command line is built on (docs/python.md).

    read(path | DataFrame)      the data of any input the command line reads (read_arrays: of numpy arrays)
    fit(data, effects=...)      a calibration: the Result `fluxcal fit` prints (.text(), .to_dict(), .to_dataframe(),
                                .calibration)
    diagnose(data)              where the model fails and which effect is missing (.verdict, .diagnosis)
    replay(recording)           a recording through the service's pipeline, compared with what it recorded live
    simulate(out, config=...)   a simulated unit's data and its truth
    load_calibration(path), save_calibration(cal, path), cal.apply(field_nT)
    EffectTerm, register_effect(cls)   an effect of your own (docs/effects.md), from a notebook cell

>>> import fluxcal
>>> sorted(n for n in fluxcal.__all__ if n[0].islower())[:4]
['diagnose', 'fit', 'load_calibration', 'read']
"""

from service.io.calfile import load_calibration, save_calibration
from service.numerics.calib.model import ArrayCalibration
from service.numerics.effects import EffectTerm, known_effects, register_effect
from service.wiring.api import Data, diagnose, fit, read, read_arrays, replay, simulate

__all__ = ["ArrayCalibration", "Data", "EffectTerm", "diagnose", "fit", "known_effects", "load_calibration", "read",
           "read_arrays", "register_effect", "replay", "save_calibration", "simulate"]
