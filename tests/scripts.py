"""Importing a script that is no package's module (a benchmark, the dev set's scoring script) by its path."""

import importlib.util
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def load_script(path: Path, name: str):
    """The module of the script at ``path`` (absolute, or relative to the repository), run once under ``name``.
    Benchmarks put benchmarks/ on the import path for their own imports."""
    spec = importlib.util.spec_from_file_location(name, ROOT / path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod
