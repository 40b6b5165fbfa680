"""The import graph of labkit: layered, without cycles, light to import."""

import ast
import re
import subprocess
import sys
from pathlib import Path

import labkit

PACKAGE = Path(labkit.__file__).parent


def _modules():
    """Dotted name -> path of every module of labkit."""
    out = {}
    for path in sorted(PACKAGE.rglob("*.py")):
        parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
        name = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
        out[name] = path
    return out


def _top_level_imports(name, path, modules):
    """labkit modules that ``name`` imports at module level (a submodule import counts as the submodule)."""
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found = set()
    for node in ast.parse(path.read_text()).body:
        if isinstance(node, ast.Import):
            found |= {a.name for a in node.names if a.name in modules}
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")[: len(package.split(".")) - node.level + 1]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            if target in modules:
                found.add(target)
            found |= {f"{target}.{a.name}" for a in node.names if f"{target}.{a.name}" in modules}
    found.discard(name)
    return found


def _cycle(graph):
    """One import cycle as a list of modules, or None."""
    state, stack = {}, []

    def visit(v):
        state[v] = 1
        stack.append(v)
        for w in sorted(graph[v]):
            if state.get(w) == 1:
                return stack[stack.index(w):] + [w]
            if w not in state:
                found = visit(w)
                if found:
                    return found
        state[v] = 2
        stack.pop()
        return None

    for v in sorted(graph):
        if v not in state:
            found = visit(v)
            if found:
                return found
    return None


def test_module_level_imports_have_no_cycle():
    modules = _modules()
    graph = {name: _top_level_imports(name, path, modules) for name, path in modules.items()}
    assert _cycle(graph) is None
    # the detector finds a cycle when there is one
    assert _cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == ["a", "b", "c", "a"]


def _all_imports(name, path, modules):
    """labkit modules that ``name`` imports anywhere, also inside functions (a submodule import counts as it)."""
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            found |= {a.name for a in node.names if a.name in modules}
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")[: len(package.split(".")) - node.level + 1]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            if target in modules:
                found.add(target)
            found |= {f"{target}.{a.name}" for a in node.names if f"{target}.{a.name}" in modules}
    found.discard(name)
    return found


def test_imports_have_no_cycle_also_counting_imports_inside_functions():
    modules = _modules()
    graph = {name: _all_imports(name, path, modules) for name, path in modules.items()}
    assert _cycle(graph) is None


def test_top_level_holds_at_most_twelve_modules():
    """The folders show the concepts: loose modules at the top are few."""
    top = sorted(p.name for p in PACKAGE.glob("*.py"))
    assert len(top) <= 12, top


def test_voxel_thinning_and_point_spacing_have_one_home():
    """Only labkit.neighbours.sampling computes one point per voxel or a median nearest-neighbour spacing."""
    home = PACKAGE / "neighbours" / "sampling.py"
    offenders = []
    for path in _modules().values():
        if path == home:
            continue
        text = path.read_text()
        for node in ast.walk(ast.parse(text)):
            if isinstance(node, ast.FunctionDef) and re.search(r"voxel|spacing|subsample|even_subset", node.name):
                body = ast.get_source_segment(text, node) or ""
                # a function of that name elsewhere must hand the work to the one home
                if not re.search(r"\b(voxel_thin|voxel_sample|median_spacing|even_subset)\(", body):
                    offenders.append(f"{path.relative_to(PACKAGE.parent)}:{node.name}")
            if isinstance(node, ast.Call) and ast.unparse(node.func).endswith("lexsort"):
                args = ast.unparse(node)
                if re.search(r"d2|dist2", args) and re.search(r"key|inv", args) and "cell" in text:
                    offenders.append(f"{path.relative_to(PACKAGE.parent)}: nearest-the-centre per cell")
    assert offenders == []


def test_cli_and_demo_share_output_helpers_instead_of_importing_each_other():
    modules = _modules()
    demo = _top_level_imports("labkit.demo", modules["labkit.demo"], modules)
    assert "labkit.cli.main" not in demo and "labkit.core.outputs" in demo
    assert "from .cli" not in modules["labkit.demo"].read_text()


