"""The shared helper that keeps old keyword and attribute names working for one release."""

import warnings
from dataclasses import dataclass

import pytest

from labkit._deprecation import renamed_attribute, renamed_keywords
from labkit.errors import LabkitError


@renamed_keywords(normal_k="k", normals=("source_normals", "target_normals"))
def _f(a, *, k=12, source_normals=None, target_normals=None):
    return a, k, source_normals, target_normals


def test_new_names_pass_without_a_warning():
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert _f(1, k=5, target_normals="t") == (1, 5, None, "t")


def test_old_name_warns_naming_the_new_one_and_is_passed_on():
    with pytest.warns(DeprecationWarning, match=r"'normal_k' is deprecated .* use 'k'") as record:
        assert _f(1, normal_k=7) == (1, 7, None, None)
    assert len(record) == 1
    assert record[0].filename == __file__  # the warning points at the caller's line


def test_old_pair_is_split_into_the_new_keywords():
    with pytest.warns(DeprecationWarning, match="source_normals and target_normals"):
        assert _f(0, normals=("s", "t")) == (0, 12, "s", "t")
    with pytest.warns(DeprecationWarning):
        assert _f(0, normals=None) == (0, 12, None, None)
    with pytest.warns(DeprecationWarning), pytest.raises(LabkitError, match="pair"):
        _f(0, normals=("s", "t", "u"))


def test_old_and_new_name_together_are_refused():
    with pytest.raises(LabkitError, match="give 'k' only"):
        _f(1, k=3, normal_k=4)


def test_renamed_attribute_warns_and_reads_the_new_field():
    @dataclass(frozen=True)
    class Record:
        metric: str
        criterion = renamed_attribute("metric", "criterion")

    r = Record("point_to_plane")
    with pytest.warns(DeprecationWarning, match=r"Record.criterion is deprecated.*use .metric"):
        assert r.criterion == "point_to_plane"
