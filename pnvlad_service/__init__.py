"""pnvlad: LiDAR place recognition (PointNetVLAD) as a library, a CLI and an HTTP service.

Data flows one way through the modules named for each job::

    readers -> preprocess (filter G) -> prepare (drives to submaps) -> benchmark / splits
            -> models (encoder) -> train / evaluate -> index (FAISS bundle) -> server

Heavy dependencies (torch, faiss, fastapi) are imported only by the modules that need them,
so ``import pnvlad_service`` and ``pnvlad --help`` stay fast.
"""

__version__ = "0.1.0"
