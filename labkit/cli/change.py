"""Helpers of ``labkit change`` and ``labkit register``: parameters from the data, the registration file's
orientation, priors for undetermined parameters, and the name of the coordinate frame."""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np

from ..core.lengths import length_text
from ..change.defaults import m3c2_parameters


def change_parameters(ref, moved, args):
    """Normal radius, cylinder radius and max depth: as given, else chosen from the data (printed with the rule)."""
    if args.normal_radius and args.cylinder_radius and args.max_depth:
        return args.normal_radius, args.cylinder_radius, args.max_depth
    chosen = m3c2_parameters(ref, moved, expected_change=args.expected_change, rng=args.seed)
    print("\nM3C2 parameters (lengths in m of the metric coordinates; --normal-radius, --cylinder-radius, "
          "--max-depth override):")
    given = {"cylinder": args.cylinder_radius, "normal": args.normal_radius, "max depth": args.max_depth}
    for line in chosen.lines():
        key = next((k for k in given if line.startswith(k)), None)
        print(f"  {line if key is None or given[key] is None else key + ': given on the command line'}")
    return (args.normal_radius or chosen.normal_radius, args.cylinder_radius or chosen.cylinder_radius,
            args.max_depth or chosen.max_depth)


def registration_for(registration, args, crs=None):
    """The registration file oriented compared -> reference (a file of ``labkit register REF CMP`` is inverted)."""
    names = ", ".join(registration.parameter_names)
    if crs is not None and getattr(registration, "crs", None) and not same_crs(registration.crs, crs):
        warnings.warn(f"the registration file {args.registration} was made in another CRS "
                      f"({registration.crs[:60]}...) than {args.reference}", stacklevel=2)
    if _maps_reference_onto_compared(dict(getattr(registration, "inputs", ())), args.reference, args.compared):
        print(f"registration {args.registration}: {names} with covariance; it maps {args.reference} onto "
              f"{args.compared}, used inverted (compared -> reference)")
        return registration.inverse()
    print(f"registration {args.registration}: {names} with covariance (compared -> reference)")
    return registration


def _maps_reference_onto_compared(roles, reference, compared) -> bool:
    """The file's source is the reference and its target the compared epoch: by path, else by file name."""
    src, tgt = roles.get("source"), roles.get("target")
    if src is None or tgt is None:
        return False
    path = lambda a, b: Path(a).resolve() == Path(b).resolve()  # noqa: E731
    if path(src, reference) and path(tgt, compared):
        return True
    if path(src, compared) and path(tgt, reference):
        return False
    name = lambda a, b: Path(a).name == Path(b).name  # noqa: E731  (the files were moved together)
    return name(src, reference) and name(tgt, compared) and not (name(src, compared) and name(tgt, reference))


def same_crs(a: str, b: str) -> bool:
    """Two CRS texts name the same CRS (GDAL/PROJ through rasterio), or are equal text where they cannot be parsed."""
    import rasterio
    from rasterio.crs import CRS
    from rasterio.errors import CRSError

    try:
        with rasterio.Env():  # GDAL's message on a CRS it cannot read goes to rasterio's logger, not stderr
            return CRS.from_user_input(a) == CRS.from_user_input(b)
    except CRSError:
        return a == b


def held_priors(registration, args) -> dict:
    """Prior standard deviations for the parameters the registration left undetermined (printed)."""
    if registration is None:
        return {}
    diag = dict(zip(registration.parameter_names, np.diag(registration.covariance)))
    held = {n: np.radians(args.held_rotation_std) for n, v in diag.items() if n.startswith("r") and np.isinf(v)}
    if held:  # rotations the registration held at their initial value: the stated prior
        print(f"undetermined {', '.join(held)}: prior std {args.held_rotation_std:g} deg in the LoD")
    shifts = [n for n, v in diag.items() if n.startswith("t") and np.isinf(v)]
    if shifts and args.held_shift_std is not None:
        held.update({n: args.held_shift_std for n in shifts})
        print(f"undetermined {', '.join(shifts)}: prior std {length_text(args.held_shift_std)} in the LoD")
    elif shifts:
        print(f"undetermined {', '.join(shifts)}: the LoD is infinite where they move the surface along the "
              "normal; --held-shift-std M states a prior (e.g. the survey's horizontal accuracy)")
    return held


def frame_text(cloud) -> str:
    """What the coordinates are: the CRS's name (metres as read), or a local frame."""
    if not cloud.crs:
        return "a local frame (no CRS in the file), m"
    name = cloud.crs.split('"')[1] if cloud.crs.count('"') >= 2 else cloud.crs
    f = cloud.units.factors
    converted = cloud.units.converted and f is not None and not np.allclose(f, 1.0)
    return f"{name}, coordinates in m" + (f" (converted from {cloud.units.label(native=True)})" if converted else "")
