"""Architecture rules for the ``octolgp`` package, checked statically with :mod:`ast`.

Every ``octolgp/**/*.py`` file is parsed (nothing is imported) into a :class:`Module`,
and each rule below is one function returning :class:`Violation` s, each its own test
that fails listing every offending ``file:line``:

1. **No import cycles** among octolgp modules (imports under ``if TYPE_CHECKING:``
   excepted). Cycles make import order matter, hide half-initialised modules and keep
   the layers below from being used, tested or replaced on their own.
2. **No private names across modules** (``from octolgp.x import _y``): a leading
   underscore means "only this module relies on it"; importing it elsewhere makes a
   refactor of ``x`` silently break ``y``.
3. **No reaching into other objects' private attributes**: ``obj._x`` only on ``self``
   or ``cls``. Same reason as rule 2, for instances; third-party private attributes
   (``np._x``) are no better, so only an explicit (file, attribute) allowlist, each with
   its reason, may excuse one.
4. **Numerics stay below the application**: ``octolgp.geometry``, ``octolgp.gp``,
   ``octolgp.training``, ``octolgp.partition`` and ``octolgp.scan`` never import the
   online map, persistence, sinks, readers, CLI, benchmarks or batch methods (not even
   for typing): they are the reusable core everything else is built from.
5. **Rerun only in its adapters** (``octolgp/sinks/*rerun*``, ``octolgp/io/rrd*``): a
   heavy, version-pinned dependency stays behind the sink protocol and the rrd reader.
6. **sqlite3 only in** ``octolgp/persist/``: one place owns the map file's schema.
7. **No result-bearing globals**: no ``global`` statement, and no module-level name
   bound to a mutable container (list/dict/set displays or comprehensions,
   ``list()``, ``dict()``, ``defaultdict(...)``, ...). Results that live in module state
   leak between maps, threads and tests; constants must be immutable (tuple,
   ``frozenset``, ``MappingProxyType``). ``__dunder__`` names (``__all__``) are exempt.
8. **``import octolgp`` stays light**: it must not pull in matplotlib, sklearn, rerun,
   dask or distributed (checked in a fresh interpreter).
9. **The layout exists**: the subpackages, ``octolgp/py.typed``, and
   ``python -m octolgp --help``.
10. **Leaf engines apart**: ``octolgp.engines.lattice`` and ``octolgp.engines.exact`` never
    import each other, and the orchestrator (``octolgp.mapping.online`` and the modules it
    delegates to) imports only the seam (``octolgp.engines``, ``octolgp.engines.base``),
    so a third engine is one module and the map never branches on which it has.

The import graph (rule 1) has one edge per import statement anywhere in a file,
including inside functions: a lazy import still closes a cycle once it runs. ``from
octolgp.x import y`` is an edge to ``octolgp.x.y`` when that is a module (file or
package) and to ``octolgp.x`` otherwise; ``import octolgp.x.y`` is an edge to
``octolgp.x.y``; a package's node is its ``__init__.py``. Edges from a package's
``__init__`` to its submodules (re-exports) are ordinary edges, so a submodule that
imports a name back from its own package (``from octolgp.a import z``) closes a cycle.
Implicit imports of parent packages are not edges (Python handles those), and imports
of modules that do not exist are ignored here (other tests fail on those).

The ``test_checker_*`` tests run each rule on small synthetic sources, so that a bug in
the checker cannot make the real rules pass silently.
"""

from __future__ import annotations

import ast
import functools
import itertools
import re
import subprocess
import sys
from collections import deque
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from collections.abc import Set as AbstractSet
from dataclasses import dataclass
from pathlib import Path
from types import MappingProxyType

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = "octolgp"

#: The layers that must not depend on the application around them (rule 4).
NUMERICS = (
    "octolgp.geometry",
    "octolgp.gp",
    "octolgp.training",
    "octolgp.partition",
    "octolgp.scan",
)
#: What the numerics must never import (rule 4).
APPLICATION = (
    "octolgp.mapping",
    "octolgp.persist",
    "octolgp.sinks",
    "octolgp.io",
    "octolgp.cli",
    "octolgp.bench",
    "octolgp.batch",
)
#: Subpackages that must be directories with an ``__init__.py`` (rule 9).
SUBPACKAGES = (
    "geometry",
    "gp",
    "batch",
    "mapping",
    "persist",
    "sinks",
    "io",
    "sim",
    "bench",
)
#: Parts of the layout that may be a module or a package (rule 9).
MODULES_OR_PACKAGES = ("scan", "training", "partition", "export", "cli")
#: Top-level modules that must be single files (rule 9).
TOP_LEVEL_MODULES = ("config", "errors")
#: Heavy optional dependencies ``import octolgp`` must not load (rule 8).
HEAVY_MODULES = ("matplotlib", "sklearn", "rerun", "distributed", "dask")
#: (file, attribute) pairs allowed to read a private attribute of something that is not
#: ``self``/``cls`` (rule 3). Each entry needs a comment saying why. Keep it empty.
ALLOWED_PRIVATE_ATTRIBUTES: frozenset[tuple[str, str]] = frozenset()
#: Calls that build a mutable container (rule 7); matched on the called name.
MUTABLE_FACTORIES = frozenset(
    {
        "list",
        "dict",
        "set",
        "bytearray",
        "OrderedDict",
        "defaultdict",
        "deque",
        "Counter",
        "ChainMap",
        "WeakKeyDictionary",
        "WeakValueDictionary",
        "WeakSet",
    }
)
_UPPER_CASE = re.compile(r"_?[A-Z][A-Z0-9_]*")


