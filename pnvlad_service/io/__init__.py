"""Reading and writing point-cloud files and the benchmark's published files (stage: read)."""
