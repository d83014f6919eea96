"""The import rules ARCHITECTURE.md states, checked on the source (every import statement, at
module level or inside a function): the layers, no service importing another, nothing importing
a program, no import circle, no fixture of the tests in the product."""

from __future__ import annotations

import ast
import re
from collections.abc import Iterator
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("protocol", "mesh", "services", "apps", "sim")
SERVICES = ("robot", "camera", "detector", "controller", "learner")
THIRD_PARTY_NOT_IN_PROTOCOL = ("zenoh", "argparse", "subprocess", "socket", "threading")


def _modules() -> dict[str, Path]:
    out: dict[str, Path] = {}
    for package in PACKAGES:
        for path in sorted((ROOT / package).rglob("*.py")):
            parts = path.relative_to(ROOT).with_suffix("").parts
            name = ".".join(["archery", *(parts[:-1] if parts[-1] == "__init__" else parts)])
            out[name] = path
    return out


MODULES = _modules()


def _imports(name: str, path: Path) -> Iterator[str]:
    """Every module this one imports (absolute names; `from P import M` as P.M where M is a
    module), in any scope."""
    is_package = path.name == "__init__.py"
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            yield from (alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = name.split(".")
                anchor = anchor[: len(anchor) - node.level + (1 if is_package else 0)]
                base = ".".join([*anchor, base] if base else anchor)
            for alias in node.names:
                full = f"{base}.{alias.name}"
                yield full if full in MODULES else base


def _ours(imported: str) -> str | None:
    """The module of ours an import names (the longest known prefix), or None."""
    parts = imported.split(".")
    for k in range(len(parts), 0, -1):
        candidate = ".".join(parts[:k])
        if candidate in MODULES:
            return candidate
    return None


GRAPH = {
    name: {m for m in map(_ours, _imports(name, path)) if m is not None and m != name}
    for name, path in MODULES.items()
}


def _layer(module: str) -> str:
    """The folder a module of ours is in (`archery.LAYER...`)."""
    return module.split(".")[1]


def test_the_contract_imports_only_itself_and_does_no_io() -> None:
    for name, path in MODULES.items():
        if _layer(name) != "protocol":
            continue
        assert {_layer(m) for m in GRAPH[name]} <= {"protocol"}, (name, GRAPH[name])
        imported = set(_imports(name, path))
        bad = {i for i in imported if i.split(".")[0] in THIRD_PARTY_NOT_IN_PROTOCOL}
        assert not bad, (name, bad)


def test_the_runtime_imports_only_the_contract() -> None:
    for name in MODULES:
        if _layer(name) == "mesh":
            assert {_layer(m) for m in GRAPH[name]} <= {"protocol", "mesh"}, (name, GRAPH[name])


def test_sim_imports_only_the_contract() -> None:
    for name in MODULES:
        if _layer(name) == "sim":
            assert {_layer(m) for m in GRAPH[name]} <= {"protocol", "sim"}, (name, GRAPH[name])


def test_services_are_exactly_five_and_never_import_each_other_or_a_program() -> None:
    packages = {p.name for p in (ROOT / "services").iterdir() if (p / "__init__.py").is_file()}
    assert packages == set(SERVICES)
    assert {p.name for p in (ROOT / "services").glob("*.py")} == {"__init__.py"}
    for name in MODULES:
        if _layer(name) != "services" or name == "archery.services":
            continue
        own = name.split(".")[2]
        for imported in GRAPH[name]:
            layer = _layer(imported)
            assert layer in ("protocol", "mesh", "sim", "services"), (name, imported)
            if layer == "services":
                assert imported.split(".")[2] == own, (name, imported)
            if layer == "sim":  # physics for the robot and camera, the analytic model
                assert own in ("robot", "camera", "learner"), (name, imported)


def test_nothing_imports_a_program() -> None:
    for name in MODULES:
        if _layer(name) != "apps":
            assert not {m for m in GRAPH[name] if _layer(m) == "apps"}, (name, GRAPH[name])


def _cycle_from(start: str) -> list[str] | None:
    stack = [(start, [start])]
    seen: set[str] = set()
    while stack:
        node, path = stack.pop()
        for nxt in GRAPH[node]:
            if nxt == start:
                return path
            if nxt not in seen:
                seen.add(nxt)
                stack.append((nxt, [*path, nxt]))
    return None


def _is_package_of(a: str, b: str) -> bool:
    return b.startswith(a + ".")


def test_no_import_circles() -> None:
    """No module reaches itself through its imports (a package's `__init__` importing its own
    modules is not a circle of theirs)."""
    circles = []
    for name in MODULES:
        cycle = _cycle_from(name)
        if cycle and not any(_is_package_of(m, name) or _is_package_of(name, m) for m in cycle):
            circles.append(" → ".join([*cycle, name]))
    assert not circles, "\n".join(circles)


def _python_files() -> Iterator[Path]:
    """Every Python file of the repository: the product, the tests, the benchmarks, docker/."""
    for folder in (*PACKAGES, "tests", "benchmarks", "docker"):
        yield from sorted((ROOT / folder).rglob("*.py"))


def test_everything_imports_the_product_by_its_one_name() -> None:
    """The distribution installs one import name, `archery`: every import of the product, in
    the product, the tests and the benchmarks, goes through it (a top-level `protocol`,
    `services` … is not installed)."""
    old = []
    for path in _python_files():
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Import):
                names = [alias.name for alias in node.names]
            elif isinstance(node, ast.ImportFrom) and not node.level:
                names = [node.module or ""]
            else:
                continue
            old += [f"{path.relative_to(ROOT)}: {n}" for n in names if n.split(".")[0] in PACKAGES]
    assert not old, "\n".join(old)