# --------------------------------------------------------------------------------------
# Model: modules, imports, violations
# --------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Module:
    """One parsed source file of the package.

    Attributes
    ----------
    name : str
        Dotted module name; a package's ``__init__.py`` is named after the package.
    path : str
        Path relative to the repository root, as shown in failure messages.
    tree : ast.Module
        The parsed source.
    is_package : bool
        Whether the file is a package's ``__init__.py``.
    """

    name: str
    path: str
    tree: ast.Module
    is_package: bool

    @property
    def package(self) -> str:
        """The package relative imports resolve against (the module's own, if one)."""
        return self.name if self.is_package else self.name.rpartition(".")[0]

    def within(self, prefixes: Iterable[str]) -> bool:
        """Whether the module is one of ``prefixes`` or inside one of them."""
        return any(_is_within(self.name, p) for p in prefixes)


@dataclass(frozen=True)
class ImportRef:
    """One imported thing: ``import module`` or ``from module import name``.

    Attributes
    ----------
    module : str
        Absolute dotted module (relative imports resolved).
    name : str or None
        The name of a ``from`` import; None for ``import module``.
    line : int
        Line of the import statement.
    type_checking : bool
        Whether the import sits under ``if TYPE_CHECKING:`` (never runs).
    """

    module: str
    name: str | None
    line: int
    type_checking: bool

    @property
    def spelled(self) -> str:
        """The import as written (modulo relative imports and aliases)."""
        if self.name is None:
            return f"import {self.module}"
        return f"from {self.module} import {self.name}"

    @property
    def candidates(self) -> tuple[str, ...]:
        """Dotted names this import may denote, most specific first."""
        if self.name is None or self.name == "*":
            return (self.module,)
        return (f"{self.module}.{self.name}", self.module)


@dataclass(frozen=True)
class Violation:
    """One breach of a rule, at ``path:line``."""

    path: str
    line: int
    detail: str

    def __str__(self) -> str:
        return f"{self.path}:{self.line}: {self.detail}"


def _is_within(name: str, prefix: str) -> bool:
    """Whether dotted ``name`` is ``prefix`` or a submodule of it."""
    return name == prefix or name.startswith(prefix + ".")


def module_name(relpath: Path) -> tuple[str, bool]:
    """Dotted name of a source file and whether it is a package ``__init__``.

    Parameters
    ----------
    relpath : Path
        Path relative to the repository root, e.g. ``octolgp/gp/kernels.py``.

    Returns
    -------
    tuple of (str, bool)
        ``("octolgp.gp.kernels", False)``; ``("octolgp.gp", True)`` for its
        ``__init__.py``.
    """
    parts = list(relpath.with_suffix("").parts)
    is_package = parts[-1] == "__init__"
    if is_package:
        parts.pop()
    return ".".join(parts), is_package


def parse_module(name: str, source: str, *, path: str, is_package: bool = False) -> Module:
    """Parse ``source`` into a :class:`Module` (also used on synthetic sources)."""
    return Module(name, path, ast.parse(source, filename=path), is_package)


@functools.cache
def package_modules() -> tuple[Module, ...]:
    """Every ``octolgp/**/*.py`` of the working tree, parsed (cached for the session)."""
    modules = []
    for file in sorted((ROOT / PACKAGE).rglob("*.py")):
        relpath = file.relative_to(ROOT)
        name, is_package = module_name(relpath)
        modules.append(
            parse_module(
                name,
                file.read_text(encoding="utf-8"),
                path=relpath.as_posix(),
                is_package=is_package,
            )
        )
    return tuple(modules)


def _is_type_checking(test: ast.expr) -> bool:
    """Whether an ``if`` test is ``TYPE_CHECKING`` or ``typing.TYPE_CHECKING``."""
    return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or (
        isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING"
    )


