"""The public stage functions carry numpydoc sections: Parameters, and Returns when they return a value.

A public stage function is what a stage offers to the stages after it: a function or class of a stage
folder (``geometry`` to ``simulation``) that a later stage, the ROS machinery (``ros/``), a node or a tool
(``cli/``) imports, found with ``ast`` over the imports (re-exports followed to the defining module).
``common/`` sits under every stage and is not counted.
"""
from __future__ import annotations

import ast
from pathlib import Path
import re

import gls_calibration
from test_layering import STAGES     # the stages in pipeline order: one owner

PACKAGE = Path(gls_calibration.__file__).parent
DOCUMENTED_STAGES = ("geometry", "scan", "fiducials", "registration", "discrepancy", "models", "correction",
                     "calibration", "report", "simulation")
# Functions without parameters and protocols (no constructor): nothing to put under "Parameters".
NO_PARAMETERS = frozenset({"gls_calibration.geometry.head_config.default_head_config_path",
                           "gls_calibration.models.model_selection.DeviationModel"})


def _module_name(path: Path) -> str:
    parts = path.relative_to(PACKAGE).with_suffix("").parts
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(("gls_calibration",) + parts)


def _stage(module: str) -> str:
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else ""


TREES = {_module_name(path): ast.parse(path.read_text(), filename=str(path)) for path in PACKAGE.rglob("*.py")}


def _definitions(module: str) -> dict[str, ast.AST]:
    """The functions and classes defined at the top level of ``module``."""
    return {node.name: node for node in TREES[module].body
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef))}


def _reexports(module: str) -> dict[str, tuple[str, str]]:
    """Names ``module`` imports at its top level from the package: local name -> (module, name)."""
    found = {}
    for node in TREES[module].body:
        if isinstance(node, ast.ImportFrom) and node.level == 0 and (node.module or "").startswith("gls_calibration."):
            for alias in node.names:
                found[alias.asname or alias.name] = (node.module, alias.name)
    return found


def _resolve(module: str, name: str, depth: int = 0) -> tuple[str, str] | None:
    """The (module, name) that defines ``module.name``, following re-exports; None when not a function/class."""
    if module not in TREES or depth > 10:
        return None
    if name in _definitions(module):
        return module, name
    source = _reexports(module).get(name)
    return _resolve(*source, depth + 1) if source else None


def _imported_names(module: str) -> set[tuple[str, str]]:
    """Every (module, name) of the package that ``module`` imports, by name or as ``alias.name`` of a module."""
    tree = TREES[module]
    names, module_aliases = set(), {}
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and node.level == 0 and (node.module or "").startswith("gls_calibration"):
            for alias in node.names:
                submodule = f"{node.module}.{alias.name}"
                if submodule in TREES:
                    module_aliases[alias.asname or alias.name] = submodule
                else:
                    names.add((node.module, alias.name))
        elif isinstance(node, ast.Import):
            for alias in node.names:
                if alias.name in TREES and alias.asname:
                    module_aliases[alias.asname] = alias.name
    for node in ast.walk(tree):
        if (isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name)
                and node.value.id in module_aliases):
            names.add((module_aliases[node.value.id], node.attr))
    return names


def public_stage_functions() -> dict[tuple[str, str], ast.AST]:
    """The public stage functions: (module, name) -> the definition's node."""
    found = {}
    for importer in TREES:
        for module, name in _imported_names(importer):
            resolved = _resolve(module, name)
            if resolved is None or _stage(resolved[0]) not in DOCUMENTED_STAGES:
                continue
            if STAGES.index(_stage(importer)) > STAGES.index(_stage(resolved[0])):
                found[resolved] = _definitions(resolved[0])[resolved[1]]
    return dict(sorted(found.items()))


def _sections(docstring: str) -> set[str]:
    """The numpydoc section titles of a docstring (a title line underlined with dashes)."""
    lines = [line.strip() for line in docstring.splitlines()]
    return {title for title, underline in zip(lines, lines[1:]) if title and re.fullmatch(r"-{3,}", underline)}


def _own_nodes(function: ast.AST):
    """The nodes of a function's body, without those of functions, lambdas and classes nested in it."""
    pending = list(ast.iter_child_nodes(function))
    while pending:
        node = pending.pop()
        yield node
        if not isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda, ast.ClassDef)):
            pending.extend(ast.iter_child_nodes(node))


