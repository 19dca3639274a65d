"""The wiring wing: what joins numerics and I/O into the service and its commands.

pipeline (the one pipeline of live input, replay and `fit --method rls`, with its gate and live
effects), daemon (`fluxcal run`: input, pipeline, sinks), config (the TOML configuration), fitting
(batch calibration of lab data), cli and commands/ (one module per command).
"""