def walk_with_type_checking(tree: ast.AST) -> Iterator[tuple[ast.AST, bool]]:
    """Every node below ``tree``, with whether it sits under ``if TYPE_CHECKING:``.

    Only the body of such an ``if`` counts; its ``else`` runs.
    """
    stack: list[tuple[ast.AST, bool]] = [(tree, False)]
    while stack:
        node, flag = stack.pop()
        yield node, flag
        if isinstance(node, ast.If) and _is_type_checking(node.test):
            stack.extend((child, True) for child in node.body)
            stack.extend((child, flag) for child in node.orelse)
        else:
            stack.extend((child, flag) for child in ast.iter_child_nodes(node))


def _absolute(module: Module, node: ast.ImportFrom) -> str:
    """The absolute module of a ``from`` import, resolving relative imports."""
    if node.level == 0:
        return node.module or ""
    base = module.package.split(".")
    base = base[: len(base) - (node.level - 1)]
    return ".".join([*base, *([node.module] if node.module else [])])


def iter_imports(module: Module) -> Iterator[ImportRef]:
    """Every import in ``module``, anywhere in the file, in source order.

    Parameters
    ----------
    module : Module
        The parsed file.

    Yields
    ------
    ImportRef
        One per imported module (``import a, b`` gives two) or imported name.
    """
    refs: list[ImportRef] = []
    for node, type_checking in walk_with_type_checking(module.tree):
        if isinstance(node, ast.Import):
            refs.extend(
                ImportRef(alias.name, None, node.lineno, type_checking) for alias in node.names
            )
        elif isinstance(node, ast.ImportFrom):
            source = _absolute(module, node)
            refs.extend(
                ImportRef(source, alias.name, node.lineno, type_checking) for alias in node.names
            )
    yield from sorted(refs, key=lambda r: r.line)


def _top_level(ref: ImportRef) -> str:
    """The distribution-level module an import loads (``rerun`` for ``rerun.blueprint``)."""
    return ref.module.partition(".")[0]


def _fail_on(rule: str, violations: Sequence[Violation]) -> None:
    """Fail the calling test listing every violation, or do nothing if there are none."""
    if violations:
        listing = "\n".join(f"  {v}" for v in sorted(violations, key=lambda v: (v.path, v.line)))
        pytest.fail(f"{rule}: {len(violations)} violation(s)\n{listing}", pytrace=False)


# --------------------------------------------------------------------------------------
# Rule 1: import cycles
# --------------------------------------------------------------------------------------

#: Import graph: module -> imported module -> first line of such an import.
Graph = Mapping[str, Mapping[str, int]]


def resolve(ref: ImportRef, known: AbstractSet[str]) -> str | None:
    """The octolgp module an import runs, or None if it names none that exists.

    ``from octolgp.x import y`` is ``octolgp.x.y`` when that is a module, else
    ``octolgp.x``.
    """
    return next((c for c in ref.candidates if c in known and _is_within(c, PACKAGE)), None)


def import_graph(modules: Sequence[Module]) -> dict[str, dict[str, int]]:
    """Module -> octolgp modules it imports at run time (``TYPE_CHECKING`` left out).

    Self-imports are left out; each edge keeps the line of its first import.
    """
    known = {m.name for m in modules}
    graph: dict[str, dict[str, int]] = {m.name: {} for m in modules}
    for module in modules:
        for ref in iter_imports(module):
            target = resolve(ref, known)
            if ref.type_checking or target is None or target == module.name:
                continue
            graph[module.name].setdefault(target, ref.line)
    return graph


def strongly_connected_components(graph: Graph) -> list[list[str]]:
    """Tarjan's strongly connected components of ``graph``, each sorted."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    on_stack: set[str] = set()
    stack: list[str] = []
    components: list[list[str]] = []

    def visit(node: str) -> None:
        index[node] = low[node] = len(index)
        stack.append(node)
        on_stack.add(node)
        for succ in graph.get(node, {}):
            if succ not in index:
                visit(succ)
                low[node] = min(low[node], low[succ])
            elif succ in on_stack:
                low[node] = min(low[node], index[succ])
        if low[node] == index[node]:
            component = []
            while True:
                member = stack.pop()
                on_stack.discard(member)
                component.append(member)
                if member == node:
                    break
            components.append(sorted(component))

    for node in sorted(graph):
        if node not in index:
            visit(node)
    return components


def _shortest_cycle(graph: Graph, start: str, members: set[str]) -> list[str]:
    """Shortest cycle ``start -> ... -> start`` within ``members`` (breadth first)."""
    parent: dict[str, str] = {}
    queue = deque([start])
    while queue:
        node = queue.popleft()
        for succ in sorted(graph.get(node, {})):
            if succ not in members:
                continue
            if succ == start:
                path = [node]
                while path[-1] != start:
                    path.append(parent[path[-1]])
                return [*reversed(path), start]
            if succ not in parent:
                parent[succ] = node
                queue.append(succ)
    raise AssertionError(f"{start} is in a component but on no cycle")  # pragma: no cover


def find_cycles(graph: Graph) -> list[list[str]]:
    """Import cycles: for each module on one, the shortest cycle through it.

    Returns
    -------
    list of list of str
        Distinct cycles, each ``[a, b, ..., a]`` starting at its smallest module.
    """
    cycles: dict[tuple[str, ...], list[str]] = {}
    for component in strongly_connected_components(graph):
        if len(component) < 2:
            continue
        for start in component:
            cycle = _shortest_cycle(graph, start, set(component))[:-1]
            pivot = cycle.index(min(cycle))
            rotated = [*cycle[pivot:], *cycle[:pivot]]
            cycles.setdefault(tuple(rotated), [*rotated, rotated[0]])
    return sorted(cycles.values())


def check_import_cycles(modules: Sequence[Module]) -> list[Violation]:
    """Rule 1: one violation per import cycle, at the first module's import."""
    graph = import_graph(modules)
    paths = {m.name: m.path for m in modules}
    violations = []
    for cycle in find_cycles(graph):
        hops = " -> ".join(f"{a} ({paths[a]}:{graph[a][b]})" for a, b in itertools.pairwise(cycle))
        violations.append(
            Violation(
                paths[cycle[0]],
                graph[cycle[0]][cycle[1]],
                f"import cycle: {hops} -> {cycle[0]}",
            )
        )
    return violations


