"""Procedural furniture shapes, user mesh loading, synthetic rooms and renderer, dataset converters and contract bag writing."""
