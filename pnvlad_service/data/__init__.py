"""From raw scans to benchmark data: drives and their sources, drives cut into submaps through
the filter G (:mod:`pnvlad_service.preprocess`), trees on disk, training tuples and evaluation
sets, and the clouds loaded for training (stage: data)."""
