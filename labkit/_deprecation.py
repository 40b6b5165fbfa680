"""Old keyword and attribute names kept working for one release, with a warning naming the new one.

>>> import warnings
>>> @renamed_keywords(normal_k="k")
... def f(*, k=12):
...     return k
>>> with warnings.catch_warnings(record=True) as caught:
...     warnings.simplefilter("always")
...     f(normal_k=5)
5
>>> str(caught[0].message)
"f(): the keyword 'normal_k' is deprecated and will be removed in the next release; use 'k'"
"""

from __future__ import annotations

import functools
import warnings

from .errors import LabkitError


def renamed_keywords(**renames):
    """Decorator: accept the old name of a keyword argument, warn, and pass it on under the new name.

    Parameters
    ----------
    **renames : str or tuple of str
        ``old="new"``; or ``old=("new_a", "new_b")`` for an old keyword whose value was a pair
        that is now given as two keywords (e.g. ``normals=(s, t)`` became ``source_normals=s,
        target_normals=t``).

    Giving the old and the new name together raises :class:`LabkitError`.
    """

    def decorate(func):
        @functools.wraps(func)
        def wrapper(*args, **kwargs):
            for old, new in renames.items():
                if old not in kwargs:
                    continue
                value = kwargs.pop(old)
                names = (new,) if isinstance(new, str) else tuple(new)
                clash = [n for n in names if n in kwargs]
                if clash:
                    raise LabkitError(f"{func.__name__}(): give {clash[0]!r} only ({old!r} is its old name)")
                shown = names[0] if len(names) == 1 else " and ".join(names)
                warnings.warn(
                    f"{func.__name__}(): the keyword {old!r} is deprecated and will be removed in the next "
                    f"release; use {shown!r}",
                    DeprecationWarning,
                    stacklevel=2,
                )
                if len(names) == 1:
                    kwargs[names[0]] = value
                else:
                    parts = (None,) * len(names) if value is None else tuple(value)
                    if len(parts) != len(names):
                        raise LabkitError(f"{old} must be a pair ({', '.join(names)}), got {value!r}")
                    kwargs.update(zip(names, parts))
            return func(*args, **kwargs)

        return wrapper

    return decorate


def renamed_attribute(new: str, old: str):
    """A read-only property under the old name ``old`` that warns and returns the attribute ``new``."""

    def getter(self):
        warnings.warn(
            f"{type(self).__name__}.{old} is deprecated and will be removed in the next release; use .{new}",
            DeprecationWarning,
            stacklevel=2,
        )
        return getattr(self, new)

    getter.__doc__ = f"Deprecated name of :attr:`{new}` (removed in the next release)."
    return property(getter)
