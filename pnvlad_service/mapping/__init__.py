"""Mapping: a map's runs aligned into one map that agrees with itself (``pnvlad map align``):
a pose graph of odometry, verified loop closures and GNSS/INS fixes, solved by GTSAM."""
