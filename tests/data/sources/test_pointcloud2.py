"""data.sources.pointcloud2: the decoder's size checks on hand-made messages (the bags of
test_rosbag.py cover the layouts)."""

from __future__ import annotations

import numpy as np
import pytest

from pnvlad_service.data.sources.pointcloud2 import CloudError, decode_pointcloud2


def test_decode_refuses_clouds_whose_sizes_do_not_fit() -> None:
    from types import SimpleNamespace as NS

    fields = [NS(name=n, offset=4 * k, datatype=7, count=1) for k, n in enumerate("xyz")]
    ok = NS(
        height=1,
        width=2,
        fields=fields,
        is_bigendian=False,
        point_step=12,
        row_step=24,
        data=np.zeros(24, np.uint8),
    )
    assert decode_pointcloud2(ok).shape == (2, 3)
    with pytest.raises(CloudError, match="need 24 bytes of data, the message has 20"):
        decode_pointcloud2(NS(**{**ok.__dict__, "data": np.zeros(20, np.uint8)}))
    with pytest.raises(CloudError, match="does not fit a point of 10 bytes"):
        decode_pointcloud2(NS(**{**ok.__dict__, "point_step": 10, "row_step": 20}))
    empty = NS(**{**ok.__dict__, "width": 0, "row_step": 0, "data": np.zeros(0, np.uint8)})
    assert decode_pointcloud2(empty).shape == (0, 3)
