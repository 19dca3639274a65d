"""The serial kind: the unit's frames on a serial port (RS-422 / USB-serial, a pty, any pyserial URL); the ICD's
frames are its first protocol (drivers/serial_source.py, drivers/assemble.py)."""

from __future__ import annotations

from ..declare import Counted, NoDecode, Protocol, SourceKind, Transport
from ._icd import icd_samples

ICD = Protocol(
    "icd", "the ICD's binary frames: sync, version, probe count, counter, unit clock in us, counts, CRC-16",
    decoder="fluxcal.drivers.serial_source:SerialIcd",
    counters=(
        Counted("frames_accepted", "frames with a good CRC", decoded=True, what="{n:,} frame(s) with a good CRC"),
        Counted("crc_failures", "frames failing their CRC (bit errors on the line)", fault="crc", label="CRC failures",
                what="{n:,} frame(s) failed their CRC",
                advice="bit errors on the line: check the cable, its screen and its length for the baud rate",
                share="frames"),
        Counted("bytes_skipped", "bytes that belong to no frame (noise, a cut frame, a wrong baud rate)"),
        Counted("duplicates", "frames repeating one received before bit for bit, dropped", fault="duplicates",
                label="duplicate frames", what="{n:,} frame(s) repeating one received before bit for bit, dropped",
                advice="sent again by the unit or a link that replays its buffer"),
        Counted("seq_backsteps", "frames whose counter or clock stepped back, no copy of one received (stale), dropped",
                fault="backsteps", label="frames stepping back",
                what="{n:,} frame(s) whose counter or clock stepped back, no copy of one received, dropped",
                advice="a stale frame, or a unit counter that jumped back"),
        Counted("restarts", "the unit restarted: counter and clock back near zero, followed on", fault="restarts",
                label="unit restart", what="{n:,} restart(s) of the unit: its counter and clock went back near zero",
                advice="followed: seq and time go on from the last sample's; the samples the unit sent before the first "
                       "one received are counted missed (its new counter says how many), none that never existed",
                one_shot=True),
        Counted("clock_jumps", "the unit's clock jumped while its counter ran on: time repaired from the counter",
                fault="clock_jumps", label="unit clock jump",
                what="{n:,} jump(s) of the unit's clock while its counter ran on",
                advice="time repaired from the counter at the unit's period: no sample lost or made up", one_shot=True),
        Counted("counter_jumps", "the unit's counter jumped while its clock ran on: no sample counted missed",
                fault="counter_jumps", label="unit counter jump",
                what="{n:,} jump(s) of the unit's counter while its clock ran on",
                advice="followed by the clock: no sample counted missed that the clock says never existed",
                one_shot=True),
    ) + icd_samples("with a good CRC"),
    no_decode=NoDecode(
        "bytes",
        begin="bytes arrive but no frame decodes (baud rate? probe count?): {n:,} bytes in {t}, 0 frames; check "
              "source.baudrate and unit.n_probes against the unit (health: counters.bytes_skipped)",
        end="frames decode again after {t}; {n:,} bytes in between decoded into no frame",
        total="{k} stretch(es) of bytes that decoded into no frame ({n:,} bytes)"))

KIND = SourceKind(
    "serial", "the unit's frames on a serial port: a device path (/dev/ttyUSB0, /dev/pts/N) or a pyserial URL",
    config="fluxcal.drivers.serial_source:SerialConfig",
    factory="fluxcal.drivers.serial_source:open_source",
    counters=(Counted("bytes_received", "every byte read from the port", arrival=True),),
    protocols=(ICD,),
    transports=(Transport("pty", "the ICD's bytes through a pseudo-terminal, read by this kind",
                          link="fluxcal.drivers.sim.ports:pty_link", process=True),),
    port_keys=("source.port",),
    unit_clock=True,
    needs_rate=True,
)