def test_reading_io_and_ransac_loads_no_heavy_dependency():
    """laspy, numba, matplotlib and pyvista load only when a function needs them."""
    code = ("import sys, labkit.io, labkit.ransac, labkit.regions, labkit.cli; "
            "print(sorted(m for m in ('laspy', 'numba', 'matplotlib.pyplot', 'pyvista') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"


# --------------------------------------------------------------------------- size of a module
MAX_LINES = 600  # what one reads in a sitting; most modules stay under about 400


def test_no_module_is_longer_than_one_reads_in_a_sitting():
    lengths = {path.relative_to(PACKAGE.parent).as_posix(): len(path.read_text().splitlines())
               for path in _modules().values()}
    assert {name: n for name, n in lengths.items() if n > MAX_LINES} == {}


# --------------------------------------------------------------------------- private names across packages
#: Imports of a private name from a module of another package that are known today, each with its reason.
#: Every entry is (importing module, imported module, name). Fix the cause, then remove the entry.
PRIVATE_IMPORTS = set()  # empty since distances takes its normals from labkit.features.pca_at


def _package_of(name, modules):
    return name if modules[name].name == "__init__.py" else name.rpartition(".")[0]


def _private_imports():
    """(importer, imported module, name) for every ``from X import _name`` where X is a labkit module elsewhere.

    A private name may be shared inside its package (``labkit.tiles.register`` uses ``labkit.tiles.survey._Files``)
    and a private *module* of the importer's own package may be imported; a private name of a module in another
    package may not (``labkit.change.distances`` importing ``labkit.registration.matching.match._x``).
    """
    modules = _modules()
    found = set()
    for name, path in modules.items():
        package = _package_of(name, modules)
        for node in ast.walk(ast.parse(path.read_text())):
            if not isinstance(node, ast.ImportFrom):
                continue
            if node.level:
                base = package.split(".")[: len(package.split(".")) - node.level + 1]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            if target not in modules:
                continue
            for alias in node.names:
                private = alias.name.startswith("_") and not alias.name.startswith("__")
                if private and f"{target}.{alias.name}" in modules:
                    home = target  # a private submodule: allowed from its own package
                else:
                    home = _package_of(target, modules)
                if private and home != package:
                    found.add((name, target, alias.name))
    return found


def test_no_module_imports_a_private_name_of_another_package():
    found = _private_imports()
    assert found - PRIVATE_IMPORTS == set()
    assert PRIVATE_IMPORTS - found == set()  # a fixed case leaves the allowlist


# --------------------------------------------------------------------------- runnable examples
def _public_objects():
    """(where, name, object) of every function and class in ``labkit.__all__`` and the public modules' ``__all__``."""
    import importlib
    import inspect
    import warnings

    out = []
    names = [n for n, p in _modules().items()
             if not any(part.startswith("_") for part in n.split(".")[1:])]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        for name in ["labkit"] + sorted(set(names) - {"labkit"}):
            module = importlib.import_module(name)
            for attr in getattr(module, "__all__", ()):
                obj = getattr(module, attr)
                if inspect.isfunction(obj) or inspect.isclass(obj):
                    out.append((name, attr, obj))
    return out


def test_every_public_function_and_class_has_a_runnable_example():
    import inspect

    objects = _public_objects()
    assert len(objects) > 50  # the walk found the public API (tiles, io, regions, ransac, ...)
    without = sorted({f"{where}.{name}" for where, name, obj in objects
                      if not ("Examples\n--------" in (inspect.getdoc(obj) or "") and ">>>" in inspect.getdoc(obj))})
    assert without == []


# --------------------------------------------------------------------------- references
_SECTION = re.compile(r"^(\w[\w ]*)\n-+$", re.MULTILINE)


def _sections(doc):
    """Numpydoc section titles of ``doc`` in order, and the body of each."""
    heads = list(_SECTION.finditer(doc))
    return [(m.group(1), doc[m.end():heads[i + 1].start() if i + 1 < len(heads) else len(doc)])
            for i, m in enumerate(heads)]


def _first_reference(doc):
    """Text of the ``.. [1]`` entry of the References section, or None."""
    body = dict(_sections(doc)).get("References")
    if body is None:
        return None
    m = re.match(r"\s*\.\. \[1\] (.*?)(?=\n\.\. \[2\]|\Z)", body, re.DOTALL)
    return " ".join(m.group(1).split()) if m else None


def test_first_reference_parser_rejects_what_it_should():
    assert _first_reference("Summary.\n\nExamples\n--------\n>>> 1\n1") is None
    assert _first_reference("S.\n\nReferences\n----------\nSomebody (2000).\n") is None  # not numbered
    doc = "S.\n\nReferences\n----------\n.. [1] Notebook 04,\n   eq. 5.\n.. [2] X (1999): Y.\n\nExamples\n--------\n"
    assert _first_reference(doc) == "Notebook 04, eq. 5."


def test_every_public_function_cites_its_equations_or_literature():
    """Every function in ``labkit.__all__`` names what it follows: a notebook or seed equation or a publication.

    The References section sits after Notes and before Examples, and a notebook it cites exists.
    """
    import inspect
    import warnings

    notebooks = {p.name[:2] for p in (PACKAGE.parent / "notebooks").glob("[0-9][0-9]-*.ipynb")}
    assert len(notebooks) >= 10
    bad = {}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        functions = {n: getattr(labkit, n) for n in labkit.__all__ if inspect.isfunction(getattr(labkit, n))}
    assert len(functions) > 25  # the walk found the top-level functions (icp, m3c2, read_cloud, ...)
    for name, func in functions.items():
        doc = inspect.getdoc(func) or ""
        first = _first_reference(doc)
        titles = [t for t, _ in _sections(doc)]
        if first is None:
            bad[name] = "no numbered References section"
        elif not re.search(r"\b(notebooks?|seed) \d\d|\(\d{4}\)", first, re.IGNORECASE):
            bad[name] = f"first reference cites neither a notebook, a seed nor a publication: {first!r}"
        elif "Notes" in titles[titles.index("References"):] or "Examples" in titles[:titles.index("References")]:
            bad[name] = f"References out of place in {titles}"
        else:
            cited = set(re.findall(r"notebooks? (\d\d)", first, re.IGNORECASE))
            for a, b in re.findall(r"notebooks (\d\d)-(\d\d)", first, re.IGNORECASE):
                cited |= {f"{i:02d}" for i in range(int(a), int(b) + 1)}
            if cited - notebooks:
                bad[name] = f"cites notebooks that do not exist: {sorted(cited - notebooks)}"
    assert bad == {}


# --------------------------------------------------------------------------- imports inside functions
#: In-function imports of labkit's own modules, (importer, imported module) -> why it is not at the top.
LAZY_IMPORTS = {
    ("labkit.neighbours.treecache", "labkit.neighbours.kdtree"): "heavy",
    ("labkit.neighbours.sampling", "labkit.neighbours.kdtree"): "heavy",  # regions thins without the compiled tree
    ("labkit.cli.main", "labkit.change.m3c2"): "heavy",
    ("labkit.registration.methods", "labkit.registration"): "heavy",  # cli imports compare, which imports methods
    ("labkit.demo", "labkit.features"): "heavy",  # demo is imported by cli
    ("labkit.change.distances", "labkit.features"): "heavy",
    ("labkit.plotting.registration", "labkit.registration.matching.match"): "heavy",
    ("labkit.tiles.register", "labkit.registration"): "heavy",  # the icp function loads matching
    ("labkit.widgets", "labkit.features"): "heavy",
    ("labkit.widgets", "labkit.registration"): "heavy",
    ("labkit.widgets", "labkit.registration.matching.match"): "heavy",
}


def _lazy_imports():
    """(importer, imported module) of every ``from labkit... import`` inside a function."""
    modules = _modules()
    found = set()
    for name, path in modules.items():
        package = _package_of(name, modules)
        for func in ast.walk(ast.parse(path.read_text())):
            if not isinstance(func, (ast.FunctionDef, ast.AsyncFunctionDef)):
                continue
            for node in ast.walk(func):
                if isinstance(node, ast.ImportFrom) and (node.level or (node.module or "").startswith("labkit")):
                    base = package.split(".")[: len(package.split(".")) - node.level + 1] if node.level else []
                    found.add((name, ".".join(base + ([node.module] if node.module else []))))
    return found


def test_labkit_modules_are_imported_inside_functions_only_to_stay_light_or_to_break_a_cycle():
    assert _lazy_imports() == set(LAZY_IMPORTS)
    # "heavy" is true: importing (and using) the target loads numba; "cycle" is true: the target imports the importer
    modules = _modules()
    for (importer, target), why in LAZY_IMPORTS.items():
        if why == "cycle":
            assert importer in _top_level_imports(target, modules[target], modules)
    heavy = sorted({t for (_, t), why in LAZY_IMPORTS.items() if why == "heavy"})
    code = ("import sys, importlib; m = importlib.import_module({!r}); "
            "getattr(m, 'icp', None); print('numba' in sys.modules)")
    runs = {t: subprocess.Popen([sys.executable, "-c", code.format(t)], stdout=subprocess.PIPE, text=True)
            for t in heavy}  # fresh interpreters, side by side
    assert {t: run.communicate()[0].strip() for t, run in runs.items()} == {t: "True" for t in heavy}
