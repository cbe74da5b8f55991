"""Plugins: the user's own combiners, learners, orders or environment families, one file each.

A plugin is a Python file (or an importable module) whose classes register themselves by name
with the library's registries when it is imported; recipes then use those names.
"""

from __future__ import annotations

import importlib
import importlib.util
import sys
from collections.abc import Iterable
from pathlib import Path

from layered.errors import BadInput


class PluginError(BadInput, ImportError):
    """A plugin that cannot be found or imported."""


def load_plugin(spec: str) -> str:
    """Import a plugin from a `.py` path or a module name; returns how to name it again later
    (the absolute path, or the module name). Importing the same plugin twice is harmless."""
    if spec.endswith(".py"):
        path = Path(spec).resolve()
        if not path.is_file():
            raise PluginError(f"plugin {spec}: no such file")
        name = f"layered_plugin_{path.stem}_{abs(hash(str(path))) % 10**8}"
        if name not in sys.modules:
            module_spec = importlib.util.spec_from_file_location(name, path)
            assert module_spec is not None and module_spec.loader is not None
            module = importlib.util.module_from_spec(module_spec)
            sys.modules[name] = module
            try:
                module_spec.loader.exec_module(module)
            except Exception as e:
                del sys.modules[name]
                raise PluginError(f"plugin {spec}: {e.__class__.__name__}: {e}") from e
        return str(path)
    try:
        importlib.import_module(spec)
    except ImportError as e:
        raise PluginError(f"plugin {spec}: {e} (a plugin named as a module is imported as Python imports it: "
                          "installed, or its folder on PYTHONPATH; a file is named by its path ending in .py)") from e
    return spec


def load_plugins(specs: Iterable[str]) -> list[str]:
    """Load every plugin; the list of how each is named again (see load_plugin)."""
    return [load_plugin(spec) for spec in specs]
