"""pnvlad_service.server."""
