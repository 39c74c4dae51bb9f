"""The layers hold, read from the source (nothing is imported): ``protocols/`` is sans-IO and
imports only the standard library, numpy and itself; ``emulators/`` never imports ``tcf_hil``;
``tcf_hil/`` may import anything declared; only command-line modules end the process; and
every third-party module imported anywhere in the three packages is declared in
pyproject.toml. Each failure lists the offending ``file:line``s."""

from __future__ import annotations

import ast
import re
import sys
import tomllib
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from functools import cache
from importlib.metadata import packages_distributions
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("protocols", "emulators", "tcf_hil")
STDLIB = frozenset(sys.stdlib_module_names)
FORBIDDEN_STDLIB = frozenset({"socket", "threading", "asyncio", "time", "subprocess", "select",
                              "selectors", "multiprocessing"})
"""Standard modules that do I/O, wait or run concurrently: not sans-IO, so not in protocols."""
ALIASES: dict[str, frozenset[str]] = {
    "can": frozenset({"python-can"}),
    "sklearn": frozenset({"scikit-learn"}),
    "open3d": frozenset({"open3d", "open3d-cpu"}),
    "ouster": frozenset({"ouster-sdk"}),
}
"""Import name -> distributions, for modules that may not be installed here (open3d-cpu has no
wheel off x86_64); installed ones are looked up with packages_distributions()."""
NOT_FOR_THE_PACKAGE = frozenset({"test"})
"""Extras that serve the test suite, not the package: importing one of their distributions
from tcf_hil/, emulators/ or protocols/ is undeclared."""
GUARD_EXCEPTIONS = frozenset({"ImportError", "ModuleNotFoundError", "Exception",
                              "BaseException"})


@dataclass(frozen=True)
class Import:
    """One import: ``module`` as written (relative ones resolved to their package), where."""

    where: str
    module: str
    lazy: bool  # inside a function: importing the module does not need it
    guarded: bool  # inside try/except ImportError (or broader) or contextlib.suppress
    names: tuple[str, ...] = ()  # what ``from module import ...`` takes
    typing_only: bool = False  # under ``if TYPE_CHECKING:``: never imported at run time

    @property
    def top(self) -> str:
        return self.module.split(".")[0]


@dataclass(frozen=True)
class Exit:
    where: str
    what: str


def _catches_import_errors(types: ast.expr | None) -> bool:
    if types is None:  # a bare except
        return True
    exprs = types.elts if isinstance(types, ast.Tuple) else [types]
    return any(isinstance(e, ast.Name | ast.Attribute)
               and (e.id if isinstance(e, ast.Name) else e.attr) in GUARD_EXCEPTIONS
               for e in exprs)


def _private(name: str) -> bool:
    return name.startswith("_") and not name.startswith("__")


def _call_name(func: ast.expr) -> str:
    """``a.b.c`` for a called name (``""`` for anything else)."""
    parts: list[str] = []
    while isinstance(func, ast.Attribute):
        parts.append(func.attr)
        func = func.value
    if not isinstance(func, ast.Name):
        return ""
    return ".".join([func.id, *reversed(parts)])


