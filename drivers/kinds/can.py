"""The CAN kind: the unit's frames on a python-can bus (socketcan, an SLCAN adapter, a virtual bus); the ICD's
frames, one per probe axis per sample, are its first protocol (drivers/can_source.py, drivers/assemble.py)."""

from __future__ import annotations

from ..declare import Counted, NoDecode, Protocol, SourceKind, Transport
from ._icd import icd_samples

ICD = Protocol(
    "icd", "the ICD's CAN frames: id = base_id + 4 x probe + axis, the axis's counts, the sample counter and the "
           "probe's temperature; no unit clock: t_s = seq / rate_hz",
    decoder="fluxcal.drivers.can_source:CanIcd",
    counters=(
        Counted("frames_accepted", "the unit's ICD frames", decoded=True, what="{n:,} frame(s) of the unit's"),
        Counted("wrong_length", "frames with the unit's ids that are no classic 8-byte data frame, dropped",
                fault="wrong_length", label="CAN frames of a wrong length",
                what="{n:,} frame(s) with the unit's ids that are no 8-byte data frame, dropped",
                advice="another node sends on the unit's ids, or the unit speaks another ICD version: check "
                       "source.base_id", arrival=True),
        Counted("remote_frames", "remote frames with the unit's ids (another node asking for them), ignored",
                fault="remote_frames", label="CAN remote frames", what="{n:,} remote frame(s) with the unit's ids, "
                                                                       "ignored",
                advice="another node on the bus asks for the unit's ids", arrival=True),
        Counted("can_incomplete", "samples dropped because a frame of theirs never came (source.window_samples, "
                                  "window_s)", fault="can_incomplete", label="CAN samples incomplete",
                what="{n:,} CAN sample(s) dropped, a frame of each never came (each is also one of the samples "
                     "missed, not a loss beside them)"),
        Counted("duplicates", "frames for a sample already held or settled, dropped", fault="duplicates",
                label="duplicate CAN frames", what="{n:,} frame(s) for a sample already held or settled, dropped",
                advice="sent twice by the unit or a gateway, or a late copy"),
        Counted("restarts", "the unit restarted: its sample counter back near zero, followed on", fault="restarts",
                label="unit restart", what="{n:,} restart(s) of the unit: its sample counter went back near zero",
                advice="followed: seq and time go on from the last sample's; the samples the unit sent before the first "
                       "one received are counted missed (its new counter says how many), none that never existed",
                one_shot=True),
    ) + icd_samples("whose frames came whole", flags="; none on CAN: its frames carry no flags byte"),
    no_decode=NoDecode(
        "frames",
        begin="frames arrive on the bus but none with the unit's ids (base id? probe count?): {n:,} frames in {t}, "
              "0 of the unit's; is the unit sending? check source.base_id and unit.n_probes against the unit "
              "(health: counters.foreign_frames)",
        end="the unit's frames decode again after {t}; {n:,} frames of other ids in between",
        total="{k} stretch(es) of frames on the bus and none of the unit's ({n:,} frames)",
        label="no frame of the unit's"))

KIND = SourceKind(
    "can", "the unit's frames on a CAN bus, through any python-can interface (socketcan, slcan, virtual, ...)",
    config="fluxcal.drivers.can_source:CanConfig",
    factory="fluxcal.drivers.can_source:open_source",
    counters=(
        Counted("foreign_frames", "frames of other nodes' (or reserved, or extended) ids: the bus is shared, not a "
                                  "fault", arrival=True),
        Counted("error_frames", "error frames the interface reports", fault="error_frames", label="CAN error frames",
                what="{n:,} error frame(s) reported by the interface",
                advice="faults on the bus itself: check its termination, wiring and bitrate", arrival=True),
        Counted("bad_frames", "what the adapter gave that is no frame (a garbled SLCAN line), dropped",
                fault="bad_frames", label="bad CAN frames",
                what="{n:,} line(s) or frame(s) from the CAN adapter that are no frame, dropped",
                advice="garbled on the adapter's serial link or by its firmware: check the USB cable and the adapter",
                arrival=True),
    ),
    protocols=(ICD,),
    transports=(Transport("can-virtual", "the ICD's CAN frames on python-can's in-process virtual bus",
                          link="fluxcal.drivers.sim.can_ports:virtual_link"),
                Transport("slcan", "the ICD's CAN frames as an SLCAN adapter's lines on a pseudo-terminal",
                          link="fluxcal.drivers.sim.can_ports:slcan_link", process=True)),
    port_keys=("source.interface", "source.channel"),
    unit_clock=False,
    needs_rate=True,
)
