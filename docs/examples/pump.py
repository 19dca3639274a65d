"""An effect of your own: a field that turns at a known frequency, as a pump or motor on the platform makes.

    corrected = v0 - (a cos(2 pi f t) + b sin(2 pi f t))        per probe, a and b in nT per axis

Linear in its parameters: columns() returns the regressors, the fit engine does the rest. Used by the
tutorial docs/tutorial-own-effect.md:

    fluxcal diagnose recordings/grad3-pump.mcap --effects docs/examples/pump.py:Pump
"""

import numpy as np

from fluxcal import EffectTerm


class Pump(EffectTerm):
    """A field at PUMP_HZ in the platform frame, per probe: cosine and sine amplitudes per axis, nT."""

    name = "pump"
    title = "Pump"
    physical = "a field turning at the pump's frequency"
    frame = "corrected"              # the pump sits on the platform: its field adds to the corrected vector
    per_sample = True                # each sample's correction needs that sample alone: the service can take it

    HZ = 1.5                         # the pump's rated speed, turns per second

    def param_names(self, view):
        return [f"{view.name}.pump {part} {axis} nT" for part in ("cos", "sin") for axis in "xyz"]

    def columns(self, view):
        w = 2 * np.pi * self.HZ * view.data.t_s       # the unit's clock: the same phase in every window
        cols = np.zeros((w.size, 3, 6))
        for axis in range(3):
            cols[:, axis, axis] = np.cos(w)
            cols[:, axis, 3 + axis] = np.sin(w)
        return cols