# --------------------------------------------------------------------------------------
# Rule 2: private names imported across modules
# --------------------------------------------------------------------------------------


def _is_private(name: str) -> bool:
    """A single leading underscore, not a ``__dunder__``."""
    return name.startswith("_") and not (name.startswith("__") and name.endswith("__"))


def check_private_imports(modules: Sequence[Module]) -> list[Violation]:
    """Rule 2: ``from octolgp.x import _y`` in any module but ``octolgp.x`` itself.

    A private *submodule* (``from octolgp.p import _impl``) may be imported from inside
    its own package ``octolgp.p``.
    """
    known = {m.name for m in modules}
    violations = []
    for module in modules:
        for ref in iter_imports(module):
            if (
                ref.name is None
                or not _is_private(ref.name)
                or not _is_within(ref.module, PACKAGE)
                or ref.module == module.name
            ):
                continue
            submodule = f"{ref.module}.{ref.name}"
            if submodule in known and _is_within(module.name, ref.module):
                continue
            violations.append(
                Violation(module.path, ref.line, f"`{ref.spelled}`: private name of {ref.module}")
            )
    return violations


# --------------------------------------------------------------------------------------
# Rule 3: private attributes of other objects
# --------------------------------------------------------------------------------------


def check_private_attributes(
    modules: Sequence[Module],
    allowed: frozenset[tuple[str, str]] = ALLOWED_PRIVATE_ATTRIBUTES,
) -> list[Violation]:
    """Rule 3: every ``x._attr`` whose ``x`` is not the name ``self`` or ``cls``."""
    violations = []
    for module in modules:
        for node in ast.walk(module.tree):
            if (
                isinstance(node, ast.Attribute)
                and _is_private(node.attr)
                and not (isinstance(node.value, ast.Name) and node.value.id in {"self", "cls"})
                and (module.path, node.attr) not in allowed
            ):
                violations.append(
                    Violation(
                        module.path,
                        node.lineno,
                        f"`{ast.unparse(node)}`: private attribute of something not self/cls",
                    )
                )
    return violations


# --------------------------------------------------------------------------------------
# Rules 4-6: who may import what
# --------------------------------------------------------------------------------------


def check_numerics_independent(modules: Sequence[Module]) -> list[Violation]:
    """Rule 4: numerics modules import no application package, even for typing."""
    violations = []
    for module in modules:
        if not module.within(NUMERICS):
            continue
        for ref in iter_imports(module):
            hit = next(
                (a for a in APPLICATION for c in ref.candidates if _is_within(c, a)),
                None,
            )
            if hit is not None:
                where = " (under TYPE_CHECKING)" if ref.type_checking else ""
                violations.append(
                    Violation(module.path, ref.line, f"`{ref.spelled}`{where}: numerics -> {hit}")
                )
    return violations


#: The leaf engines (rule 10): each its own module, neither importing the other.
ENGINES = ("octolgp.engines.lattice", "octolgp.engines.exact")
#: What the orchestrator may import of the engines (rule 10): the seam, not an engine.
ENGINE_SEAM = ("octolgp.engines", "octolgp.engines.base")
#: The orchestrators, which call ``self.engine`` and never an engine's internals.
ORCHESTRATORS = ("octolgp.mapping.online", "octolgp.mapping.correction", "octolgp.mapping.evidence")