def _returns_value(node: ast.AST) -> bool:
    """Whether a function returns something other than None: by its annotation, else by its return statements."""
    if isinstance(node, ast.ClassDef):
        return False
    annotation = node.returns
    if annotation is not None:
        return not (isinstance(annotation, ast.Constant) and annotation.value is None)
    return any(isinstance(child, ast.Return) and child.value is not None for child in _own_nodes(node))


def _is_generator(node: ast.AST) -> bool:
    return any(isinstance(child, (ast.Yield, ast.YieldFrom)) for child in _own_nodes(node))


def _call_method(node: ast.AST) -> ast.AST | None:
    """The ``__call__`` a class defines, else None."""
    return next((child for child in getattr(node, "body", ()) if isinstance(child, ast.FunctionDef)
                 and isinstance(node, ast.ClassDef) and child.name == "__call__"), None)


def missing_sections(node: ast.AST, qualified_name: str) -> list[str]:
    """The sections the docstring of ``node`` (``module.name``) lacks ("Parameters", "Returns"/"Yields").

    A class is called through its constructor (its docstring) and, when it defines one, its ``__call__``.
    """
    sections = _sections(ast.get_docstring(node) or "")
    call = _call_method(node)
    missing = [f"__call__ {section}" for section in missing_sections(call, "__call__")] if call else []
    if qualified_name not in NO_PARAMETERS and "Parameters" not in sections:
        missing.append("Parameters")
    if _returns_value(node):
        wanted = "Yields" if _is_generator(node) else "Returns"
        if wanted not in sections:
            missing.append(wanted)
    return missing


def test_the_definition_finds_the_stage_entry_points():
    public = public_stage_functions()
    assert ("gls_calibration.calibration.procedure", "calibrate") in public
    assert ("gls_calibration.fiducials.measure", "measure_fiducials") in public
    assert len(public) > 50
    assert not any(_stage(module) == "common" for module, _ in public)


def test_every_public_stage_function_has_its_sections():
    problems = [f"{module}.{name}: no {', '.join(missing)}"
                for (module, name), node in public_stage_functions().items()
                if (missing := missing_sections(node, f"{module}.{name}"))]
    assert problems == []


def test_the_allow_list_holds_only_functions_without_parameters():
    public = public_stage_functions()
    for qualified in NO_PARAMETERS:
        node = public[tuple(qualified.rsplit(".", 1))]
        if isinstance(node, ast.ClassDef):   # a protocol: no constructor of its own
            assert any(getattr(base, "id", "") == "Protocol" for base in node.bases), qualified
            assert not any(getattr(child, "name", "") == "__init__" for child in node.body), qualified
            continue
        assert isinstance(node, ast.FunctionDef), qualified
        arguments = node.args
        assert not (arguments.posonlyargs or arguments.args or arguments.kwonlyargs
                    or arguments.vararg or arguments.kwarg), f"{qualified} takes parameters"


def test_the_check_sees_a_missing_section():
    # The check above can fail: a docstring without a Returns section, and one without any section.
    source = ('def f(x: float) -> float:\n    """Return x.\n\n    Parameters\n    ----------\n'
              '    x : float\n        A value.\n    """\n    return x\n\n'
              'def g(x: float) -> None:\n    """Do nothing."""\n')
    tree = ast.parse(source)
    assert missing_sections(tree.body[0], "f") == ["Returns"]
    assert missing_sections(tree.body[1], "g") == ["Parameters"]
    # without an annotation, a return statement with a value asks for Returns; a nested one does not
    plain = ast.parse('def h(x):\n    """Do x.\n\n    Parameters\n    ----------\n    x : int\n        A value.\n'
                      '    """\n    def inner():\n        return x\n    return inner()\n\n'
                      'def k(x):\n    """Do x.\n\n    Parameters\n    ----------\n    x : int\n        A value.\n'
                      '    """\n    def inner():\n        return x\n    inner()\n')
    assert missing_sections(plain.body[0], "h") == ["Returns"]
    assert missing_sections(plain.body[1], "k") == []
    # and a class whose __call__ lacks its sections
    callable_class = ast.parse('class C:\n    """A thing.\n\n    Parameters\n    ----------\n    a : int\n'
                               '        A value.\n    """\n\n    def __call__(self, x) -> float:\n'
                               '        """Return x."""\n')
    assert missing_sections(callable_class.body[0], "C") == ["__call__ Parameters", "__call__ Returns"]
