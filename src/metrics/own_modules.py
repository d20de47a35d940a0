"""Importing a video metric package with its own top-level helper modules.

`pycvvdp` (ColorVideoVDP) and `pyfvvdp` (FovVideoVDP, Noisebase's protocol) each append their own folder
to `sys.path` and then `from interp import ...`: the first one imported leaves its `interp` in
`sys.modules`, and the second gets that one. Imported after `pyfvvdp`, `pycvvdp` fails (`pyfvvdp`'s
`interp` has no `interp1dim2`); imported before, `pyfvvdp` would silently run on `pycvvdp`'s
interpolation. `own_top_level` imports a package with its folder first on the path and none of the shared
names cached, then puts back what was there, so each package binds its own helpers.
"""

from __future__ import annotations

import importlib
import importlib.util
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

#: The top-level module names both packages import from their own folders.
SHARED_NAMES = ("interp",)


def package_dir(package: str) -> Path | None:
    """The folder of an installed package, found without importing it (None when it is not installed)."""
    spec = importlib.util.find_spec(package)
    if spec is None or not spec.submodule_search_locations:
        return None
    return Path(next(iter(spec.submodule_search_locations)))


@contextmanager
def own_top_level(package: str, names: tuple[str, ...] = SHARED_NAMES) -> Iterator[None]:
    """Inside: `names` resolve to `package`'s own folder; after: `sys.modules` and `sys.path` as before
    for `names` (the package keeps the functions it bound)."""
    folder = package_dir(package)
    saved = {n: sys.modules.pop(n) for n in names if n in sys.modules}
    if folder is not None:
        sys.path.insert(0, str(folder))
    try:
        yield
    finally:
        if folder is not None:
            sys.path.remove(str(folder))  # the first occurrence: the one inserted above
        for n in names:
            sys.modules.pop(n, None)
        sys.modules.update(saved)


def import_own(module: str, package: str) -> object:
    """`importlib.import_module(module)` with `package`'s own top-level helpers (`own_top_level`)."""
    if module in sys.modules:
        return sys.modules[module]
    with own_top_level(package):
        return importlib.import_module(module)
