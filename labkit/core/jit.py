"""The package's one switch for compiled kernels: ``numba.njit`` with the disk cache, or the plain function.

Every compiled loop of labkit goes through :func:`compiled`: it adds ``cache=True``
(the machine code is written once and loaded by every later process, see
:mod:`labkit.core.numba_cache`) and ``nogil=True`` (threads can run the kernels side
by side) to the options the kernel asks for. numba itself is imported on the first
call of :func:`compiled`, not when this module is imported: a module that asks for
its kernels on their first use (``compiled(kernel)`` inside a function) keeps numba
out of ``import labkit.ransac``; a module that decorates its kernels with
``@compiled`` loads numba when it is imported. Without numba, :func:`compiled`
returns the function itself and :func:`have_numba` tells callers with a numpy route
to take it.
"""

from __future__ import annotations

import hashlib
import importlib.util
import types

__all__ = ["SIMD", "compiled", "have_numba"]

#: Options of the loops that sum over points: numpy's float semantics (a division by zero gives inf or NaN
#: instead of a branch that raises) and sums that may be reordered, so that the loops run in SIMD registers.
#: Only for coordinates reduced to a local origin: reordered differences of UTM-sized numbers lose digits.
SIMD = {"error_model": "numpy", "fastmath": {"reassoc", "nsz", "contract"}}

_KERNELS = {}  # (function, signature, options) -> its compiled version
_HAVE = []  # [bool] once asked


def have_numba() -> bool:
    """True when numba can be imported (found without importing it).

    Examples
    --------
    >>> import sys
    >>> from labkit.core.jit import have_numba
    >>> have_numba() == (__import__("importlib.util").util.find_spec("numba") is not None)
    True
    """
    if not _HAVE:
        _HAVE.append(importlib.util.find_spec("numba") is not None)
    return _HAVE[0]


def compiled(f=None, /, *, signature=None, **options):
    """``numba.njit(signature, cache=True, nogil=True, **options)(f)`` where numba is installed, else ``f``.

    Parameters
    ----------
    f : function, optional
        The kernel. Without it, a decorator with these options is returned (``@compiled(fastmath=True)``).
    signature : str, optional
        Compile at once for these types (eagerly, or loaded from the cache); default: on the first call,
        for the types of its arguments.
    **options
        Further options of ``numba.njit`` (``error_model``, ``fastmath``, ``parallel``, ...), e.g.
        :data:`SIMD`.

    Returns
    -------
    The compiled kernel; the same object for the same function and options (compiled once per process).

    Examples
    --------
    >>> from labkit.core.jit import SIMD, compiled, have_numba
    >>> from labkit.neighbours.moments import knn_moments  # defined under @compiled
    >>> type(knn_moments).__name__ == ("CPUDispatcher" if have_numba() else "function")
    True
    >>> from labkit.sphere.sweeps import _correlates
    >>> compiled(_correlates, **SIMD) is compiled(_correlates, **SIMD)  # compiled once per process
    True
    """
    if f is None:
        return lambda g: compiled(g, signature=signature, **options)
    flags = _canonical(options)
    key = (f, signature, flags)
    kernel = _KERNELS.get(key)
    if kernel is None:
        if have_numba():
            import numba  # (first use: numba's own start-up is paid here, not on import of the caller)

            args = () if signature is None else (signature,)
            kernel = numba.njit(*args, cache=True, nogil=True, **options)(_cache_name(f, flags) if options else f)
        else:  # pragma: no cover - depends on the environment
            kernel = f
        _KERNELS[key] = kernel
    return kernel


def _canonical(options):
    """The options as a string that is the same in every process (sets sorted: their order follows the hash seed)."""
    return repr(sorted((k, sorted(v) if isinstance(v, (set, frozenset)) else v) for k, v in options.items()))


def _cache_name(f, flags):
    """f under a name of its own for these options: numba's disk cache keys a kernel by its name and argument
    types only, so the same function compiled with other options (e.g. fastmath) would load the wrong code."""
    g = types.FunctionType(f.__code__, f.__globals__, f.__name__, f.__defaults__, f.__closure__)
    g.__qualname__ = f"{f.__qualname__}__{hashlib.sha1(flags.encode()).hexdigest()[:8]}"
    g.__module__, g.__doc__ = f.__module__, f.__doc__
    return g
