"""Text clouds (labkit.io.ascii) that are valid although unusual are read; what stays invalid is refused."""

import pytest

from labkit.core.errors import CloudFileError
from labkit.io import read_cloud

XYZ = [[1.0, 2.0, 3.0], [4.0, 5.5, 6.0]]


@pytest.mark.parametrize("name, text", [
    ("bom.xyz", "\ufeff1 2 3\n4 5.5 6\n"),
    ("bom_header.csv", "\ufeffx,y,z\n1,2,3\n4,5.5,6\n"),
    ("bom_semicolon.txt", "\ufeff1;2;3\n4;5.5;6\n"),
    ("comment.xyz", "# exported by a scanner\n# units: m\n1 2 3\n4 5.5 6\n"),
    ("comment_inside.xyz", "1 2 3\n# second strip\n4 5.5 6\n"),
    ("comment_after_header.csv", "x,y,z\n# a note\n1,2,3\n4,5.5,6\n"),
    ("comment_at_end.xyz", "1 2 3 # first\n4 5.5 6\n"),
    ("trailing_comma.csv", "1,2,3,\n4,5.5,6,\n"),
    ("trailing_comma_header.csv", "x,y,z,\n1,2,3,\n4,5.5,6,\n"),
    ("trailing_semicolon.txt", "1;2;3;\n4;5.5;6;\n"),
    ("trailing_space.xyz", "1 2 3  \n4 5.5 6\t\n"),
    ("crlf.xyz", "1 2 3\r\n4 5.5 6\r\n"),
    ("bom_comment_trailing.csv", "\ufeff# note\n1,2,3,\n4,5.5,6,\n"),
    ("blank_lines.xyz", "\n\n1 2 3\n\n4 5.5 6\n\n"),
])
def test_unusual_but_valid_text_is_read(tmp_path, name, text):
    path = tmp_path / name
    path.write_bytes(text.encode("utf-8"))
    cloud = read_cloud(path)
    assert cloud.xyz.tolist() == XYZ
    assert cloud.attributes == {}


@pytest.mark.parametrize("text", ["# x y z intensity\n1 2 3 7\n4 5.5 6 8\n", "#x,y,z,intensity\n1,2,3,7\n4,5.5,6,8\n",
                                  "\ufeff//X Y Z Intensity\n1 2 3 7\n4 5.5 6 8\n"])
def test_a_header_behind_a_comment_sign_names_the_columns(tmp_path, text):
    path = tmp_path / "h.txt"
    path.write_bytes(text.encode("utf-8"))
    cloud = read_cloud(path)
    assert cloud.xyz.tolist() == XYZ and cloud["intensity"].tolist() == [7, 8]


@pytest.mark.parametrize("text, fragment", [
    ("1,,2,3\n", "names no column"), ("1,2,3\n4,5\n", "cannot parse|columns"), ("1 2\n", "3 columns"), ("# only a comment\n", "empty"),
])
def test_what_stays_invalid(tmp_path, text, fragment):
    path = tmp_path / "bad.csv"
    path.write_text(text)
    with pytest.raises(CloudFileError, match=fragment):
        read_cloud(path)