class _Scanner(ast.NodeVisitor):
    def __init__(self, rel: str, package: str) -> None:
        self.rel, self.package = rel, package
        self.imports: list[Import] = []
        self.exits: list[Exit] = []
        self.attributes: list[tuple[str, str, str]] = []  # (where, alias, attribute)
        self.aliases: dict[str, str] = {}  # a name bound by an import -> what it names
        self._depth = 0  # functions around the node
        self._guards = 0  # import guards around the node
        self._typing = 0  # ``if TYPE_CHECKING:`` blocks around the node

    def _add(self, node: ast.AST, module: str, names: tuple[str, ...] = ()) -> None:
        self.imports.append(Import(f"{self.rel}:{getattr(node, 'lineno', 0)}", module,
                                   self._depth > 0, self._guards > 0, names,
                                   self._typing > 0))

    def visit_If(self, node: ast.If) -> None:
        typing = "TYPE_CHECKING" in ast.unparse(node.test)
        self.visit(node.test)
        self._typing += typing
        for stmt in node.body:
            self.visit(stmt)
        self._typing -= typing
        for stmt in node.orelse:
            self.visit(stmt)

    def visit_Attribute(self, node: ast.Attribute) -> None:
        if isinstance(node.value, ast.Name) and _private(node.attr):
            self.attributes.append((f"{self.rel}:{node.lineno}", node.value.id, node.attr))
        self.generic_visit(node)

    def _function(self, node: ast.FunctionDef | ast.AsyncFunctionDef | ast.Lambda) -> None:
        self._depth += 1
        self.generic_visit(node)
        self._depth -= 1

    visit_FunctionDef = visit_AsyncFunctionDef = visit_Lambda = _function  # noqa: N815

    def _try(self, node: ast.Try | ast.TryStar) -> None:
        guard = any(_catches_import_errors(h.type) for h in node.handlers)
        self._guards += guard
        for stmt in node.body:
            self.visit(stmt)
        self._guards -= guard
        for other in [*node.handlers, *node.orelse, *node.finalbody]:
            self.visit(other)

    visit_Try = visit_TryStar = _try  # noqa: N815

    def visit_With(self, node: ast.With) -> None:
        guard = any(isinstance(i.context_expr, ast.Call)
                    and _call_name(i.context_expr.func).split(".")[-1] == "suppress"
                    and any(_catches_import_errors(a) for a in i.context_expr.args)
                    for i in node.items)
        self._guards += guard
        self.generic_visit(node)
        self._guards -= guard

    def visit_Import(self, node: ast.Import) -> None:
        for alias in node.names:
            self._add(node, alias.name)
            if alias.asname:
                self.aliases[alias.asname] = alias.name

    def visit_ImportFrom(self, node: ast.ImportFrom) -> None:
        names = tuple(a.name for a in node.names)
        if node.level:  # relative: inside this file's own package
            module = ".".join(filter(None, [self.package, node.module]))
        elif node.module:
            module = node.module
        else:
            return
        self._add(node, module, names)
        for a in node.names:
            self.aliases[a.asname or a.name] = f"{module}.{a.name}"

    def visit_Call(self, node: ast.Call) -> None:
        name = _call_name(node.func)
        if (name.split(".")[-1] in ("import_module", "__import__") and node.args
                and isinstance(node.args[0], ast.Constant)
                and isinstance(node.args[0].value, str)):
            self._add(node, node.args[0].value)
        if name in ("sys.exit", "exit", "quit"):
            self.exits.append(Exit(f"{self.rel}:{node.lineno}", f"{name}("))
        self.generic_visit(node)

    def visit_Raise(self, node: ast.Raise) -> None:
        exc = node.exc.func if isinstance(node.exc, ast.Call) else node.exc
        if exc is not None and _call_name(exc).split(".")[-1] == "SystemExit":
            self.exits.append(Exit(f"{self.rel}:{node.lineno}", "raise SystemExit"))
        self.generic_visit(node)


def scan(path: Path, root: Path = ROOT) -> _Scanner:
    rel = path.relative_to(root).as_posix()
    scanner = _Scanner(rel, rel.split("/")[0])
    scanner.visit(ast.parse(path.read_text(encoding="utf-8"), filename=rel))
    return scanner


def files(*packages: str) -> Iterator[Path]:
    for package in packages:
        found = sorted((ROOT / package).rglob("*.py"))
        assert found, f"no Python files under {package}/"
        yield from found


def all_imports(*packages: str) -> list[Import]:
    return [i for f in files(*packages) for i in scan(f).imports]


def _fail(offenders: list[str], what: str) -> None:
    if offenders:
        pytest.fail(f"{what}:\n  " + "\n  ".join(offenders), pytrace=False)


# ---------------------------------------------------------------------------------------------
# what pyproject.toml declares
# ---------------------------------------------------------------------------------------------
def _normalize(name: str) -> str:
    return re.sub(r"[-_.]+", "-", name).lower()


def _requirement_name(req: str) -> str:
    m = re.match(r"\s*([A-Za-z0-9][A-Za-z0-9._-]*)", req)
    assert m, f"cannot read the requirement {req!r}"
    return _normalize(m[1])


def declared() -> dict[str, bool]:
    """Distributions the package may import -> True where always installed (a dependency
    without an environment marker), False where only sometimes (a marker, or an extra)."""
    project = tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))["project"]
    own = _normalize(project["name"])
    out: dict[str, bool] = {}
    for req in project["dependencies"]:
        out[_requirement_name(req)] = ";" not in req
    for extra, reqs in project.get("optional-dependencies", {}).items():
        if extra in NOT_FOR_THE_PACKAGE:
            continue
        for req in reqs:
            name = _requirement_name(req)
            if name != own:
                out.setdefault(name, False)
    return out


