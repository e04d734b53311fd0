"""The benchmark submap format: one submap is 4096 points, x, y, z in the normalised frame.

On disk (the published PointNetVLAD layout) a submap is a ``<timestamp>.bin`` file of
little-endian float64 x, y, z interleaved, no header: 4096 × 3 × 8 = 98,304 bytes, every
coordinate in [-1, 1]. In memory the encoder takes float32 [B, 4096, 3].
"""

from __future__ import annotations

#: Points in one submap (the encoder's input size).
SUBMAP_POINTS = 4096
#: Element type of a ``.bin`` submap on disk.
SUBMAP_DTYPE = "<f8"
#: Bytes of one ``.bin`` submap: float64 × 3 × 4096.
SUBMAP_BYTES = SUBMAP_POINTS * 3 * 8
#: Largest |coordinate| of a submap (the normalised frame is [-1, 1]).
SUBMAP_BOUND = 1.0
