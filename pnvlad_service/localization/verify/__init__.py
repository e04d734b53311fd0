"""Verifying by registration: a query registered to its retrieved candidates (or to the map near
a prior pose), in this process or in a child process, behind one :class:`~.verifier.Verifier`."""
