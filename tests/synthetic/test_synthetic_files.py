"""The row of tile files: names, contents read back by labkit.io, bad input."""

import numpy as np
import pytest

from labkit.core.errors import LabkitError
from labkit.io import read_cloud
from labkit.synthetic import tile_row


@pytest.mark.parametrize("suffix", [".laz", ".las", ".csv"])
def test_each_tile_holds_ten_points_on_the_x_axis_of_its_cell(suffix, tmp_path):
    folder = tile_row(3, size=4.0, suffix=suffix, folder=tmp_path)
    assert folder == tmp_path
    assert sorted(p.name for p in folder.iterdir()) == [f"t{i}{suffix}" for i in range(3)]
    for i in range(3):
        xyz = read_cloud(folder / f"t{i}{suffix}").xyz
        assert np.allclose(xyz, np.column_stack([4.0 * i + 0.4 * np.arange(10), np.zeros(10), np.zeros(10)]))


def test_a_fresh_folder_each_call_and_bad_input_refused():
    assert tile_row(1) != tile_row(1)
    for kwargs in ({"n": 0}, {"size": -1.0}, {"suffix": ".ply"}):
        with pytest.raises(LabkitError):
            tile_row(**kwargs)