def check_engines_apart(modules: Sequence[Module]) -> list[Violation]:
    """Rule 10: the engines never import each other; orchestrators only the engine seam."""
    violations = []
    for module in modules:
        for ref in iter_imports(module):
            engine = next((e for e in ENGINES for c in ref.candidates if _is_within(c, e)), None)
            if engine is None:
                continue
            if module.within(ENGINES) and not module.within((engine,)):
                violations.append(
                    Violation(module.path, ref.line, f"`{ref.spelled}`: engine -> {engine}")
                )
            if module.name in ORCHESTRATORS:
                violations.append(
                    Violation(module.path, ref.line, f"`{ref.spelled}`: orchestrator -> {engine}")
                )
    return violations


def _rerun_allowed(module: Module) -> bool:
    """``octolgp/sinks/**`` named ``*rerun*``, or ``octolgp/io/rrd*`` (file or package)."""
    parts = Path(module.path).with_suffix("").parts
    if parts[:2] == (PACKAGE, "sinks"):
        return any("rerun" in part for part in parts[2:])
    if parts[:2] == (PACKAGE, "io"):
        return len(parts) > 2 and parts[2].startswith("rrd")
    return False


def _sqlite_allowed(module: Module) -> bool:
    """Anything under ``octolgp/persist/``."""
    return module.within([f"{PACKAGE}.persist"])


#: Rules 5 and 6: dependency -> which modules may import it.
CONFINED: Mapping[str, Callable[[Module], bool]] = MappingProxyType(
    {"rerun": _rerun_allowed, "sqlite3": _sqlite_allowed}
)


def check_dependency_confined(modules: Sequence[Module], dependency: str) -> list[Violation]:
    """Rules 5 and 6: imports of ``dependency`` outside the modules allowed to use it."""
    is_allowed = CONFINED[dependency]
    return [
        Violation(module.path, ref.line, f"`{ref.spelled}` outside its allowed modules")
        for module in modules
        if not is_allowed(module)
        for ref in iter_imports(module)
        if _top_level(ref) == dependency
    ]


# --------------------------------------------------------------------------------------
# Rule 7: no result-bearing globals
# --------------------------------------------------------------------------------------


def _module_level_statements(body: Sequence[ast.stmt]) -> Iterator[ast.stmt]:
    """Statements that run at module level, including inside ``if``/``try``/``with``."""
    for stmt in body:
        yield stmt
        if isinstance(stmt, ast.If):
            yield from _module_level_statements(stmt.body)
            yield from _module_level_statements(stmt.orelse)
        elif isinstance(stmt, ast.Try | ast.TryStar):
            for block in (stmt.body, stmt.orelse, stmt.finalbody):
                yield from _module_level_statements(block)
            for handler in stmt.handlers:
                yield from _module_level_statements(handler.body)
        elif isinstance(stmt, ast.With):
            yield from _module_level_statements(stmt.body)


_DISPLAYS: tuple[tuple[type[ast.expr], str], ...] = (
    (ast.List, "list display"),
    (ast.Dict, "dict display"),
    (ast.Set, "set display"),
    (ast.ListComp, "list comprehension"),
    (ast.DictComp, "dict comprehension"),
    (ast.SetComp, "set comprehension"),
)


def mutable_container(expr: ast.expr) -> str | None:
    """What mutable container ``expr`` builds (``"dict display"``), or None."""
    for kind, description in _DISPLAYS:
        if isinstance(expr, kind):
            return description
    if isinstance(expr, ast.Call):
        func = expr.func
        called = func.id if isinstance(func, ast.Name) else getattr(func, "attr", None)
        if called in MUTABLE_FACTORIES:
            return f"{called}() call"
    return None


def _bindings(target: ast.expr, value: ast.expr) -> Iterator[tuple[str, ast.expr]]:
    """(name, value) for each plain name an assignment binds.

    ``a, b = [], 1`` pairs element-wise; an unpacking that cannot be paired (``a, b =
    f()``, starred targets) binds every name to the whole value.
    """
    if isinstance(target, ast.Name):
        yield target.id, value
    elif isinstance(target, ast.Tuple | ast.List):
        if (
            isinstance(value, ast.Tuple | ast.List)
            and len(value.elts) == len(target.elts)
            and not any(isinstance(e, ast.Starred) for e in (*target.elts, *value.elts))
        ):
            for element, element_value in zip(target.elts, value.elts, strict=True):
                yield from _bindings(element, element_value)
        else:
            for element in target.elts:
                yield from _bindings(element, value)
    elif isinstance(target, ast.Starred):
        yield from _bindings(target.value, value)


def _is_type_alias(annotation: ast.expr) -> bool:
    """``X: TypeAlias = ...`` or ``X: typing.TypeAlias = ...``."""
    return (isinstance(annotation, ast.Name) and annotation.id == "TypeAlias") or (
        isinstance(annotation, ast.Attribute) and annotation.attr == "TypeAlias"
    )


