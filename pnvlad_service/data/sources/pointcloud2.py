"""sensor_msgs/PointCloud2 decoding: x, y, z of any layout into [N, 3], with numpy only.

:func:`decode_pointcloud2` reads x, y and z (float32 or float64, any offsets, any point step,
extra fields ignored, organised clouds with padded rows, either byte order) through one
structured dtype: no per-point Python loop. :func:`header_stamp` reads a serialised message's
header stamp and frame without decoding the message (ROS 1 and ROS 2 CDR wire formats), so a
bag's clouds can be indexed without decoding every cloud.
"""

from __future__ import annotations

import struct
from typing import Any

import numpy as np

#: PointField datatype -> numpy type code (sensor_msgs/PointField constants).
POINTFIELD_TYPES = {1: "i1", 2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4", 7: "f4", 8: "f8"}
_FIELD_NAMES = {1: "INT8", 2: "UINT8", 3: "INT16", 4: "UINT16", 5: "INT32", 6: "UINT32"}


class CloudError(ValueError):
    """A PointCloud2 message that cannot be decoded (the drive adds the bag and topic)."""


def decode_pointcloud2(msg: Any) -> np.ndarray:
    """x, y, z of a ``sensor_msgs/msg/PointCloud2`` message: [height * width, 3], row order.

    float32 when x, y and z are all float32, else float64; non-finite points are kept (the
    drive drops and counts them). ``msg`` needs ``height``, ``width``, ``fields`` (``name``,
    ``offset``, ``datatype``), ``is_bigendian``, ``point_step``, ``row_step`` and ``data``.
    Raises :class:`CloudError` on a cloud without x/y/z, with integer coordinates, or whose
    sizes do not fit its data.
    """
    fields = {}
    for f in msg.fields:
        fields.setdefault(f.name, f)
    missing = [n for n in "xyz" if n not in fields]
    if missing:
        names = ", ".join(f.name for f in msg.fields) or "none"
        raise CloudError(f"PointCloud2 without field(s) {', '.join(missing)} (fields: {names})")
    order = ">" if msg.is_bigendian else "<"
    formats, offsets = [], []
    for n in "xyz":
        f = fields[n]
        code = POINTFIELD_TYPES.get(int(f.datatype))
        if code not in ("f4", "f8"):
            kind = _FIELD_NAMES.get(int(f.datatype), f"datatype {f.datatype}")
            raise CloudError(f"field {n} is {kind}: x, y and z must be float32 or float64")
        if f.offset + int(code[1]) > msg.point_step:
            raise CloudError(
                f"field {n} at offset {f.offset} does not fit a point of {msg.point_step} bytes"
            )
        formats.append(order + code)
        offsets.append(int(f.offset))
    height, width = int(msg.height), int(msg.width)
    step, row = int(msg.point_step), int(msg.row_step)
    out_dtype = np.float32 if all(c.endswith("f4") for c in formats) else np.float64
    if height * width == 0:
        return np.empty((0, 3), dtype=out_dtype)
    data = np.asarray(msg.data, dtype=np.uint8).reshape(-1)
    need = (height - 1) * row + width * step
    if row < width * step or data.size < need:
        raise CloudError(
            f"{height} x {width} points of {step} bytes in rows of {row} bytes need "
            f"{need} bytes of data, the message has {data.size}"
        )
    dtype = np.dtype(
        {"names": list("xyz"), "formats": formats, "offsets": offsets, "itemsize": step}
    )
    grid = np.ndarray((height, width), dtype=dtype, buffer=data, strides=(row, step))
    pts = np.empty((height * width, 3), dtype=out_dtype)
    for k, n in enumerate("xyz"):
        pts[:, k] = grid[n].reshape(-1)
    return pts


def header_stamp(raw: bytes | memoryview, ros2: bool) -> tuple[int, str] | None:
    """(header stamp ns, frame_id) read from a serialised message that starts with a Header.

    ROS 1: seq, secs, nsecs, frame_id; ROS 2 CDR: 4 bytes of encapsulation, sec, nanosec,
    frame_id (NUL-terminated). ``None`` for an encapsulation this does not know (the caller then
    deserialises the message).
    """
    if ros2:
        kind = raw[1]
        if raw[0] != 0 or kind not in (0, 1):
            return None
        fmt = "<" if kind == 1 else ">"
        sec, nsec, n = struct.unpack_from(fmt + "iII", raw, 4)
        n = max(n - 1, 0)  # the CDR string's length counts its NUL
    else:
        sec, nsec, n = struct.unpack_from("<III", raw, 4)
    frame = bytes(raw[16 : 16 + n])
    if len(frame) != n:
        raise struct.error("frame_id runs past the end of the message")
    return sec * 1_000_000_000 + nsec, frame.decode("utf-8", "replace")
