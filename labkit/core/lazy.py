"""Lazy public names of a package (PEP 562): imported on first use, then cached in the package."""

from __future__ import annotations

import importlib


def lazy_attribute(package: str, exports: dict, namespace: dict, name: str):
    """The object ``name`` from the module ``exports[name]``, kept in ``namespace`` for the next access.

    ``package`` names the package in the AttributeError raised for a name it does not export.

    Examples
    --------
    >>> from labkit.core.lazy import lazy_attribute
    >>> space = {}
    >>> lazy_attribute("pkg", {"sqrt": "math"}, space, "sqrt")(9.0), sorted(space)
    (3.0, ['sqrt'])
    >>> lazy_attribute("pkg", {}, space, "cube")
    Traceback (most recent call last):
    AttributeError: module 'pkg' has no attribute 'cube'
    """
    module = exports.get(name)
    if module is None:
        raise AttributeError(f"module {package!r} has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    namespace[name] = value
    return value
