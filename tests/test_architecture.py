"""The house: layers without cycles (pyproject.toml), public names across modules."""

import ast
import pathlib

import grimp
import pytest

import robust_sindy

PACKAGE = pathlib.Path(robust_sindy.__file__).parent
ROOT = PACKAGE.parent
COMMANDS = {"cli", "fit_command", "reproduce", "bench", "zoo", "frontier"}


@pytest.fixture(scope="module")
def graph():
    # Every import statement, those inside functions included.
    return grimp.build_graph("robust_sindy", cache_dir=None)


def _cycles(graph) -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan)."""
    index, low, stack, on, out = {}, {}, [], set(), []

    def visit(v):
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in graph.find_modules_directly_imported_by(v):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    # A package's __init__ re-exports its modules: an edge into it from one of them
    # is an import of a sibling through the package, counted as such.
    for module in sorted(graph.modules):
        if module not in index:
            visit(module)
    return out


def test_no_import_cycles(graph):
    assert _cycles(graph) == []


def test_the_layer_contract_holds():
    from importlinter.cli import lint_imports

    assert lint_imports(config_filename=str(ROOT / "pyproject.toml"), no_cache=True) == 0


def test_nothing_imports_the_commands(graph):
    for name in COMMANDS - {"cli"}:
        importers = graph.find_modules_that_directly_import(f"robust_sindy.{name}")
        assert importers <= {"robust_sindy.cli"}, (name, importers)


def _private_imports(path: pathlib.Path):
    """The private names (``_name``) a module imports from the package."""
    tree = ast.parse(path.read_text())
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and (
            node.level or "robust_sindy" in (node.module or "")
        ):
            for alias in node.names:
                if alias.name.startswith("_") and not alias.name.startswith("__"):
                    yield node.module, alias.name


#: Private modules of compiled kernels, imported as modules by their one user.
KERNEL_MODULES = {"_kernel", "_temporal_kernels"}


def test_modules_use_only_public_names_of_other_modules():
    found = {
        (str(p.relative_to(ROOT)), module, name)
        for p in PACKAGE.rglob("*.py")
        for module, name in _private_imports(p)
        if name not in KERNEL_MODULES
    }
    assert found == set()
