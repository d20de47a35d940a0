"""Imports inside `src/` run one way (docs/architecture.md, "Packages and the direction of imports"): a
module imports only packages of a lower layer, or its own package. The renderer may read the data
layouts (render -> data); a data module never imports the renderer, a trainer, an evaluation or a task.
Read from the source text (ast), so a lazy import inside a function counts too."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

SRC = Path(__file__).resolve().parents[1] / "src"

#: Each top-level package (or module) of src/ and its layer: an import must go to a strictly lower layer
#: or stay in its own package. A new package gets a row here, where its imports put it.
LAYERS: dict[str, int] = {
    "errors": 0,
    "io": 1,
    "multirun": 1,
    "launch": 1,
    "provenance": 2,
    "metrics": 2,
    "gp": 2,
    "data": 3,
    "report": 3,
    "tracking": 3,
    "render": 4,
    "models": 4,
    "objectives": 5,
    "stages": 5,
    "schema": 6,
    # The data kind stands below the trainer and the evaluation: the task builds it and hands it to them.
    "kinds": 7,
    "train": 8,
    "eval": 9,
    "tasks": 10,
    "run": 11,
    "bench": 11,
    "studies": 11,
}
#: src/__init__.py registers the config resolvers, which read the feature catalogues (data).
PACKAGE_INIT_IMPORTS = {"data"}


def _package(path: Path, src: Path = SRC) -> str:
    return path.relative_to(src).with_suffix("").parts[0]


def _imported_packages(path: Path) -> set[str]:
    """The src packages a file imports (top level or inside functions), by their first name after src."""
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        names = []
        if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names = [node.module]
        elif isinstance(node, ast.Import):
            names = [alias.name for alias in node.names]
        found |= {name.split(".")[1] for name in names if name.startswith("src.") and name.count(".") >= 1}
    return found


def back_arrows(src: Path = SRC) -> list[str]:
    """Every import from a file to a package of the same or a higher layer (its own package excepted)."""
    arrows = []
    for path in sorted(src.rglob("*.py")):
        if path == src / "__init__.py":
            arrows += [f"src/__init__.py -> {p}" for p in _imported_packages(path) - PACKAGE_INIT_IMPORTS]
            continue
        package = _package(path, src)
        for target in sorted(_imported_packages(path) - {package}):
            if LAYERS[target] >= LAYERS[package]:
                arrows.append(f"{path.relative_to(src.parent)} ({package}) -> {target}")
    return arrows


def test_every_package_has_a_layer():
    packages = {_package(p) for p in SRC.rglob("*.py") if p != SRC / "__init__.py"}
    assert packages == set(LAYERS)


def test_no_import_runs_back_up():
    assert back_arrows() == []


def test_a_data_module_importing_the_renderer_is_found(tmp_path):
    """The check itself: the arrow this project once had (a data layout read from src/render)."""
    for package, text in {
        "data": "from src.render.volume_aovs import CHANNEL_COUNT\n",
        "render": "from src.data.volume_aovs import CHANNEL_COUNT\n",
        "eval": "def f():\n    import src.tasks.nerf\n",
    }.items():
        (tmp_path / package).mkdir()
        (tmp_path / package / "m.py").write_text(text)
    (tmp_path / "__init__.py").write_text("from src.data.features import feature_count\n")
    assert back_arrows(tmp_path) == [
        f"{tmp_path.name}/data/m.py (data) -> render",
        f"{tmp_path.name}/eval/m.py (eval) -> tasks",
    ]


@pytest.mark.parametrize("package", ["io", "data", "render"])
def test_lower_packages_never_import_training_evaluation_or_tasks(package):
    for path in (SRC / package).rglob("*.py"):
        assert not _imported_packages(path) & {"train", "eval", "tasks", "run"}, path


def private_imports(src: Path = SRC) -> list[str]:
    """Every private name (one leading underscore) a file imports from another module of src/, top level
    or inside a function: a shared piece has a public name in its home module."""
    found = []
    for path in sorted(src.rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("src"):
                found += [
                    f"{path.relative_to(src.parent)}: {node.module}.{alias.name}"
                    for alias in node.names
                    if alias.name.startswith("_") and not alias.name.startswith("__")
                ]
    return found


def test_no_private_name_is_imported_across_modules(tmp_path):
    assert private_imports() == []
    (tmp_path / "data").mkdir()
    (tmp_path / "data" / "m.py").write_text(
        "from src.data.shards import shard_name as _name\n"
        "def f():\n    from src.render.scenes import _hidden\n"
    )
    assert private_imports(tmp_path) == [f"{tmp_path.name}/data/m.py: src.render.scenes._hidden"]