def check_globals(modules: Sequence[Module]) -> list[Violation]:
    """Rule 7: ``global`` statements and module-level names bound to mutable containers."""
    violations: list[Violation] = []
    for module in modules:
        violations.extend(
            Violation(module.path, node.lineno, f"`global {', '.join(node.names)}`")
            for node in ast.walk(module.tree)
            if isinstance(node, ast.Global)
        )
        for stmt in _module_level_statements(module.tree.body):
            if isinstance(stmt, ast.Assign):
                targets, value = stmt.targets, stmt.value
            elif isinstance(stmt, ast.AnnAssign) and stmt.value is not None:
                if _is_type_alias(stmt.annotation):
                    continue
                targets, value = [stmt.target], stmt.value
            else:
                continue
            for target in targets:
                for name, bound in _bindings(target, value):
                    container = mutable_container(bound)
                    if container is None or (name.startswith("__") and name.endswith("__")):
                        continue
                    kind = (
                        "constant must be immutable (tuple, frozenset, MappingProxyType)"
                        if _UPPER_CASE.fullmatch(name)
                        else "module-level mutable state"
                    )
                    violations.append(
                        Violation(module.path, stmt.lineno, f"`{name}` = {container}: {kind}")
                    )
    return violations


# --------------------------------------------------------------------------------------
# Self-tests of the checker on synthetic sources
# --------------------------------------------------------------------------------------


def _fake(name: str, source: str, *, is_package: bool = False) -> Module:
    """A synthetic module named ``name`` with a path derived from it."""
    path = name.replace(".", "/") + ("/__init__.py" if is_package else ".py")
    return parse_module(name, source, path=path, is_package=is_package)


def test_checker_module_name() -> None:
    assert module_name(Path("octolgp/gp/kernels.py")) == ("octolgp.gp.kernels", False)
    assert module_name(Path("octolgp/gp/__init__.py")) == ("octolgp.gp", True)
    assert module_name(Path("octolgp/__init__.py")) == ("octolgp", True)


def test_checker_iter_imports_flags_and_relative() -> None:
    module = _fake(
        "octolgp.a.m",
        "from typing import TYPE_CHECKING\n"
        "import os, octolgp.b\n"
        "if TYPE_CHECKING:\n"
        "    from octolgp.c import C\n"
        "else:\n"
        "    from octolgp.d import D\n"
        "def f() -> None:\n"
        "    from . import sibling\n"
        "    from ..e import E\n",
    )
    refs = [(r.module, r.name, r.line, r.type_checking) for r in iter_imports(module)]
    assert refs == [
        ("typing", "TYPE_CHECKING", 1, False),
        ("os", None, 2, False),
        ("octolgp.b", None, 2, False),
        ("octolgp.c", "C", 4, True),
        ("octolgp.d", "D", 6, False),
        ("octolgp.a", "sibling", 8, False),
        ("octolgp.e", "E", 9, False),
    ]


def test_checker_detects_cycle_between_two_modules() -> None:
    modules = [
        _fake("octolgp.a", "from octolgp.b import g\n"),
        _fake("octolgp.b", "import os\n\ndef g() -> None:\n    from octolgp.a import f\n"),
    ]
    assert find_cycles(import_graph(modules)) == [["octolgp.a", "octolgp.b", "octolgp.a"]]
    (violation,) = check_import_cycles(modules)
    assert str(violation) == (
        "octolgp/a.py:1: import cycle: octolgp.a (octolgp/a.py:1) -> "
        "octolgp.b (octolgp/b.py:4) -> octolgp.a"
    )


def test_checker_detects_cycle_through_package_init() -> None:
    modules = [
        _fake("octolgp.p", "from octolgp.p.m import helper\nz = 1\n", is_package=True),
        _fake("octolgp.p.m", "from octolgp.p import z\n"),
        _fake("octolgp.p.n", "from octolgp.p import m\n"),  # a submodule: no edge to p
    ]
    graph = import_graph(modules)
    assert graph["octolgp.p.n"] == {"octolgp.p.m": 1}
    assert find_cycles(graph) == [["octolgp.p", "octolgp.p.m", "octolgp.p"]]


def test_checker_ignores_type_checking_imports_for_cycles() -> None:
    modules = [
        _fake("octolgp.a", "from octolgp.b import g\n"),
        _fake(
            "octolgp.b",
            "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from octolgp.a import f\n",
        ),
    ]
    assert check_import_cycles(modules) == []


def test_checker_finds_every_cycle_in_a_component() -> None:
    graph = {"a": {"b": 1}, "b": {"a": 1, "c": 1}, "c": {"b": 1}, "d": {"d": 1}}
    assert find_cycles(graph) == [["a", "b", "a"], ["b", "c", "b"]]


