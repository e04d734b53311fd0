"""The filter G: one raw point cloud in metres to one benchmark submap (stage: preprocess).

- :mod:`~pnvlad_service.preprocess.filter_g`: the filter and its settings (``GConfig``,
  ``apply_g``, ``filter_g``, ``scan_config`` for single scans) and the crop, ground and
  normalisation steps;
- :mod:`~pnvlad_service.preprocess.ground`: the ground plane and the height map under a cloud;
- :mod:`~pnvlad_service.preprocess.voxel`: the voxel grid sized to the target count, and the
  column-by-column reductions every step uses.

It imports none of the stages but ``io``: ``data`` (making submaps), ``synth``, ``index``,
``localization`` (raw-scan queries) and ``evaluation`` run G from here.
"""
