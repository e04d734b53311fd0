"""Answering "where am I?": a bundle and a model loaded together, queries embedded and searched,
concurrent queries batched (stage: serve, without HTTP)."""
