"""Sphinx configuration of labkit's documentation site.

Build it from the repository root (warnings are errors)::

    python -m sphinx -W -b html docs docs/_build/html

The API reference is generated from ``labkit.__all__`` and the ``__all__`` (or public names) of every
public module; the course is every notebook in ``notebooks/`` (``docs/notebooks`` links there), executed
by myst-nb with a per-notebook timeout. Executed notebooks are kept in a jupyter-cache
(``docs/_build/.jupyter_cache``, or ``LABKIT_NOTEBOOK_CACHE``): a rebuild re-runs only notebooks whose
code changed, and ``tests/test_notebooks.py`` fills the same cache when ``LABKIT_NOTEBOOK_CACHE`` is set, so
CI executes each notebook once. The cache does not see changes of labkit itself: after those,
``LABKIT_NB_EXECUTION=force`` (or deleting the cache folder) runs every notebook again.
"""

from __future__ import annotations

import importlib
import inspect
import os
import pkgutil
import sys
from pathlib import Path

DOCS = Path(__file__).resolve().parent
ROOT = DOCS.parent
sys.path.insert(0, str(ROOT))

import labkit  # noqa: E402

# The notebooks' kernels inherit this environment: matplotlib's inline backend (no MPLBACKEND), pyvista
# off screen through EGL, labkit importable from this checkout.
os.environ.pop("MPLBACKEND", None)
os.environ.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")
os.environ.setdefault("PYVISTA_OFF_SCREEN", "true")
os.environ["PYTHONPATH"] = os.pathsep.join(p for p in (str(ROOT), os.environ.get("PYTHONPATH", "")) if p)

project = "labkit"
author = "labkit contributors"
copyright = "labkit contributors, MIT licence"
release = labkit.__version__

extensions = [
    "myst_nb",
    "sphinx.ext.autodoc",
    "sphinx.ext.autosummary",
    "sphinx.ext.mathjax",
    # MathJax served from the site itself (no CDN): the equations render offline, in the course room too
    "sphinx-mathjax-offline",
    "numpydoc",
]

exclude_patterns = ["_build", "Thumbs.db", ".DS_Store", "**/.ipynb_checkpoints"]
html_theme = "pydata_sphinx_theme"
html_title = "labkit"
html_theme_options = {"navigation_with_keys": False, "show_toc_level": 2}

# API reference: numpydoc renders the docstrings; autosummary writes one page per public name
autosummary_generate = True
autosummary_imported_members = True
autodoc_default_options = {"members": False}
numpydoc_show_class_members = False
numpydoc_class_members_toctree = False
numpydoc_xref_param_type = False

# The course: myst-nb executes the notebooks (cached), stops the build on an error or a timeout
nb_execution_mode = os.environ.get("LABKIT_NB_EXECUTION", "cache")
nb_execution_cache_path = os.environ.get("LABKIT_NOTEBOOK_CACHE", str(DOCS / "_build" / ".jupyter_cache"))
nb_execution_timeout = int(os.environ.get("LABKIT_NB_TIMEOUT", "900"))
nb_execution_raise_on_error = True
nb_execution_show_tb = True
nb_merge_streams = True
# Interactive widgets need a running kernel; the static site loads no widget manager from a CDN (it works
# offline: nothing is fetched from the internet), and a widget's cell shows its code and figures only
nb_ipywidgets_js = {}
myst_enable_extensions = ["dollarmath", "amsmath", "html_image"]
myst_heading_anchors = 3
# notebooks number their sections freely (## 3, ### 9b); a class re-exported by a package has two names
# (labkit.PointCloud, labkit.cloud.PointCloud) that both resolve to its one page
suppress_warnings = ["myst.header", "ref.python"]

# ---------------------------------------------------------------------------------------------------
# API pages, generated before Sphinx reads the sources
# ---------------------------------------------------------------------------------------------------

SKIP_TOP = {"cli", "__main__"}  # labkit.<name> and its submodules: the command line, not an API


