"""data.cuts: where submaps are cut along a drive, against an independent plain loop over
travelled distance."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pnvlad_service.data.cuts import check_box_m, resolve_geometry, submap_cuts
from pnvlad_service.errors import InputError
from tests.data.helpers import FRAMES, STEP_M, plain_cuts


@settings(max_examples=150, deadline=None)
@given(
    steps=st.lists(st.sampled_from([0.0, 0.25, 0.5, 1.0, 1.5, 3.0, 12.5]), min_size=1, max_size=80),
    window=st.sampled_from([5.0, 10.0, 20.0, 25.0]),
    stride=st.sampled_from([2.5, 10.0, 20.0, 25.0]),
)
def test_cuts_match_a_plain_loop(steps: list[float], window: float, stride: float) -> None:
    d = [0.0]
    for s in steps:
        d.append(d[-1] + s)
    cuts = submap_cuts(np.array(d), window, stride)
    expected = plain_cuts(d, window, stride)
    assert [c.scan for c in cuts] == [e[0] for e in expected]
    assert [list(range(c.first, c.last + 1)) for c in cuts] == [e[1] for e in expected]


def test_cuts_on_a_regular_drive() -> None:
    d = np.arange(FRAMES) * STEP_M  # 0 .. 58.5 m
    train = submap_cuts(d, 20.0, 10.0)
    test = submap_cuts(d, 20.0, 20.0)
    # Centres at 10, 20, 30, 40 m (50 m + 10 m > 58.5 m); nearest scans 10.5, 19.5, 30, 40.5.
    assert [c.scan for c in train] == [7, 13, 20, 27]
    assert [c.scan for c in test] == [7, 20]
    assert (train[0].first, train[0].last) == (0, 13)


@pytest.mark.parametrize("bad", [-1.0, -0.0001, float("nan"), float("inf"), float("-inf"), "x"])
def test_a_bad_box_is_one_line_naming_box_m(bad: object) -> None:
    for allow_zero in (False, True):
        with pytest.raises(InputError) as exc:
            check_box_m(bad, allow_zero=allow_zero)  # type: ignore[arg-type]
        assert exc.value.source == "box_m" and "\n" not in str(exc.value)
    with pytest.raises(InputError, match="box_m"):
        resolve_geometry("oxford", "test", None, bad, None)  # type: ignore[arg-type]


def test_box_none_is_none_and_zero_is_none_only_where_allowed() -> None:
    assert check_box_m(None) is None and check_box_m(None, allow_zero=True) is None
    assert check_box_m(30) == 30.0 and isinstance(check_box_m(30), float)
    assert check_box_m(0, allow_zero=True) is None
    with pytest.raises(InputError, match="box_m"):
        check_box_m(0)
    # The layouts' defaults where no box is given; 0 turns the in-house box off.
    assert resolve_geometry("oxford", "train", None, None, None)[3] is None
    assert resolve_geometry("inhouse", "train", None, None, None)[3] == 25.0
    assert resolve_geometry("inhouse", "train", None, 0, None)[3] is None
    assert resolve_geometry("oxford", "test", None, 30, None)[3] == 30.0
