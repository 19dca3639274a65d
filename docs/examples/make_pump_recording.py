"""Make recordings/grad3-pump.mcap: a simulated three-probe array with an effect that is none of the
catalogue's, for the tutorial docs/tutorial-own-effect.md.

A small pump on the platform turns a magnet at 1.5 Hz next to probe s2: s2 sees a field of 4 nT that
turns in the platform's x-y plane, the other probes nothing. No column of the recording logs the pump.

    python docs/examples/make_pump_recording.py [OUT.mcap]
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from fluxcal.drivers.block import SampleBlock
from fluxcal.drivers.sim import Unit, load_sim_config
from fluxcal.recordings import write_recording

PUMP_HZ = 1.5
PUMP_NT = 4.0


def pump_field_nT(t_s: np.ndarray) -> np.ndarray:
    """(N, 3) the pump's field at s2 in the platform frame."""
    w = 2 * np.pi * PUMP_HZ * t_s
    return PUMP_NT * np.stack([np.cos(w), np.sin(w), np.zeros_like(w)], axis=1)


def make(out: Path) -> Path:
    probes = [{"name": f"s{k + 1}", "position_m": [0.3 * np.cos(2 * np.pi * k / 3), 0.3 * np.sin(2 * np.pi * k / 3), 0],
               "offset_nT": [120.0 * (k + 1), -80.0, 45.0 * k], "scale": [1.01, 0.99 - 0.01 * k, 1.005],
               "nonorth_deg": [0.4, -0.3, 0.2 * k], "misalign_deg": [0.5 * k, -0.4, 1.0], "noise_nT": 0.6}
              for k in range(3)]
    cfg = load_sim_config({"seed": 2026, "rate_hz": 25.0, "duration_s": 160.0,
                           "field": {"total_nT": 49000.0, "inclination_deg": 64.0, "declination_deg": 2.0},
                           "reference": {"enabled": True, "noise_nT": 0.05},
                           "motion": {"kind": "tumble", "rate_deg_s": 25.0, "tumble_period_s": 7.0},
                           "temperature": {"start_C": 18.0, "amplitude_C": 2.0, "period_s": 150.0},
                           "probes": probes})
    unit = Unit(cfg)
    block = unit.digitise(0, cfg.n_samples).to_block()
    forward = unit.world.probes.forward_matrix[1]                     # platform field -> s2's raw output
    field = block.field_nT.copy()
    field[:, 1] += pump_field_nT(block.t_s - block.t_s[0]) @ forward.T
    block = SampleBlock(t_s=block.t_s, seq=block.seq, field_nT=np.round(field, 3), temp_C=block.temp_C,
                        flags=block.flags, extras=block.extras)
    truth = {**unit.world.truth(), "pump": {"probe": "s2", "hz": PUMP_HZ, "amplitude_nT": PUMP_NT,
                                             "field": "platform frame: A (cos wt, sin wt, 0), t from the start"}}
    write_recording(out, [block], unit="grad3", probe_names=[p["name"] for p in probes], truth=truth)
    return out


if __name__ == "__main__":
    print(make(Path(sys.argv[1] if len(sys.argv) > 1 else "recordings/grad3-pump.mcap")))
