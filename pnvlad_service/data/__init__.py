"""From raw scans to benchmark data: the filter G, drives cut into submaps, trees on disk,
training tuples and evaluation sets, and the clouds loaded for training (stage: preprocess)."""
