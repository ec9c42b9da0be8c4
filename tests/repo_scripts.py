"""The repository's scripts (docs/, benchmarks/, pipelines/, data-samples/) loaded as modules
by the tests that check them: they are files, not packages."""

from __future__ import annotations

import importlib.util
from pathlib import Path
from types import ModuleType

ROOT = Path(__file__).resolve().parents[1]


def load_script(relpath: str) -> ModuleType:
    """Import the script at ``ROOT / relpath`` under a name of its own."""
    path = ROOT / relpath
    spec = importlib.util.spec_from_file_location("repo_script_" + path.stem, path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module
