"""fluxcal's own kinds of input, one declaration a module (`KIND`, a fluxcal.drivers.declare.SourceKind): fluxcal.drivers.registry
finds every module here, and installed packages' and registered kinds beside them (docs/sources.md)."""
