"""Progress of long work: one small mechanism for reading, normals, ICP, distances, tiles, writing.

The library is silent unless asked. Every long-running public function takes a
``progress`` argument and hands it to :func:`progress_steps`:

``False`` or ``None`` (the library default)
    Nothing is shown; the reporter is a no-op (one attribute test per step).
``True``
    A tqdm bar on stderr when stderr is a terminal, a notebook widget in Jupyter
    (``tqdm.auto``); plain lines on stderr otherwise (logs, pipes, CI, or when
    tqdm is not installed), at most one every ``interval`` seconds plus the last.
``"bar"`` / ``"lines"``
    Force the tqdm bar or the plain lines.
a callable
    Called with a :class:`ProgressEvent` after every step (for GUIs, logging,
    tests); nothing is printed.

How a step reports (the stable API the other modules call)::

    from labkit.core.progress import progress_steps

    with progress_steps(progress, total=len(cloud), desc="reading a.laz", unit="pts") as step:
        for chunk in chunks:
            ...
            step(len(chunk))                       # advance by a number of points

    with progress_steps(progress, total=max_iter, desc="ICP", unit="it") as step:
        for k in range(max_iter):
            ...
            step(1, info=f"shift {t[0]:+.4f} {t[1]:+.4f} {t[2]:+.4f} m, {n_pairs:,} pairs")

``total=None`` when the number of steps is not known in advance (a bar then
counts without a percentage). The ICP loop may stop early: leaving the ``with``
block closes the bar wherever it stands. The command line maps ``--quiet`` to
``progress=False`` (see :func:`from_cli`); a caller that holds a ``quiet`` flag
writes ``progress=not quiet``.
"""

from __future__ import annotations

import contextlib
import sys
import time
from dataclasses import dataclass

from .errors import LabkitError

__all__ = ["progress_steps", "ProgressEvent", "Reporter", "from_cli", "IterationSteps"]

MODES = ("bar", "lines")
INTERVAL = 1.0  # seconds between two plain lines


@dataclass(frozen=True)
class ProgressEvent:
    """One step of a long task, as handed to a progress callback.

    ``desc`` names the task, ``done`` counts what is finished (points,
    iterations, tiles; ``unit`` says which), ``total`` is the expected count or
    None, ``n`` the size of this step, ``info`` an optional text (e.g. the
    current shift and number of pairs), ``finished`` is True on the last event
    (sent when the task ends, with ``n == 0``).

    Examples
    --------
    >>> from labkit.core.progress import ProgressEvent
    >>> event = ProgressEvent("reading a.laz", done=250, total=1000, n=250, unit="pts")
    >>> event.fraction, event.finished
    (0.25, False)
    """

    desc: str
    done: int
    total: int | None
    n: int
    unit: str = "it"
    info: str = ""
    finished: bool = False

    @property
    def fraction(self) -> float | None:
        """``done / total`` in [0, 1], or None without a total."""
        if not self.total:
            return None
        return min(self.done / self.total, 1.0)


class Reporter:
    """Counts the steps of one task and passes them to a sink (bar, lines, callback or nothing).

    Made by :func:`progress_steps`; call it as ``step(n, info="...")``.

    Examples
    --------
    A Reporter is what :func:`progress_steps` yields: call it with the size of each step.

    >>> from labkit.core.progress import progress_steps
    >>> events = []
    >>> with progress_steps(events.append, total=10, desc="chunks") as step:
    ...     step(4)
    ...     step(6, info="last")
    >>> type(step).__name__, [(e.done, e.info, e.finished) for e in events]
    ('Reporter', [(4, '', False), (10, 'last', False), (10, 'last', True)])
    """

    def __init__(self, sink, desc: str, total: int | None, unit: str):
        self.desc, self.total, self.unit, self.done, self.info = desc, total, unit, 0, ""
        self._sink = sink
        self.enabled = sink is not None

    def __call__(self, n: int = 1, info: str = "") -> None:
        if self._sink is None:
            return
        n = int(n)
        self.done += n
        self.info = str(info) if info else self.info
        self._sink.step(self, n, str(info) if info else "")

    def close(self) -> None:
        if self._sink is not None:
            self._sink.close(self)
            self._sink = None


