"""Make recordings/grad3-flap.mcap: a simulated three-probe array with a field that is a non-linear function of a
logged column, for the discovery of shape in docs/tutorial-discover.md and docs/diagnose.md.

A magnet rides on a flap whose angle the recording logs (flap_deg: two slow swings within +-30 deg). As the angle
rises the magnet closes on probe s2: its field there lies along one platform direction and grows as the inverse
cube of the distance, A (c / (c - flap_deg))^n with c = 83.4 deg and n = 3; s1, further away, sees 0.15 of it along
the same direction, s3 nothing. The catalogue's `column` takes its linear part, the harmonics of the flap's swings
stay in the residual.

    python docs/examples/make_flap_recording.py [OUT.mcap]
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from fluxcal.drivers.block import SampleBlock
from fluxcal.drivers.sim import Unit, load_sim_config
from fluxcal.recordings import write_recording

C_DEG = 83.4
POWER = 3.0
FIELD_NT = 30.0
DIRECTION = np.array([0.61, -0.31, 0.73]) / np.linalg.norm([0.61, -0.31, 0.73])
S1_SHARE = 0.15


def flap_deg(t_s: np.ndarray) -> np.ndarray:
    """The flap's angle: two swings, at 0.0583 and 0.1896 Hz."""
    return 18.0 * np.sin(2 * np.pi * 0.0583 * t_s + 0.4) + 11.0 * np.sin(2 * np.pi * 0.1896 * t_s + 2.1)


def magnet_field_nT(angle_deg: np.ndarray) -> np.ndarray:
    """(N, 3) the magnet's field at s2 in the platform frame, less its mean over the swings."""
    f = (C_DEG / (C_DEG - angle_deg)) ** POWER
    return FIELD_NT * np.outer(f - f.mean(), DIRECTION)


def make(out: Path) -> Path:
    probes = [{"name": f"s{k + 1}", "position_m": [0.3 * np.cos(2 * np.pi * k / 3), 0.3 * np.sin(2 * np.pi * k / 3), 0],
               "offset_nT": [-150.0 * (k + 1), 60.0, 35.0 * k], "scale": [0.99, 1.01 - 0.01 * k, 1.004],
               "nonorth_deg": [-0.3, 0.4, 0.1 * k], "misalign_deg": [0.4 * k, 0.6, -0.8], "noise_nT": 0.6}
              for k in range(3)]
    cfg = load_sim_config({"seed": 2036, "rate_hz": 25.0, "duration_s": 180.0,
                           "field": {"total_nT": 49000.0, "inclination_deg": 64.0, "declination_deg": 2.0},
                           "reference": {"enabled": True, "noise_nT": 0.05},
                           "motion": {"kind": "tumble", "rate_deg_s": 25.0, "tumble_period_s": 7.0},
                           "temperature": {"start_C": 18.0, "amplitude_C": 2.0, "period_s": 150.0},
                           "probes": probes})
    unit = Unit(cfg)
    block = unit.digitise(0, cfg.n_samples).to_block()
    forward = unit.world.probes.forward_matrix                      # platform field -> each probe's raw output
    angle = flap_deg(block.t_s - block.t_s[0])
    b = magnet_field_nT(angle)
    field = block.field_nT.copy()
    field[:, 1] += b @ forward[1].T
    field[:, 0] += S1_SHARE * b @ forward[0].T
    extras = {**block.extras, "flap_deg": np.round(angle, 2)}
    block = SampleBlock(t_s=block.t_s, seq=block.seq, field_nT=np.round(field, 3), temp_C=block.temp_C,
                        flags=block.flags, extras=extras)
    truth = {**unit.world.truth(), "flap magnet": {
        "probes": {"s2": 1.0, "s1": S1_SHARE}, "field_nT": FIELD_NT, "direction_platform": DIRECTION.tolist(),
        "law": "field_nT (c / (c - flap_deg))^n less its mean, along direction_platform", "c_deg": C_DEG,
        "n": POWER}}
    write_recording(out, [block], unit="grad3", probe_names=[p["name"] for p in probes], truth=truth)
    return out


if __name__ == "__main__":
    print(make(Path(sys.argv[1] if len(sys.argv) > 1 else "recordings/grad3-flap.mcap")))
