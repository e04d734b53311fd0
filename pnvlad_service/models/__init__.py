"""pnvlad_service.models."""
