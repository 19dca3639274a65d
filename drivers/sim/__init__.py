"""The simulated acquisition unit: a physical world (motion, field, probes, effects) behind the ICD.

    config.py   the [sim] section (SimConfig, load_sim_config)
    world.py    platform motion, ambient field and gradient, the probes' forward model and effects
    unit.py     digitisation into ICD serial bytes / CAN frames, with fault injection and its record
    ports.py    emitters: a pty serial port, a python-can bus, an SLCAN adapter on a pty (can_ports.py)
    source.py   the simulated unit as a Source (its kind: drivers/kinds/sim.py): in process, or through a
                transport another kind declares (ports.py, can_ports.py)
"""

from .config import SimConfig, load_sim_config
from .unit import FaultRecord, Unit, UnitSamples
from .world import World, WorldSamples

__all__ = ["SimConfig", "load_sim_config", "World", "WorldSamples", "Unit", "UnitSamples", "FaultRecord"]
