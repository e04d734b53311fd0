"""pnvlad command line (installed as the ``pnvlad_cli`` package).

Each command group lives in the module named for it; the commands are thin: they parse options,
call into :mod:`pnvlad_service` and print. Heavy imports (torch, faiss, fastapi) happen inside
command bodies so that ``pnvlad --help`` answers at once.
"""
