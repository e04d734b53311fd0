"""FAISS index bundles of a map: key choice, the bundle on disk, building, adding (stage: index)."""
