"""A drive's robotics outputs, from one description of a step: the live view in Foxglove, the
same as an MCAP file, a ROS 2 bag, TUM and KITTI trajectories.

- :mod:`.step`: what a drive step is (:class:`~.step.DriveStep`), the map under it
  (:class:`~.step.MapView`), the ``map`` frame (:class:`~.step.Frames`) and the frames and units
  every output uses;
- :mod:`.sinks`: the :class:`~.sinks.Sink` interface, :class:`~.sinks.Outputs` (the sinks of a
  run; a failing one dropped with a one-line error) and :func:`~.sinks.open_outputs`;
- :mod:`.foxglove_view`: the live view and the MCAP (Foxglove SDK, extra ``view``);
- :mod:`.ros2bag`: the ROS 2 bag (``rosbags``, extra ``rosbag``);
- :mod:`.trajectory`: the TUM and KITTI files (evo reads them);
- :mod:`.map_view`: the map of an index bundle; :mod:`.mcap_track`: a drive read back from its
  MCAP and drawn.

It knows nothing of drives or queries: the drive runner (and the server) hand it steps.
"""
