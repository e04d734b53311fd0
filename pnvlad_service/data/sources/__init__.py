"""Where drives come from: each module reads one kind of recording into the
:class:`~pnvlad_service.data.drive.Drive` face (timestamps, poses, ``scan(i)``), or helps one
do so.

- :mod:`.kitti`: KITTI-odometry sequence folders (:class:`~.kitti.KittiSequence`).
- :mod:`.csv_drive`: a folder of scans plus a CSV of poses (:class:`~.csv_drive.CsvDrive`).
- :mod:`.rosbag`: ROS 1 / ROS 2 bags (:class:`~.rosbag.RosbagDrive`; without poses
  :class:`~.rosbag.RosbagClouds`), with :mod:`.pointcloud2` decoding their clouds and
  :mod:`.pose_streams` their poses and /tf; :mod:`.rosbag_write` writes a drive as a bag.
- :mod:`.odometry`: poses estimated from the scans alone (KISS-ICP), for a robot without a pose
  stream.
"""
