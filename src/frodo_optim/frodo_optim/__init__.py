"""Optimiser node: per-object pose and shape refinement (paper Sec. 5.3) and mesh publication."""
