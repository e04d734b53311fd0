"""One APIRouter per resource: ``localize`` (POST /localize, /localize/batch) and ``ops``
(health, readiness, info, metrics)."""