def test_checker_private_imports() -> None:
    modules = [
        _fake("octolgp.x", "_y = 1\n"),
        _fake("octolgp.p", "", is_package=True),
        _fake("octolgp.p._impl", ""),
        _fake("octolgp.p.m", "from octolgp.p import _impl\nfrom octolgp.x import __doc__\n"),
        _fake("octolgp.q", "from octolgp.x import _y as y, z\nfrom octolgp.p import _impl\n"),
        _fake("octolgp.r", "from numpy import _private\n"),
    ]
    assert [str(v) for v in check_private_imports(modules)] == [
        "octolgp/q.py:1: `from octolgp.x import _y`: private name of octolgp.x",
        "octolgp/q.py:2: `from octolgp.p import _impl`: private name of octolgp.p",
    ]


def test_checker_private_attributes() -> None:
    module = _fake(
        "octolgp.a",
        "class A:\n"
        "    def f(self, other: 'A') -> None:\n"
        "        self._x = other._x\n"
        "        np._core\n"
        "        self.__dict__\n"
        "    @classmethod\n"
        "    def g(cls) -> None:\n"
        "        cls._registry\n",
    )
    assert [str(v) for v in check_private_attributes([module])] == [
        "octolgp/a.py:3: `other._x`: private attribute of something not self/cls",
        "octolgp/a.py:4: `np._core`: private attribute of something not self/cls",
    ]
    allowed = frozenset({("octolgp/a.py", "_core")})
    assert len(check_private_attributes([module], allowed)) == 1


def test_checker_numerics_and_confined_dependencies() -> None:
    modules = [
        _fake(
            "octolgp.gp.kernels",
            "from typing import TYPE_CHECKING\n"
            "if TYPE_CHECKING:\n"
            "    from octolgp.mapping.online import OnlineMap\n"
            "from octolgp import sinks\n"
            "import octolgp.geometry.keys\n"
            "from octolgp.iox import X\n",
        ),
        _fake("octolgp.sinks.rerun", "import rerun as rr\n"),
        _fake("octolgp.sinks.rerun_sink", "import rerun.blueprint\n"),
        _fake("octolgp.sinks.null", "from rerun import components\n"),
        _fake("octolgp.io.rrd", "import rerun\n", is_package=True),
        _fake("octolgp.io.rrd.reader", "import rerun\n"),
        _fake("octolgp.io.carmen", "import rerun\nimport sqlite3\n"),
        _fake("octolgp.persist.sqlite", "import sqlite3\n"),
        _fake("octolgp.rerun_helpers", "import rerun\n"),
    ]
    assert [str(v) for v in check_numerics_independent(modules)] == [
        "octolgp/gp/kernels.py:3: `from octolgp.mapping.online import OnlineMap` "
        "(under TYPE_CHECKING): numerics -> octolgp.mapping",
        "octolgp/gp/kernels.py:4: `from octolgp import sinks`: numerics -> octolgp.sinks",
    ]
    assert [v.path for v in check_dependency_confined(modules, "rerun")] == [
        "octolgp/sinks/null.py",
        "octolgp/io/carmen.py",
        "octolgp/rerun_helpers.py",
    ]
    assert [v.path for v in check_dependency_confined(modules, "sqlite3")] == [
        "octolgp/io/carmen.py"
    ]


def test_checker_globals() -> None:
    module = _fake(
        "octolgp.a",
        "import logging\n"
        "from collections import defaultdict\n"
        "from types import MappingProxyType\n"
        "from typing import TypeAlias\n"
        "__all__ = ['x']\n"
        "logger = logging.getLogger(__name__)\n"
        "SIZES = (1, 2)\n"
        "NAMES = frozenset({'a'})\n"
        "TABLE = MappingProxyType({'a': 1})\n"
        "Alias: TypeAlias = list[int]\n"
        "_cache = {}\n"
        "LIMITS = [1, 2]\n"
        "seen: set[int] = set()\n"
        "a, b = [], 1\n"
        "c = d = {}\n"
        "try:\n"
        "    registry = defaultdict(list)\n"
        "except ImportError:\n"
        "    pass\n"
        "def f() -> None:\n"
        "    global _count\n"
        "    local = []\n",
    )
    assert [str(v) for v in check_globals([module])] == [
        "octolgp/a.py:21: `global _count`",
        "octolgp/a.py:11: `_cache` = dict display: module-level mutable state",
        "octolgp/a.py:12: `LIMITS` = list display: constant must be immutable "
        "(tuple, frozenset, MappingProxyType)",
        "octolgp/a.py:13: `seen` = set() call: module-level mutable state",
        "octolgp/a.py:14: `a` = list display: module-level mutable state",
        "octolgp/a.py:15: `c` = dict display: module-level mutable state",
        "octolgp/a.py:15: `d` = dict display: module-level mutable state",
        "octolgp/a.py:17: `registry` = defaultdict() call: module-level mutable state",
    ]


