"""Command-line options (labkit.cli): an option that does not apply to the chosen method or mode is refused (exit 2,
one line naming the option), never accepted and ignored."""

import argparse

import pytest

from labkit.cli.main import _method_options, main

CHANGE = ["change", "a.las", "b.las", "--normal-radius", "1", "--cylinder-radius", "1", "--max-depth", "1"]


@pytest.mark.parametrize("argv, option", [
    (["register", "a.las", "b.las", "--method", "icp", "--extent", "5"], "--extent"),
    (["register", "a.las", "b.las", "--method", "icp", "--max-points", "10"], "--max-points"),
    (["register", "a.las", "b.las", "--method", "icp-huber", "--extent", "1"], "--extent"),
    (["register", "a.las", "b.las", "--method", "icp-tukey", "--max-points", "100"], "--max-points"),
    (["register", "a.las", "b.las", "--method", "icp-point", "--extent", "2"], "--extent"),
    (["register", "a.las", "b.las", "--method", "icp-classes", "--max-points", "20"], "--max-points"),
    (["register", "a.las", "b.las", "--method", "consensus", "--reach", "5"], "--reach"),
    (["register", "a.las", "b.las", "--method", "consensus+icp", "--reach", "5"], "--reach"),
    (["register", "a.las", "b.las", "--extent", "5"], "--extent"),  # the default method is icp
    (["compare", "pairs.json", "--methods", "icp", "icp-huber", "--extent", "2"], "--extent"),
    (["compare", "pairs.json", "--methods", "icp-tukey", "--max-points", "50"], "--max-points"),
    (["tiles", "a.las", "--target", "b.las", "--method", "icp", "--max-points", "3"], "--max-points"),
    (["tiles", "a.las", "--target", "b.las", "--method", "icp-huber", "--extent", "3"], "--extent"),
    (CHANGE + ["--dof", "rigid"], "--dof"),
    (CHANGE + ["--dof", "translation"], "--dof"),
    (CHANGE + ["--extent", "5"], "--extent"),
    (CHANGE + ["--max-points", "10"], "--max-points"),
    (CHANGE + ["--seed", "3"], "--seed"),
    (CHANGE + ["--held-rotation-std", "0.1"], "--held-rotation-std"),
    (CHANGE + ["--register", "icp", "--extent", "5"], "--extent"),
    (CHANGE + ["--register", "icp-huber", "--max-points", "5"], "--max-points"),
    (["sphere", "a.xyz", "--radius", "0.1", "--station", "0", "0", "0", "--no-station"], "--no-station"),
    (["sphere", "a.xyz", "--radius-range", "0.1", "0.2", "--hold-radius"], "--hold-radius"),
])
def test_an_option_that_does_not_apply_is_refused(capsys, argv, option):
    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and option in err[0] and "error" in err[0]


@pytest.mark.parametrize("methods, given", [
    (["consensus"], {"extent": 2.0}), (["consensus"], {"max_points": 10}), (["consensus+icp"], {"extent": 2.0}),
    (["consensus+icp"], {"max_points": 10}), (["icp"], {"reach": 3.0}), (["icp-huber"], {"reach": 3.0}),
    (["icp", "consensus"], {"extent": 0.5, "reach": 1.0}), (["icp"], {"dof": "rigid"}), (["icp"], {"seed": 4}),
    (["consensus"], {"seed": 4}),
])
def test_an_option_that_applies_is_taken_and_the_rest_default(methods, given):
    args = argparse.Namespace(dof=None, extent=None, max_points=None, seed=None, reach=None, **{})
    for k, v in given.items():
        setattr(args, k, v)
    _method_options(args, methods)
    expected = {"dof": "translation", "extent": 1.0, "max_points": 5000, "seed": 0, **given}
    for k, v in expected.items():
        assert getattr(args, k) == v