@cache
def _installed() -> Mapping[str, list[str]]:
    return packages_distributions()


def distributions_of(module: str) -> set[str]:
    """The distributions that may provide top-level ``module``."""
    names = {module, *ALIASES.get(module, ()), *_installed().get(module, ())}
    return {_normalize(n) for n in names}


# ---------------------------------------------------------------------------------------------
# the layers
# ---------------------------------------------------------------------------------------------
def test_protocols_import_only_the_stdlib_numpy_and_themselves() -> None:
    allowed = (STDLIB - FORBIDDEN_STDLIB) | {"numpy", "protocols"}
    _fail([f"{i.where} imports {i.module}" for i in all_imports("protocols")
           if i.top not in allowed],
          "protocols/ is sans-IO: stdlib (no I/O, threads or clocks), numpy and protocols only")


def test_emulators_never_import_tcf_hil() -> None:
    _fail([f"{i.where} imports {i.module}" for i in all_imports("emulators")
           if i.top == "tcf_hil"],
          "emulators/ may import protocols, the stdlib and declared packages, never tcf_hil")


def test_every_third_party_import_is_declared() -> None:
    """tcf_hil/ may import anything, emulators/ anything but tcf_hil, as long as it is declared;
    a distribution installed only sometimes (an extra, or a platform marker) is imported only
    inside a function or under an import guard, so that importing the package never needs
    it."""
    deps = declared()
    first_party = set(PACKAGES)
    bad: list[str] = []
    for i in all_imports(*PACKAGES):
        if i.top in STDLIB or i.top in first_party:
            continue
        dists = distributions_of(i.top) & deps.keys()
        if not dists:
            bad.append(f"{i.where} imports {i.module}, which no dependency in pyproject.toml "
                       f"provides (looked for {sorted(distributions_of(i.top))})")
        elif not any(deps[d] for d in dists) and not (i.lazy or i.guarded):
            bad.append(f"{i.where} imports {i.module} at module level, but "
                       f"{'/'.join(sorted(dists))} is not always installed (an extra or a "
                       "platform marker): import it inside a function or guard it")
    _fail(bad, "undeclared third-party imports")


def private_owner(module: str, name: str | None = None, root: Path = ROOT) -> str | None:
    """The package directory (``a/b``) that owns a private module (``a.b._c``) or a private
    name (``from a.b.c import _x``: the package of ``a.b.c``), or None where nothing private
    is taken. Only files under the owner may take it."""
    parts = module.split(".")
    for i, part in enumerate(parts):
        if part.startswith("_") and not part.startswith("__"):
            return "/".join(parts[:i])
    if name is not None and name.startswith("_") and not name.startswith("__"):
        where = root.joinpath(*parts)
        return "/".join(parts if where.is_dir() else parts[:-1])
    return None


def test_no_module_takes_another_packages_private_names() -> None:
    """``a.b._c`` and ``from a.b import _x`` are private to ``a/b/``: a module elsewhere takes
    what the package exports instead (tests may reach in; they are not scanned)."""
    bad: list[str] = []
    for i in all_imports(*PACKAGES):
        if i.top not in PACKAGES:
            continue
        for name in (None, *i.names):
            owner = private_owner(i.module, name)
            if owner is not None and not i.where.startswith(owner + "/"):
                bad.append(f"{i.where} takes {i.module}{'' if name is None else ':' + name}, "
                           f"private to {owner}/")
    _fail(bad, "private names taken from outside their package")


def test_private_owners() -> None:
    assert private_owner("tcf_hil._io") == "tcf_hil"
    assert private_owner("emulators.lidar._os0", "FastRayScene") == "emulators/lidar"
    assert private_owner("protocols.ouster", "_table") == "protocols/ouster"
    assert private_owner("protocols.ouster.x", "_table") == "protocols/ouster"
    assert private_owner("protocols.ouster", "PROFILES") is None
    assert private_owner("__future__", "annotations") is None


def is_cli(rel: str) -> bool:
    parts = rel.split("/")
    return (parts[:2] == ["tcf_hil", "cli"] or rel == "tcf_hil/cli.py"
            or parts[-1] in ("_cli.py", "__main__.py"))


def test_only_command_line_modules_end_the_process() -> None:
    """A library raises its documented errors; only the CLI (tcf_hil/cli/, tcf_hil/cli.py,
    any _cli.py or __main__.py) turns them into exit statuses. benchmarks/ and .ci/ are
    scripts and not scanned."""
    bad = [f"{e.where}: {e.what}" for f in files(*PACKAGES) for e in scan(f).exits
           if not is_cli(e.where.rsplit(":", 1)[0])]
    _fail(bad, "the process is ended outside a command-line module")