@contextlib.contextmanager
def progress_steps(progress, total: int | None = None, desc: str = "", unit: str = "it", *,
                   interval: float = INTERVAL):
    """Report the steps of a long task; a context manager that yields a :class:`Reporter`.

    Parameters
    ----------
    progress : bool, None, "bar", "lines" or callable
        What to do with the steps (see the module notes); ``False``/``None`` is silent.
    total : int, optional
        Number of units expected (points, iterations, tiles); None when unknown.
    desc : str
        Name of the task (``"reading a.laz"``, ``"normals"``, ``"ICP"``).
    unit : str
        Unit of the counts (``"pts"``, ``"it"``, ``"tiles"``).
    interval : float
        Least number of seconds between two plain lines.

    Yields
    ------
    Reporter
        ``step(n=1, info="")`` advances by ``n`` units with an optional text.

    Raises
    ------
    LabkitError
        ``progress`` is none of the accepted values.

    Examples
    --------
    >>> from labkit.core.progress import progress_steps
    >>> events = []
    >>> with progress_steps(events.append, total=3, desc="tiles", unit="tiles") as step:
    ...     for _ in range(3):
    ...         step(1)
    >>> [e.done for e in events], events[-1].finished
    ([1, 2, 3, 3], True)
    >>> with progress_steps(False, total=3) as step:  # silent: the steps cost nothing
    ...     step(3)
    """
    total = None if total is None else max(int(total), 0)
    reporter = Reporter(_sink(progress, interval), desc, total, unit)
    try:
        yield reporter
    finally:
        reporter.close()


class IterationSteps:
    """Progress of an iterative solver that keeps a history of records (ICP).

    ``update(history)`` reports every record not yet reported, one step each, with the
    current shift (``record.translation``) and number of pairs (``record.n_used``) as
    ``info``; ``close(history)`` reports the rest and ends the task. Meant for a loop head,
    so that the loop body stays untouched::

        steps = IterationSteps(progress, max_iterations, "ICP")
        for it in range(...):
            steps.update(history)
            ...
        steps.close(history)

    Examples
    --------
    >>> from types import SimpleNamespace
    >>> from labkit.core.progress import IterationSteps
    >>> events = []
    >>> steps = IterationSteps(events.append, total=5, desc="ICP")
    >>> history = [SimpleNamespace(translation=[0.01 * k, 0, 0], n_used=900) for k in range(3)]
    >>> steps.update(history[:2])
    >>> steps.close(history)
    >>> [e.done for e in events], events[-1].finished
    ([1, 2, 3, 3], True)
    """

    def __init__(self, progress, total: int | None, desc: str = "ICP", *, interval: float = INTERVAL):
        self._rep = Reporter(_sink(progress, interval), desc, None if total is None else max(int(total), 0), "it")
        self._seen = 0

    def update(self, history) -> None:
        if self._rep.enabled:  # silent: not even the text is made
            for rec in history[self._seen:]:
                self._rep(1, info=iteration_text(rec))
        self._seen = len(history)

    def close(self, history=()) -> None:
        self.update(history)
        self._rep.close()


def iteration_text(record) -> str:
    """``shift (+0.2300, -0.1700, +0.1100) m, 12,345 pairs`` for one iteration record."""
    t = tuple(float(v) for v in record.translation)
    return f"shift ({t[0]:+.4f}, {t[1]:+.4f}, {t[2]:+.4f}) m, {int(record.n_used):,} pairs"


def from_cli(quiet: bool, force: bool = False, stream=None) -> bool:
    """``progress`` for the command line.

    ``--quiet`` silences it; ``--progress`` forces it (plain lines in logs and pipes);
    otherwise it is shown when stderr is a terminal, so that a script or a log that
    only reads errors sees exactly one line when a command fails.

    Examples
    --------
    >>> import io
    >>> from labkit.core.progress import from_cli
    >>> from_cli(quiet=True, force=True), from_cli(quiet=False, force=True), from_cli(False, stream=io.StringIO())
    (False, True, False)
    """
    if quiet:
        return False
    if force:
        return True
    stream = sys.stderr if stream is None else stream
    return bool(getattr(stream, "isatty", lambda: False)())