# --------------------------------------------------------------------------------------
# The rules, on the real package
# --------------------------------------------------------------------------------------


def test_package_is_found() -> None:
    names = {m.name for m in package_modules()}
    assert PACKAGE in names, f"no {PACKAGE}/__init__.py under {ROOT}"


def test_no_import_cycles() -> None:
    _fail_on("Rule 1 (no import cycles)", check_import_cycles(package_modules()))


def test_no_private_names_imported_across_modules() -> None:
    _fail_on(
        "Rule 2 (no `from octolgp.x import _private`)", check_private_imports(package_modules())
    )


def test_no_private_attributes_of_other_objects() -> None:
    _fail_on(
        "Rule 3 (private attributes only on self/cls)", check_private_attributes(package_modules())
    )


def test_numerics_do_not_import_the_application() -> None:
    _fail_on(
        f"Rule 4 ({', '.join(NUMERICS)} never import {', '.join(APPLICATION)})",
        check_numerics_independent(package_modules()),
    )


def test_rerun_only_in_its_adapters() -> None:
    _fail_on(
        "Rule 5 (rerun only in octolgp/sinks/*rerun* and octolgp/io/rrd*)",
        check_dependency_confined(package_modules(), "rerun"),
    )


def test_sqlite3_only_in_persist() -> None:
    _fail_on(
        "Rule 6 (sqlite3 only in octolgp/persist/)",
        check_dependency_confined(package_modules(), "sqlite3"),
    )


def test_engines_are_apart_and_behind_their_seam() -> None:
    _fail_on(
        "Rule 10 (leaf engines never import each other; the orchestrator imports only "
        "octolgp.engines and octolgp.engines.base)",
        check_engines_apart(package_modules()),
    )


def test_checker_engines_apart() -> None:
    lattice = _fake("octolgp.engines.lattice", "from octolgp.engines.exact import ExactEngine\n")
    online = _fake("octolgp.mapping.online", "from octolgp.engines.lattice import x\n")
    seam = _fake("octolgp.mapping.online", "from octolgp.engines import engine_for\n")
    own = _fake("octolgp.engines.lattice", "from octolgp.engines.base import Evidence\n")
    assert len(check_engines_apart([lattice])) == 1
    assert len(check_engines_apart([online])) == 1
    assert check_engines_apart([seam, own]) == []


def test_no_result_bearing_globals() -> None:
    _fail_on("Rule 7 (no result-bearing globals)", check_globals(package_modules()))


def _run_python(*args: str) -> subprocess.CompletedProcess[str]:
    """Run the test interpreter in a fresh process at the repository root."""
    return subprocess.run(
        [sys.executable, *args], cwd=ROOT, capture_output=True, text=True, timeout=300, check=False
    )


def test_import_octolgp_stays_light() -> None:
    probe = (
        f"import sys, octolgp; print(','.join(m for m in {HEAVY_MODULES!r} if m in sys.modules))"
    )
    result = _run_python("-c", probe)
    assert result.returncode == 0, f"`import octolgp` failed:\n{result.stderr}"
    assert result.stdout.strip() == "", (
        f"Rule 8: `import octolgp` loads {result.stdout.strip()}; import them lazily"
    )


@pytest.mark.parametrize("name", SUBPACKAGES)
def test_subpackage_exists(name: str) -> None:
    init = ROOT / PACKAGE / name / "__init__.py"
    assert init.is_file(), f"Rule 9: missing subpackage {PACKAGE}.{name} ({init.relative_to(ROOT)})"


@pytest.mark.parametrize("name", MODULES_OR_PACKAGES)
def test_module_or_package_exists(name: str) -> None:
    base = ROOT / PACKAGE / name
    assert base.with_suffix(".py").is_file() or (base / "__init__.py").is_file(), (
        f"Rule 9: missing {PACKAGE}.{name} (neither {name}.py nor {name}/__init__.py)"
    )


@pytest.mark.parametrize("name", TOP_LEVEL_MODULES)
def test_top_level_module_exists(name: str) -> None:
    path = ROOT / PACKAGE / f"{name}.py"
    assert path.is_file(), f"Rule 9: missing top-level module {path.relative_to(ROOT)}"


def test_py_typed_exists() -> None:
    assert (ROOT / PACKAGE / "py.typed").is_file(), "Rule 9: missing octolgp/py.typed (PEP 561)"


def test_python_m_octolgp_help() -> None:
    result = _run_python("-m", PACKAGE, "--help")
    assert result.returncode == 0, (
        f"Rule 9: `python -m {PACKAGE} --help` exited {result.returncode}:\n{result.stderr}"
    )
