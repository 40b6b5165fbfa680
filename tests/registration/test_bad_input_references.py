"""Reference files (labkit.registration.references, and the pair files of labkit.registration.compare that share their reader): wrong
containers, entries and paths give one LabkitError, never an AttributeError or TypeError."""

import json

import pytest

from labkit.registration.compare import load_pairs
from labkit.core.errors import LabkitError
from labkit.registration.references import load_references, manual_reference, save_references

REF = manual_reference([0.1, 0.0, 0.0], 0.001, region="roof", case="als-als")


@pytest.mark.parametrize("references, fragment", [
    ([1, 2], "Reference objects"), ([REF, "x"], "Reference objects"), ({"a": 3}, "Reference objects"),
    (5, "Reference objects"), (None, "Reference objects"), ([[0.1, 0, 0]], "Reference objects"),
])
def test_save_references_refuses_what_is_no_reference(tmp_path, references, fragment):
    with pytest.raises(LabkitError, match=fragment):
        save_references(references, tmp_path / "r.json")
    assert not (tmp_path / "r.json").exists()


@pytest.mark.parametrize("path", [None, 3, ""])
def test_save_references_needs_a_path(path):
    with pytest.raises(LabkitError, match="path"):
        save_references([REF], path)


def test_save_references_onto_a_folder(tmp_path):
    with pytest.raises(LabkitError, match="folder"):
        save_references([REF], tmp_path)


@pytest.mark.parametrize("doc, fragment", [
    ([[0.1, 0, 0]], "entry 0 is invalid"), ([1, 2], "entry 0 is invalid"), (["roof"], "entry 0 is invalid"),
    ({"references": 5}, "expected a list"), ({"references": {"a": 1}}, "expected a list"), (7, "expected a list"),
    ({"format": "x"}, "not a labkit reference file"), ([{"region": "a", "translation": "abc"}], "entry 0"),
    ([{"region": "a", "translation": [1, 2]}], "entry 0"), ([{"region": "a"}], "entry 0"),
])
def test_load_references_refuses_malformed_files(tmp_path, doc, fragment):
    path = tmp_path / "r.json"
    path.write_text(json.dumps(doc))
    with pytest.raises(LabkitError, match=fragment):
        load_references(path)


@pytest.mark.parametrize("path", [None, 3, ["r.json"]])
def test_load_references_needs_a_path(path):
    with pytest.raises(LabkitError, match="path"):
        load_references(path)


def test_saved_references_read_back(tmp_path):
    path = save_references([REF], tmp_path / "r.json")
    back = load_references(path)[("roof", "als-als")]
    assert back.translation.tolist() == REF.translation.tolist()


@pytest.mark.parametrize("doc", [[1, 2], [[1]], {"pairs": 3}, [None], [{"region": "a", "source": 1, "target": "b"}],
                                 [{"region": "a", "source": "a.las", "target": "b.las", "constrained": 5}]])
def test_load_pairs_refuses_malformed_files(tmp_path, doc):
    path = tmp_path / "p.json"
    path.write_text(json.dumps(doc))
    with pytest.raises(LabkitError):
        load_pairs(path)
