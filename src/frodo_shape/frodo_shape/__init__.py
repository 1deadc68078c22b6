"""Joint point/SDF shape embedding, image encoder, code fusion, training pipeline and shipped priors (paper Sec. 4, 4.2)."""
