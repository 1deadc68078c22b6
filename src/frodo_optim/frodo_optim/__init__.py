"""Optimiser node: per-object pose and shape refinement (paper Sec. 4.3) and mesh publication."""
