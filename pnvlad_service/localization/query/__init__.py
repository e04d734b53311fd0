"""Answering a query: the one query type and the path that runs it (:mod:`.run`), the
localiser (bundle and encoder loaded together), the request limits, the typed answers, the
micro-batcher, the map in service, the calibration, the thread counts and the compatibility
check of a bundle and its model."""
