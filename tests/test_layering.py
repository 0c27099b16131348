"""The engine knows nothing of Zenoh, HTTP or the service (docs/architecture.md, "Two halves"): no
engine module imports a service module, zenoh, the web stack or sqlite3, neither in its source nor
through what it imports at run time."""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import fleetmap

PACKAGE = Path(__file__).resolve().parent.parent / "service" / "fleetmap"

#: The engine, as docs/architecture.md's table lists it: these modules and every module of these
#: packages (a new kernel, reader or example is checked without being added here).
ENGINE_MODULES = (
    "scan",
    "config",
    "cell_queries",
    "tiles",
    "update_plan",
    "grid_map",
    "export",
    "upload_spool",
    "yaml_whitespace",
    "nav2_import",
)
ENGINE_PACKAGES = ("kernels", "datasets", "sim", "examples")

#: Third-party modules of the service's edges: the wire (zenoh), HTTP (the web stack) and storage.
FORBIDDEN_TOP_LEVEL = frozenset(
    {"zenoh", "fastapi", "starlette", "uvicorn", "httpx", "prometheus_client", "sqlite3"}
)

#: Service modules an engine module may name under `if TYPE_CHECKING:` only (a type, never loaded).
TYPE_ONLY = frozenset({"fleetmap.memory_budget"})


def _engine_files() -> dict[str, Path]:
    """Module name -> file, for the package's `__init__` (the engine's public names) and the engine."""
    files = {"fleetmap": PACKAGE / "__init__.py"}
    files.update({f"fleetmap.{name}": PACKAGE / f"{name}.py" for name in ENGINE_MODULES})
    for package in ENGINE_PACKAGES:
        for path in sorted((PACKAGE / package).glob("*.py")):
            module = f"fleetmap.{package}" if path.stem == "__init__" else f"fleetmap.{package}.{path.stem}"
            files[module] = path
    return files


def _is_engine(module: str) -> bool:
    parts = module.split(".")
    return module == "fleetmap" or (
        parts[0] == "fleetmap" and (parts[1] in ENGINE_MODULES or parts[1] in ENGINE_PACKAGES)
    )


def _type_checking_nodes(tree: ast.AST) -> set[ast.AST]:
    """The import statements inside `if TYPE_CHECKING:` blocks."""
    inside: set[ast.AST] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.If) and ast.unparse(node.test).endswith("TYPE_CHECKING"):
            for child in node.body:
                inside.update(n for n in ast.walk(child) if isinstance(n, ast.Import | ast.ImportFrom))
    return inside


def _imports(module: str, path: Path) -> list[tuple[str, bool, int]]:
    """(module imported, whether under TYPE_CHECKING, line) for every import in the file, at any
    depth (an import inside a function loads the module too), relative ones resolved. Each name of
    a `from fleetmap import ...` is the module it names, or for a public name the module defining it."""
    tree = ast.parse(path.read_text(), filename=str(path))
    typing_only = _type_checking_nodes(tree)
    package = module if path.stem == "__init__" else module.rpartition(".")[0]
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found += [(alias.name, node in typing_only, node.lineno) for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = package.split(".")[: len(package.split(".")) - (node.level - 1)]
                base = ".".join([*anchor, base] if base else anchor)
            if base == "fleetmap":
                found += [
                    (
                        fleetmap._EXPORTS.get(alias.name, f"fleetmap.{alias.name}"),
                        node in typing_only,
                        node.lineno,
                    )
                    for alias in node.names
                ]
            else:
                found.append((base, node in typing_only, node.lineno))
    return found


def test_engine_sources_import_no_service_module_and_no_transport() -> None:
    """Every import statement of every engine module, functions' included."""
    files = _engine_files()
    assert len(files) > len(ENGINE_MODULES) + len(ENGINE_PACKAGES), files
    wrong = []
    for module, path in files.items():
        for imported, typing_only, line in _imports(module, path):
            top = imported.split(".")[0]
            if top in FORBIDDEN_TOP_LEVEL:
                wrong.append(f"{path.name}:{line} imports {imported}")
            elif (
                top == "fleetmap" and not _is_engine(imported) and not (typing_only and imported in TYPE_ONLY)
            ):
                wrong.append(f"{path.name}:{line} imports the service module {imported}")
    assert wrong == []


def test_importing_the_whole_engine_loads_no_service_module_and_no_transport() -> None:
    """At run time, in a fresh interpreter: what the engine's imports load in turn counts too."""
    modules = sorted(_engine_files())
    code = (
        "import importlib, sys\n"
        f"for name in {modules!r}:\n"
        "    importlib.import_module(name)\n"
        "print('\\n'.join(sorted(sys.modules)))\n"
    )
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert result.returncode == 0, result.stderr
    loaded = result.stdout.split()
    transports = sorted(m for m in loaded if m.split(".")[0] in FORBIDDEN_TOP_LEVEL)
    service = sorted(m for m in loaded if m.split(".")[0] == "fleetmap" and not _is_engine(m))
    assert transports == []
    assert service == []


def test_the_rest_client_loads_no_service_runtime() -> None:
    """`fleetmap_client.rest` parses answers with `fleetmap.api_models`, whose conversions take the
    registry's types: those are type-only imports, so a client program loads neither the registry,
    its queue, journal and storage, nor Zenoh or the web stack."""
    code = "import sys, fleetmap_client.rest\nprint('\\n'.join(sorted(sys.modules)))\n"
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert result.returncode == 0, result.stderr
    loaded = result.stdout.split()
    service_runtime = {
        "fleetmap.registry", "fleetmap.fair_queue", "fleetmap.journal", "fleetmap.persistence",
        "fleetmap.database", "fleetmap.zenoh_ingest", "fleetmap.server", "fleetmap.serve_options",
        "fleetmap.serve_environment", "fleetmap.serve_ros", "fleetmap.http_server", "fleetmap.warm_up",
        "fleetmap.api",
    }  # fmt: skip
    assert sorted(m for m in loaded if m.split(".")[0] in FORBIDDEN_TOP_LEVEL - {"httpx"}) == []
    assert sorted(m for m in loaded if m in service_runtime) == []


def test_the_rest_client_and_the_api_models_load_no_numba() -> None:
    """A program that only talks to the REST API loads neither numba nor the engine's kernels: the
    client and the models take the ray limits, code names and point parsing from `cell_queries`, and
    `GridMap` and `RaycastResult` (which need the kernels) as types only. Importing the client loaded
    153 numba modules (0.6 s) before they did."""
    for module in ("fleetmap_client.rest", "fleetmap.api_models"):
        code = f"import sys, {module}\nprint('\\n'.join(sorted(sys.modules)))\n"
        result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
        assert result.returncode == 0, result.stderr
        loaded = result.stdout.split()
        assert module in loaded
        compiled = [m for m in loaded if m.split(".")[0] == "numba" or m.startswith("fleetmap.kernels")]
        assert compiled == [], f"importing {module} loads {compiled[:5]}..."