def test_the_import_package_links_each_folder() -> None:
    """`archery/` holds the package's `__init__.py` and one link per product folder, so the
    repository keeps its top-level folders and installs them as `archery.FOLDER`."""
    package = ROOT / "archery"
    assert {p.name for p in package.iterdir() if p.name != "__pycache__"} == {
        "__init__.py",
        *PACKAGES,
    }
    for name in PACKAGES:
        link = package / name
        assert link.is_symlink() and link.resolve() == (ROOT / name).resolve(), name


def test_no_test_fixture_in_the_product() -> None:
    for name, path in MODULES.items():
        text = path.read_text()
        assert not re.search(r"^(from|import) (tests|benchmarks)\b", text, re.M), name


def test_no_module_re_exports_another_modules_names() -> None:
    """A name is imported from the module that defines it: no module lists in `__all__` a name
    it imports from another module of ours (a package's `__init__`, its public face, aside)."""
    shims = []
    for name, path in MODULES.items():
        if path.name == "__init__.py":
            continue
        tree = ast.parse(path.read_text())
        exported: set[str] = set()
        imported: set[str] = set()
        for node in tree.body:
            if isinstance(node, ast.Assign) and any(
                isinstance(t, ast.Name) and t.id == "__all__" for t in node.targets
            ):
                exported = {e.value for e in node.value.elts if isinstance(e, ast.Constant)}
            if isinstance(node, ast.ImportFrom) and (node.module or "").startswith("archery."):
                imported |= {alias.asname or alias.name for alias in node.names}
        if exported & imported:
            shims.append(f"{name}: {sorted(exported & imported)}")
    assert not shims, "\n".join(shims)


RENDERING_VARIABLES = ("MUJOCO_GL", "PYOPENGL_PLATFORM")


def _names_a_rendering_variable(path: Path) -> bool:
    """Whether the module's code (not its docstrings or comments) holds a rendering variable's
    name as a string: the only way to set, read or remove it."""
    tree = ast.parse(path.read_text())
    docstrings = {
        id(node.body[0].value)
        for node in ast.walk(tree)
        if isinstance(node, ast.Module | ast.ClassDef | ast.FunctionDef | ast.AsyncFunctionDef)
        and node.body
        and isinstance(node.body[0], ast.Expr)
        and isinstance(node.body[0].value, ast.Constant)
    }
    return any(
        isinstance(node, ast.Constant)
        and isinstance(node.value, str)
        and id(node) not in docstrings
        and any(variable in node.value for variable in RENDERING_VARIABLES)
        for node in ast.walk(tree)
    )


def test_the_rendering_backend_is_picked_in_one_place() -> None:
    """`sim.gl_backend` alone reads and sets MUJOCO_GL and PYOPENGL_PLATFORM; every MuJoCo
    renderer is made by `sim.render.SceneRenderer` (which readies the backend first)."""
    for name, path in MODULES.items():
        if name != "archery.sim.gl_backend":
            assert not _names_a_rendering_variable(path), name
        if name != "archery.sim.render":
            text = path.read_text()
            assert not re.search(r"\bmujoco\.(Renderer|GLContext)\b", text), name


def test_no_test_sets_the_rendering_variables() -> None:
    """The suite runs in what a user's shell has: conftest removes the rendering variables
    before anything is imported, and no test module sets them; the one exception is the test of
    the backend's choice, which gives them to a child process as a user's shell would."""
    allowed = {"conftest.py", "test_gl_backend.py", "test_architecture.py"}
    for path in sorted((ROOT / "tests").rglob("*.py")):
        if path.name not in allowed:
            assert not _names_a_rendering_variable(path), path.name


def test_every_file_the_map_names_exists() -> None:
    """ARCHITECTURE.md's paths (the life of one θ above all) name files that exist."""
    text = (ROOT / "ARCHITECTURE.md").read_text()
    # (a path with a capital is a pattern, e.g. `protocol/verbs/NAME.py`)
    pattern = r"`((?:protocol|mesh|services|sim|apps|tests|benchmarks)/[a-z0-9_/]+\.py)`"
    named = set(re.findall(pattern, text))
    assert len(named) > 20
    missing = sorted(path for path in named if not (ROOT / path).is_file())
    assert not missing, f"ARCHITECTURE.md names files that do not exist: {missing}"


MODULE_DOCSTRING_LINES = 12


def test_every_module_opens_with_a_short_docstring() -> None:
    """Every product module opens with a docstring of a few lines that says what it holds (at
    most 12, its first and last line counted); the details go to the docstrings of the classes
    and functions they explain, the tables to README.md and ARCHITECTURE.md."""
    missing = []
    too_long = []
    for path in sorted(MODULES.values()):
        shown = str(path.relative_to(ROOT))
        docstring = ast.get_docstring(ast.parse(path.read_text()), clean=False)
        if docstring is None or not docstring.strip():
            missing.append(shown)
        elif (lines := docstring.count("\n") + 1) > MODULE_DOCSTRING_LINES:
            too_long.append(f"{shown} ({lines} lines)")
    assert not missing, f"modules without a docstring: {', '.join(missing)}"
    assert not too_long, (
        f"module docstrings over {MODULE_DOCSTRING_LINES} lines: {', '.join(too_long)}"
    )
