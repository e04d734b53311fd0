"""FAISS index bundles of a map (stage: index).

- :mod:`~pnvlad_service.index.keys`: the FAISS key by size and memory budget, search
  parameters, recall@1 against exact search;
- :mod:`~pnvlad_service.index.manifest`: the typed, frozen ``manifest.json``, which owns the
  model-compatibility check;
- :mod:`~pnvlad_service.index.bundle`: the bundle on disk, loaded (search, matches) and written;
- :mod:`~pnvlad_service.index.geometry`: the database submaps' points in metres (float16,
  memory-mapped, checked at start-up and per fetch) for geometric verification;
- :mod:`~pnvlad_service.index.smoothing`: a map's descriptors blended with their neighbours'
  along (or across) its drives;
- :mod:`~pnvlad_service.index.tree_records`: what a tree's runs recorded that a bundle copies;
- :mod:`~pnvlad_service.index.build`: listing and embedding a tree's submaps, building, adding,
  sharded building under torchrun.
"""
