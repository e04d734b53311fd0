"""pnvlad_service.synth."""
