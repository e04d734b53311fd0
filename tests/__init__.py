"""The test suite; subfolders mirror pnvlad_service/ (a package, so tests/io does not shadow the io module)."""
