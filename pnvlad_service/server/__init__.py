"""The HTTP layer over ``pnvlad_service.localization`` (FastAPI): ``app`` (the factory and its
lifespan), ``routes`` (one router per resource), ``deps`` (what the routes are handed),
``contract`` and ``bodies`` (request bodies to validated clouds), ``schemas`` (responses),
``problems`` (problem+json errors), ``middleware``, ``metrics`` and ``settings``."""
