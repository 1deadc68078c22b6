"""Shared helpers of the FroDO graph: message conversions, geometry, categories, stamp-matched frame cache, MCAP bag IO, node base with diagnostics, evaluation protocol."""
