"""Answering "where am I?" without HTTP, by job: ``query`` (the one query type, the path that
runs it, the localiser, limits, answers, batching, the map in service), ``verify`` (registration
to candidates or near a prior, in this process or a child), the drive (``tracking``,
``follow``, ``replay``) and ``client`` (the HTTP client of the server)."""