# ---------------------------------------------------------------------------- sinks
def _sink(progress, interval: float):
    if progress is None or progress is False:
        return None
    if progress is True:
        return _TqdmSink() if _tqdm_wanted() else _LineSink(interval)
    if isinstance(progress, str) and progress in MODES:
        if progress == "bar":
            if _tqdm() is None:
                raise LabkitError("progress='bar' needs tqdm (pip install tqdm); use progress=True or 'lines'")
            return _TqdmSink()
        return _LineSink(interval)
    if callable(progress) and not isinstance(progress, (bool, str)):
        return _CallbackSink(progress)
    raise LabkitError(f"progress must be True, False, 'bar', 'lines' or a callable, got {progress!r}")


def _tqdm():
    try:
        from tqdm.auto import tqdm
    except ImportError:
        return None
    return tqdm


def _in_notebook() -> bool:
    shell = sys.modules.get("IPython")
    if shell is None:
        return False
    try:
        ip = shell.get_ipython()
    except AttributeError:
        return False
    return ip is not None and type(ip).__name__ == "ZMQInteractiveShell"


def _tqdm_wanted() -> bool:
    """A bar where someone watches it (a terminal or a notebook) and tqdm is there."""
    if _tqdm() is None:
        return False
    isatty = getattr(sys.stderr, "isatty", None)
    return _in_notebook() or bool(isatty and isatty())


class _TqdmSink:
    def __init__(self):
        self._bars = {}

    def step(self, rep: Reporter, n: int, info: str) -> None:
        bar = self._bars.get(id(rep))
        if bar is None:
            bar = self._bars[id(rep)] = _tqdm()(total=rep.total, desc=rep.desc, unit=rep.unit,
                                                unit_scale=rep.unit != "it", file=sys.stderr, leave=True)
        if info:
            bar.set_postfix_str(info, refresh=False)
        bar.update(n)

    def close(self, rep: Reporter) -> None:
        bar = self._bars.pop(id(rep), None)
        if bar is not None:
            bar.close()


class _LineSink:
    """Plain lines on stderr: ``desc [####......]  40.0% (400 of 1,000 pts) info``."""

    def __init__(self, interval: float):
        self.interval, self._last, self._shown = float(interval), -float("inf"), -1

    def step(self, rep: Reporter, n: int, info: str) -> None:
        now = time.monotonic()
        if now - self._last >= self.interval or (rep.total and rep.done >= rep.total):
            self._write(rep)
            self._last = now

    def close(self, rep: Reporter) -> None:
        if self._shown != rep.done:
            self._write(rep)

    def _write(self, rep: Reporter) -> None:
        self._shown = rep.done
        sys.stderr.write(format_line(rep.desc, rep.done, rep.total, rep.unit, rep.info) + "\n")
        sys.stderr.flush()


class _CallbackSink:
    def __init__(self, callback):
        self.callback = callback

    def step(self, rep: Reporter, n: int, info: str) -> None:
        self.callback(ProgressEvent(rep.desc, rep.done, rep.total, n, rep.unit, info))

    def close(self, rep: Reporter) -> None:
        self.callback(ProgressEvent(rep.desc, rep.done, rep.total, 0, rep.unit, rep.info, finished=True))


def format_line(desc: str, done: int, total: int | None, unit: str, info: str = "", width: int = 30) -> str:
    """One plain progress line (used when no bar is drawn)."""
    if total:
        frac = min(done / total, 1.0)
        fill = int(width * frac)
        text = f"{desc} [{'#' * fill}{'.' * (width - fill)}] {100 * frac:5.1f}% ({done:,} of {total:,} {unit})"
    else:
        text = f"{desc}: {done:,} {unit}"
    return f"{text} {info}" if info else text
