"""labkit.notebook: setup_notebook takes a whole seed and refuses anything else."""

import numpy as np
import pytest

from labkit.core.errors import LabkitError
from labkit.notebook import setup_notebook


@pytest.mark.parametrize("seed", [-1, 1.5, "7", True, [1], np.nan])
def test_setup_notebook_refuses_bad_seeds(seed):
    with pytest.raises(LabkitError, match="seed"):
        setup_notebook(seed)


@pytest.mark.parametrize("seed", [0, 7, np.int64(3), 2**40])
def test_setup_notebook_takes_whole_seeds(seed):
    assert setup_notebook(seed).integers(1000) == np.random.default_rng(int(seed)).integers(1000)
