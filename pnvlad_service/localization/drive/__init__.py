"""Localising a drive: its scans, in time order, to the service by one of two policies, one row
a scan, a CSV, a report and a PNG.

- :mod:`.service`: what a drive asks (:class:`~.service.Ask`, a server or a bundle in this
  process) and the typed :class:`~.service.Reply` it reads back;
- :mod:`.tracking`: the drive localiser (:class:`~.tracking.DriveLocalizer`): search until a
  fix is confirmed, track near the odometry's prediction, say when lost;
- :mod:`.runner`: the one drive runner (:func:`~.runner.run_drive`), ``per-scan`` (each scan
  asked alone) or ``tracked`` (the drive localiser);
- :mod:`.rows`: :class:`~.rows.DriveRow` and its CSV; :mod:`.report`: the summary and the
  stages' times; :mod:`.plot`: the PNG; :mod:`.maps`: what the report knows of the map;
- :mod:`.config` and :mod:`.job`: a whole drive from its settings (``pnvlad localize
  --rosbag`` / ``--kitti``).

Each scan also goes, as a :class:`~pnvlad_service.localization.outputs.step.DriveStep`, to the
run's sinks (:mod:`pnvlad_service.localization.outputs`: the live view in Foxglove, MCAP, a
ROS 2 bag, TUM / KITTI trajectories).

Example, a KITTI sequence followed against a server::

    from pnvlad_service.client import LocalizeClient
    from pnvlad_service.data.sources.kitti import KittiSequence
    from pnvlad_service.localization.drive.runner import run_drive
    from pnvlad_service.localization.drive.service import http_ask

    drive = KittiSequence("sequences/00")
    with LocalizeClient("http://127.0.0.1:8000") as client:
        rows = run_drive(drive, http_ask(client), "tracked", truth=drive.poses)
"""