def public_modules():
    """labkit's public modules and packages (no module or package whose name starts with '_')."""
    names = []
    for info in pkgutil.walk_packages(labkit.__path__, "labkit."):
        if any(part.startswith("_") for part in info.name.split(".")) or info.name.split(".")[1] in SKIP_TOP:
            continue
        names.append(info.name)
    return sorted(names)


def public_names(module):
    """``__all__`` where a module declares it, else the functions and classes it defines."""
    if hasattr(module, "__all__"):
        return [n for n in module.__all__ if not n.startswith("_")]
    return sorted(n for n, obj in vars(module).items()
                  if not n.startswith("_") and (inspect.isfunction(obj) or inspect.isclass(obj))
                  and getattr(obj, "__module__", None) == module.__name__)


def _table(module_name, names):
    lines = [f".. currentmodule:: {module_name}", "", ".. autosummary::", "   :toctree: generated", ""]
    return lines + [f"   {n}" for n in names] + [""]


def _split_documented(module, names, documented):
    """Names of ``module`` whose object gets its page here, and those already documented under another name."""
    new, seen = [], []
    for n in names:
        obj = getattr(module, n, None)
        key = id(obj) if (inspect.isfunction(obj) or inspect.isclass(obj)) else (module.__name__, n)
        if key in documented:
            seen.append((n, documented[key]))
        else:
            documented[key] = f"{module.__name__}.{n}"
            new.append(n)
    return new, seen


def write_api_pages(folder: Path):
    folder.mkdir(exist_ok=True)
    documented = {}  # object -> the full name of its page: each object is described once
    top, _ = _split_documented(labkit, [n for n in labkit.__all__ if not n.startswith("_")], documented)
    classes = [n for n in top if inspect.isclass(getattr(labkit, n))]
    functions = [n for n in top if n not in classes]
    text = ["API reference", "=============", "",
            "Everything in ``labkit.__all__``, then every public module. Each name links to its page with the",
            "parameters, the equations it follows (References) and a runnable example.", "",
            "labkit", "------", "", "Functions", "~~~~~~~~~", ""] + _table("labkit", functions)
    text += ["Classes and exceptions", "~~~~~~~~~~~~~~~~~~~~~~", ""] + _table("labkit", classes)
    text += ["Modules", "-------", "", ".. toctree::", "   :maxdepth: 1", ""]
    for name in public_modules():
        text.append(f"   {name}")
        module = importlib.import_module(name)
        doc = inspect.getdoc(module) or ""
        summary = doc.split("\n\n")[0].strip()
        page = [name, "=" * len(name), "", f".. module:: {name}", ""]
        if summary:
            page += [summary, ""]
        names, seen = _split_documented(module, public_names(module), documented)
        page += _table(name, names) if names else []
        if seen:
            page += ["Also here, documented under another name:", ""]
            page += [f"- ``{n}``: :py:obj:`{full}`" for n, full in seen] + [""]
        if not names and not seen:
            page += ["(No public functions or classes.)", ""]
        new = "\n".join(page)
        path = folder / f"{name}.rst"
        if not path.exists() or path.read_text() != new:
            path.write_text(new)
    new = "\n".join(text)
    if not (folder / "index.rst").exists() or (folder / "index.rst").read_text() != new:
        (folder / "index.rst").write_text(new)


write_api_pages(DOCS / "api")


def escape_plain_text_math(app, what, name, obj, options, lines):
    """Docstrings write absolute values as plain text (``|d| < t``); in reST a ``|`` starts a substitution.

    Escape every ``|`` outside inline literals so the site shows the docstring as written.
    """
    for i, line in enumerate(lines):
        if "|" not in line:
            continue
        parts = line.split("``")
        lines[i] = "``".join(p if k % 2 else p.replace("|", "\\|") for k, p in enumerate(parts))


def setup(app):
    app.connect("autodoc-process-docstring", escape_plain_text_math, priority=100)
