"""The benchmark's metrics (recall@N, recall@1%), the hand-crafted baseline, ``pnvlad eval``."""
