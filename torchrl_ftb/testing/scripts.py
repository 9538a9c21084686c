"""Import a recipe or bench script by path (they are scripts, not package modules)."""
from __future__ import annotations

import importlib.util
import sys
from pathlib import Path
from types import ModuleType


def load_script(path: str | Path, name: str | None = None) -> ModuleType:
    """Execute the script at ``path`` as module ``name`` (default: its stem) and return it.

    The module is registered in ``sys.modules`` first, so dataclasses and pickling inside it work.

    Example:
        >>> from pathlib import Path
        >>> import torchrl_ftb.testing.scripts as m
        >>> load_script(Path(m.__file__), "scripts_copy").load_script.__name__
        'load_script'
    """
    path = Path(path)
    spec = importlib.util.spec_from_file_location(name or path.stem, path)
    if spec is None or spec.loader is None:
        raise ImportError(f"{path}: cannot be loaded as a Python module")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return module
