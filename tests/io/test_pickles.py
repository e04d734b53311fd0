"""io.pickles: plain data loads, anything naming a class is refused before it runs."""

from __future__ import annotations

import collections
import os
import pickle
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pnvlad_service.errors import InputError
from pnvlad_service.io.pickles import dump_plain, safe_load, safe_loads

PUBLISHED_LIKE = [
    {
        0: {
            "query": "oxford/2014-11-14-16-34-33/pointcloud_20m/1415985057262127.bin",
            "northing": 5735747.67,
            "easting": 619998.34,
            1: [7, 6],
            2: [4, 3, 2],
            3: [],
        }
    },
    {0: {"query": "x.bin", "northing": -1.5e-300, "easting": float("inf"), 0: [2**40]}},
]


class Evil:
    def __reduce__(self):
        return (os.mkdir, ("/nonexistent-should-not-run",))


@pytest.mark.parametrize("protocol", range(0, pickle.HIGHEST_PROTOCOL + 1))
def test_published_structures_load_in_every_protocol(tmp_path: Path, protocol: int) -> None:
    p = tmp_path / "q.pickle"
    p.write_bytes(pickle.dumps(PUBLISHED_LIKE, protocol=protocol))
    assert safe_load(p) == PUBLISHED_LIKE


def test_crafted_global_opcode_is_refused_and_never_runs(tmp_path: Path) -> None:
    target = tmp_path / "made_by_pickle"
    # protocol 0 by hand: GLOBAL os.mkdir, a tuple with the path, REDUCE
    payload = f"cos\nmkdir\n(V{target}\ntR.".encode()
    # the same bytes do run under the standard unpickler: the test's payload is live
    other = tmp_path / "proof"
    pickle.loads(f"cos\nmkdir\n(V{other}\ntR.".encode())
    assert other.is_dir()
    p = tmp_path / "evil.pickle"
    p.write_bytes(payload)
    with pytest.raises(InputError) as exc:
        safe_load(p)
    assert "os.mkdir" in str(exc.value)
    assert exc.value.source == str(p)
    assert not target.exists()


@pytest.mark.parametrize(
    ("obj", "named"),
    [
        (Evil(), "mkdir"),
        (np.float64(1.5), "numpy"),
        ({"a": np.arange(3)}, "numpy"),
        (collections.OrderedDict(a=1), "OrderedDict"),
        (set([1, 2]), "set"),
    ],
)
def test_pickles_naming_a_class_are_refused(tmp_path: Path, obj: object, named: str) -> None:
    p = tmp_path / "x.pickle"
    p.write_bytes(pickle.dumps(obj, protocol=2))
    with pytest.raises(InputError, match=named):
        safe_load(p)


def test_sets_need_no_class_from_protocol_4() -> None:
    assert safe_loads(pickle.dumps({1, 2, 3}, protocol=4)) == {1, 2, 3}


@pytest.mark.parametrize("cut", [1, 10, 50, -1])
def test_truncated_pickle_is_an_input_error(tmp_path: Path, cut: int) -> None:
    data = pickle.dumps(PUBLISHED_LIKE, protocol=4)
    p = tmp_path / "t.pickle"
    p.write_bytes(data[:cut])
    with pytest.raises(InputError) as exc:
        safe_load(p)
    assert exc.value.source == str(p)


@pytest.mark.parametrize("data", [b"", b"not a pickle at all", b"\x80\x05\xff\xff", b"{}"])
def test_garbage_is_an_input_error(tmp_path: Path, data: bytes) -> None:
    p = tmp_path / "g.pickle"
    p.write_bytes(data)
    with pytest.raises(InputError, match=r"g\.pickle"):
        safe_load(p)


def test_missing_file_and_directory(tmp_path: Path) -> None:
    with pytest.raises(InputError, match="not found"):
        safe_load(tmp_path / "nope.pickle")
    with pytest.raises(InputError, match="directory"):
        safe_load(tmp_path)


def test_dump_plain_refuses_numpy_and_leaves_nothing(tmp_path: Path) -> None:
    p = tmp_path / "out.pickle"
    with pytest.raises(InputError, match="numpy"):
        dump_plain({0: {"positives": [np.int64(3)]}}, p)
    assert not p.exists()
    assert list(tmp_path.iterdir()) == []


plain = st.recursive(
    st.none()
    | st.booleans()
    | st.integers()
    | st.floats(allow_nan=False)
    | st.text(max_size=20)
    | st.binary(max_size=10),
    lambda children: (
        st.lists(children, max_size=4)
        | st.dictionaries(st.integers() | st.text(max_size=5), children, max_size=4)
    ),
    max_leaves=20,
)


@settings(max_examples=60, deadline=None)
@given(obj=plain)
def test_dump_plain_round_trips_through_safe_load(tmp_path_factory, obj) -> None:
    p = tmp_path_factory.mktemp("rt") / "x.pickle"
    dump_plain(obj, p)
    assert safe_load(p) == obj
    assert pickle.loads(p.read_bytes()) == obj
