"""Answering "where am I?" without HTTP: ``limits`` (what a query may hold, the check of a
cloud), ``localizer`` (a bundle and its model loaded together, typed answers), ``batching``
(concurrent callers share forward passes) and ``client`` (the HTTP client of the server)."""
