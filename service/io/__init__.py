"""The I/O wing: the world's formats and wires, and no math beyond unit scaling.

bus (Zenoh: settings and security, key space and encodings, the service's side, the client side),
recordings (MCAP writer and reader, lab CSV), encoding (binary layouts shared by both), calfile (the
calibration file), report (the HTML report). Imports numerics for their data types, never wiring.
"""
