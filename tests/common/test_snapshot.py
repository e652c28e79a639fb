"""Restored documents are read value by value: the wrong type, shape or range is a SnapshotError
that names the field."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from services.common.protocol import pack_document, unpack_document
from services.common.snapshot import SnapshotError, SnapshotReader

GOOD: dict[str, Any] = {
    "n": 3, "x": 0.5, "flag": True, "frame": "camera", "none": None,
    "v": np.array([1.0, 0.0, 0.0]), "C": np.eye(2), "T": np.eye(4), "inner": {"k": 1},
    "empty": np.zeros((0, 48)), "scores": np.array([0.0, -np.inf]),
}


def reader() -> SnapshotReader:
    return SnapshotReader(unpack_document(pack_document(GOOD)), "doc")


def test_good_values_come_back() -> None:
    r = reader()
    assert (r.integer("n", 0, 3), r.number("x"), r.boolean("flag")) == (3, 0.5, True)
    assert r.choice("frame", ("camera", "world")) == "camera"
    assert r.optional_integer("none") is None and r.optional_map("none") is None
    assert r.map("inner").integer("k") == 1 and r.map("inner").path == "doc.inner"
    np.testing.assert_array_equal(r.unit_vector("v"), [1.0, 0.0, 0.0])
    np.testing.assert_array_equal(r.covariance("C", 2), np.eye(2))
    np.testing.assert_array_equal(r.pose("T"), np.eye(4))
    assert r.array("empty", (0, 48)).shape == (0, 48)
    assert r.array("scores", (2,), allow_minus_inf=True)[1] == -np.inf
    # lists (a JSON-like document) work as well as arrays
    assert SnapshotReader({"a": [[1, 0], [0, 1]]}, "d").covariance("a", 2).dtype == np.float64


@pytest.mark.parametrize(("read", "message"), [
    (lambda r: r.integer("missing"), "doc.missing: missing"),
    (lambda r: r.integer("x"), "doc.x: expected an integer"),
    (lambda r: r.integer("flag"), "doc.flag: expected an integer"),
    (lambda r: r.integer("n", 4), r"doc.n: 3 is outside \[4, None\]"),
    (lambda r: r.number("frame"), "doc.frame: expected a number"),
    (lambda r: r.boolean("n"), "doc.n: expected true/false"),
    (lambda r: r.choice("frame", ("world",)), r"doc.frame: expected one of \['world'\]"),
    (lambda r: r.map("n"), "doc.n: expected a map"),
    (lambda r: r.array("v", (4,)), r"doc.v: expected shape \(4,\), got \(3,\)"),
    (lambda r: r.array("frame", (3,)), "doc.frame: expected an array"),
    (lambda r: r.array("scores", (2,)), "doc.scores: contains NaN or infinity"),
    (lambda r: r.unit_vector("C", 2), r"doc.C: expected shape \(2,\)"),
    (lambda r: r.pose("C"), r"doc.C: expected shape \(4, 4\)"),
])
def test_each_fault_names_its_field(read: Any, message: str) -> None:
    with pytest.raises(SnapshotError, match=message):
        read(reader())


@pytest.mark.parametrize(("value", "check", "message"), [
    (float("nan"), lambda r: r.number("a"), "not finite"),
    (np.array([1.0, np.nan]), lambda r: r.array("a", (2,)), "NaN or infinity"),
    (np.array([1, 2], dtype="|u1"), lambda r: r.array("a", (2,)), None),
    (np.array([b"ab"]), lambda r: r.array("a", (1,)), "numeric array"),
    ([[1, "x"]], lambda r: r.array("a", (1, 2)), "not a numeric array"),
    (np.array([0.0, 2.0, 0.0]), lambda r: r.unit_vector("a"), "not a unit vector"),
    (np.array([[1.0, 0.5], [0.0, 1.0]]), lambda r: r.covariance("a", 2), "not symmetric"),
    (-np.eye(2), lambda r: r.covariance("a", 2), "negative variance"),
    (2.0 * np.eye(4), lambda r: r.pose("a"), "not a rigid transform"),
    ("x", lambda r: r.pose("a"), "expected an array"),
])
def test_bad_values_are_refused(value: Any, check: Any, message: str | None) -> None:
    r = SnapshotReader({"a": value}, "doc")
    if message is None:
        check(r)  # an integer array is numeric
    else:
        with pytest.raises(SnapshotError, match=message):
            check(r)


def test_a_document_that_is_not_a_map_is_refused() -> None:
    with pytest.raises(SnapshotError, match="doc: expected a map, got list"):
        SnapshotReader([1, 2], "doc")


def test_rows_of_nan_mark_absent_entries_where_allowed() -> None:
    points = np.arange(12.0).reshape(4, 3)
    points[1] = np.nan
    r = SnapshotReader({"p": points}, "doc")
    got = r.array("p", (4, 3), allow_nan_rows=True)
    assert np.isnan(got[1]).all() and np.array_equal(got[[0, 2, 3]], points[[0, 2, 3]])
    with pytest.raises(SnapshotError, match=r"doc\.p: contains NaN or infinity"):
        r.array("p", (4, 3))
    points[2, 0] = np.nan
    with pytest.raises(SnapshotError, match=r"doc\.p: rows \[2\] are partly NaN"):
        SnapshotReader({"p": points}, "doc").array("p", (4, 3), allow_nan_rows=True)
    points[2, 0] = np.inf
    with pytest.raises(SnapshotError, match=r"doc\.p: contains NaN or infinity"):
        SnapshotReader({"p": points}, "doc").array("p", (4, 3), allow_nan_rows=True)


def test_a_map_of_another_layout_is_refused_whole() -> None:
    r = SnapshotReader({"a": 1, "b": 2}, "doc")
    assert r.exactly("a", "b") is r
    with pytest.raises(SnapshotError, match=r"doc: expected the keys \['a'\] \(missing \[\], "
                                            r"unknown \['b'\]\)"):
        r.exactly("a")
    with pytest.raises(SnapshotError, match=r"missing \['c'\], unknown \[\]"):
        r.exactly("a", "b", "c")
