"""The import graph of labkit: layered, without cycles, light to import."""

import ast
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


def test_cli_and_demo_share_output_helpers_instead_of_importing_each_other():
    modules = _modules()
    demo = _top_level_imports("labkit.demo", modules["labkit.demo"], modules)
    assert "labkit.cli" not in demo and "labkit._outputs" in demo
    assert "from .cli" not in modules["labkit.demo"].read_text()


def test_reading_io_and_ransac_loads_no_heavy_dependency():
    """laspy, numba, matplotlib and pyvista load only when a function needs them."""
    code = ("import sys, labkit.io, labkit.ransac, labkit.regions, labkit.cli; "
            "print(sorted(m for m in ('laspy', 'numba', 'matplotlib.pyplot', 'pyvista') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"