# ---------------------------------------------------------------------------------------------
# the architecture: subsystems in order, no circles, no private names across modules
# ---------------------------------------------------------------------------------------------
SUBSYSTEMS = ("scenario", "world", "recording", "evaluation", "devices", "results", "run", "sic",
              "experiments", "cli")
"""tcf_hil's subsystems, each importing only those before it (and the helpers); the SIC, an
outside program, imports none of them (:data:`SIC_MAY_IMPORT`)."""
HELPERS = frozenset({"errors", "_io", "_crc", "_rotations", "_plots", "_logs"})
"""Small shared modules any subsystem may import; they import no subsystem."""
SIC_MAY_IMPORT = HELPERS - {"_io", "_plots", "_logs"}
"""The reference SIC is an outside program: its own package, protocols, emulators' kernels and
the errors, CRC and rotations (its rules in the issue that made it field-grade)."""


def module_name(path: Path, root: Path = ROOT) -> str:
    parts = list(path.relative_to(root).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


@cache
def module_files() -> dict[str, Path]:
    return {module_name(f): f for f in files(*PACKAGES)}


def _target(name: str, mods: Mapping[str, Path]) -> str | None:
    while name and name not in mods:
        name = name.rpartition(".")[0]
    return name or None


def import_graph() -> dict[str, dict[str, str]]:
    """module -> {imported module: where} for every import that can run (at the top of a file
    or inside a function; ``if TYPE_CHECKING:`` blocks never run), a ``from package import
    module`` pointing at the module."""
    mods = module_files()
    graph: dict[str, dict[str, str]] = {}
    for m, f in mods.items():
        out = graph.setdefault(m, {})
        for i in scan(f).imports:
            if i.top not in PACKAGES or i.typing_only:
                continue
            subs = [f"{i.module}.{n}" for n in i.names if f"{i.module}.{n}" in mods]
            for t in subs or [_target(i.module, mods)]:
                if t is not None and t != m:
                    out.setdefault(t, i.where)
    return graph


def circles(graph: Mapping[str, Mapping[str, str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    found: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in graph.get(v, {}):
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
                found.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return found


def test_no_import_circles() -> None:
    """No module imports, directly or through others, a module that imports it back (lazy
    imports inside functions count: a circle broken only by import order is still one)."""
    graph = import_graph()
    bad = []
    for comp in circles(graph):
        arrows = [f"{a} -> {b} ({graph[a][b]})" for a in comp for b in graph[a] if b in comp]
        bad.append(" <-> ".join(comp) + ":\n      " + "\n      ".join(arrows))
    _fail(bad, "import circles")


def subsystem(module: str) -> str:
    parts = module.split(".")
    return parts[1] if parts[0] == "tcf_hil" and len(parts) > 1 else parts[0]


def test_subsystems_import_only_those_below_them() -> None:
    """Each subsystem of tcf_hil imports only the subsystems listed before it in
    :data:`SUBSYSTEMS`, the helpers, protocols and emulators; a helper imports no subsystem;
    the SIC only :data:`SIC_MAY_IMPORT`. Every package under tcf_hil/ is one of them."""
    known = set(SUBSYSTEMS) | HELPERS | {"__init__", "__main__"}
    pkgs = {p.name for p in (ROOT / "tcf_hil").iterdir()
            if p.suffix == ".py" or (p / "__init__.py").exists()}
    bad = [f"tcf_hil/{p}: not a subsystem in SUBSYSTEMS nor a helper in HELPERS"
           for p in sorted(pkgs - {f"{k}.py" for k in known} - known)]
    for m, targets in import_graph().items():
        if not m.startswith("tcf_hil."):
            continue
        a = subsystem(m)
        if a in ("__main__",):
            continue
        for t, where in targets.items():
            b = subsystem(t)
            if b in ("protocols", "emulators") or b == a or t == "tcf_hil":
                continue
            if a == "sic":
                ok = b in SIC_MAY_IMPORT
            elif a in HELPERS:
                ok = b in HELPERS
            elif b in HELPERS:
                ok = True
            else:
                ok = (a in SUBSYSTEMS and b in SUBSYSTEMS
                      and SUBSYSTEMS.index(b) < SUBSYSTEMS.index(a))
            if not ok:
                bad.append(f"{where}: {m} ({a}) imports {t} ({b})")
    _fail(bad, "imports that run back up the subsystems' order")


def test_every_subsystem_says_what_it_owns() -> None:
    bad = []
    for p in sorted((ROOT / "tcf_hil").iterdir()):
        init = p / "__init__.py"
        if init.exists():
            doc = ast.get_docstring(ast.parse(init.read_text(encoding="utf-8"))) or ""
            if len(doc.split()) < 12:
                bad.append(f"{init.relative_to(ROOT)}: no docstring saying what it owns")
    _fail(bad, "subsystems without a docstring")


def test_no_module_takes_another_modules_private_names() -> None:
    """``from a.b import _x`` and ``b._x`` (``b`` an imported module) reach into a module's
    privates; a module takes only public names from another (tests may reach in)."""
    mods = module_files()
    bad: list[str] = []
    for m, f in mods.items():
        s = scan(f)
        for i in s.imports:
            if i.top not in PACKAGES:
                continue
            bad += [f"{i.where} takes {i.module}:{n}" for n in i.names
                    if _private(n) and f"{i.module}.{n}" not in mods and i.module != m]
        for where, alias, attr in s.attributes:
            target = s.aliases.get(alias)
            if target in mods and target != m:
                bad.append(f"{where} takes {target}.{attr}")
    _fail(bad, "private names taken from another module")


# ---------------------------------------------------------------------------------------------
# the checks themselves
# ---------------------------------------------------------------------------------------------
def test_the_scanner_sees_every_form_of_import_and_exit(tmp_path: Path) -> None:
    pkg = tmp_path / "emulators"
    pkg.mkdir()
    f = pkg / "x.py"
    f.write_text(
        "import socket\n"
        "from can import Bus\n"
        "from . import sibling\n"
        "from .sub import thing\n"
        "import importlib\n"
        "try:\n"
        "    import open3d\n"
        "except ImportError:\n"
        "    open3d = None\n"
        "def f():\n"
        "    import tcf_hil.world.forest\n"
        "    importlib.import_module('tcf_hil.world.scene')\n"
        "    with contextlib.suppress(Exception):\n"
        "        from threadpoolctl import threadpool_limits\n"
        "    try:\n"
        "        sys.exit(2)\n"
        "    except (SystemExit, OSError):\n"
        "        raise SystemExit('no')\n"
        "    exit(1)\n"
        "    raise SystemExit\n")
    s = scan(f, tmp_path)
    assert {i.top for i in s.imports} == {"socket", "can", "emulators", "importlib", "open3d",
                                          "tcf_hil", "threadpoolctl"}
    got = {(i.module, i.where.split(":")[1], i.lazy, i.guarded) for i in s.imports}
    assert ("emulators.sub", "4", False, False) in got
    assert ("open3d", "7", False, True) in got
    assert ("tcf_hil.world.forest", "11", True, False) in got
    assert ("tcf_hil.world.scene", "12", True, False) in got
    assert ("threadpoolctl", "14", True, True) in got
    assert [(e.where, e.what) for e in s.exits] == [
        ("emulators/x.py:16", "sys.exit("), ("emulators/x.py:18", "raise SystemExit"),
        ("emulators/x.py:19", "exit("), ("emulators/x.py:20", "raise SystemExit")]


def test_the_declared_distributions_are_read_with_their_markers_and_extras() -> None:
    deps = declared()
    assert deps["numpy"] is True and deps["python-can"] is True and deps["dask"] is True
    assert deps["embreex"] is False  # x86_64 only
    assert deps["open3d-cpu"] is False  # the [open3d] extra
    assert deps["ouster-sdk"] is False  # the [osf] extra (the test suite has it too)
    assert "pytest" not in deps  # the test suite's, not ours
    assert "tcf-hil" not in deps
    assert {"python-can"} <= distributions_of("can")
    assert {"open3d-cpu"} <= distributions_of("open3d")


@pytest.mark.parametrize(("rel", "cli"), [
    ("tcf_hil/cli.py", True), ("tcf_hil/cli/run.py", True), ("tcf_hil/sic/_cli.py", True),
    ("tcf_hil/__main__.py", True), ("tcf_hil/sic/__main__.py", True),
    ("tcf_hil/sic/_online.py", False), ("tcf_hil/client.py", False),
    ("emulators/canbus/_socketcand.py", False)])
def test_command_line_modules_are_recognised(rel: str, cli: bool) -> None:
    assert is_cli(rel) is cli
