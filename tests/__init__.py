"""The test suite; subfolders mirror pnvlad_service/ (a package: tests/io never shadows io)."""
