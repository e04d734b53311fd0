"""A bag whose drive has position fixes only: its clouds, and a ``sensor_msgs/NavSatFix``
topic turned into UTM fixes, laid together by KISS-ICP (:mod:`.fix_odometry`).

``pnvlad data prepare --rosbag BAG --cloud-topic /points --fix-topic /fix --odometry kiss-icp
--utm-zone 32U`` opens one with :func:`open_fix_drive`. A fix whose ``status.status`` is
negative (no fix) is dropped; its horizontal standard deviation is ``sqrt(cov_xx + cov_yy)``
of ``position_covariance`` where ``position_covariance_type`` is not 0 (unknown), else not
given. A fix is stamped by its header (the bag's time where that is zero); fixes with a
repeated stamp keep the first.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from pnvlad_service.data.sources.fix_odometry import FixOdometryDrive
from pnvlad_service.data.sources.fixes import Fixes
from pnvlad_service.data.sources.rosbag import RosbagClouds
from pnvlad_service.errors import InputError

NAVSAT_TYPE = "sensor_msgs/msg/NavSatFix"


def read_navsat(clouds: RosbagClouds, topic: str, utm_zone: str) -> Fixes:
    """The fixes of ``topic`` (NavSatFix) in the bag ``clouds`` holds open, in UTM ``utm_zone``.
    ``InputError`` naming the bag for a missing topic, one of another type, or no fix."""
    from pnvlad_service.io.utm import from_latlon

    rows = []
    for stamp, msg in clouds.topic_messages(topic, (NAVSAT_TYPE,), "NavSatFix"):
        if int(msg.status.status) < 0:
            continue
        cov = msg.position_covariance
        std = math.sqrt(cov[0] + cov[4]) if int(msg.position_covariance_type) else math.nan
        rows.append((stamp, msg.latitude, msg.longitude, msg.altitude, std))
    if len(rows) < 3:
        raise InputError(f"topic {topic!r}: {len(rows)} fixes (status >= 0); need 3", clouds.bag)
    arr = np.array(rows, dtype=np.float64)
    stamps = (np.array([r[0] for r in rows], dtype=np.int64) + 500) // 1000
    order = np.argsort(stamps, kind="stable")
    keep = order[np.r_[True, np.diff(stamps[order]) > 0]]
    east, north = from_latlon(utm_zone, arr[keep, 1], arr[keep, 2], "--utm-zone")
    fixes = Fixes(stamps[keep], np.stack([east, north, arr[keep, 3]], axis=1), arr[keep, 4])
    return fixes.checked(clouds.bag)


def open_fix_drive(
    bag: str | Path, cloud_topic: str, fix_topic: str, utm_zone: str, *, progress: bool = True
) -> FixOdometryDrive:
    """The drive of ``bag``'s clouds posed by KISS-ICP laid onto its NavSatFix fixes (module
    doc). Holds the bag open until its ``close()``."""
    if not utm_zone:
        raise InputError(
            "NavSatFix fixes are latitudes and longitudes: give the zone", "--utm-zone"
        )
    clouds = RosbagClouds(bag, cloud_topic)
    try:
        fixes = read_navsat(clouds, fix_topic, utm_zone)
        drive = FixOdometryDrive(clouds, fixes, progress=progress)
    except BaseException:
        clouds.close()
        raise
    drive.pose_source = f"KISS-ICP odometry laid onto {len(drive.fixes)} fixes of {fix_topic}"
    return drive
