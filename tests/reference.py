"""Released reference code for the equivalence tests, read at test time: this project ships none of it.

An environment variable names a checkout of the reference repository or a git mirror of it (then the
files are read at the commit the docs describe, with `git show`); unset, the test skips and says which
variable to set. The files are written to a temporary folder and imported from there under a name of
their own; the reference's own top-level modules (`utils`, `models`, ...) leave sys.modules again.
"""
import ast
import importlib.util
import os
import subprocess
import sys
import types
from pathlib import Path

import pytest


def materialise(var: str, repo: str, commit: str, paths, dest: Path) -> Path:
    """Write the reference's `paths` under `dest` (same relative paths) and return dest. Skips when `var`
    is unset; fails when it is set but a file cannot be read."""
    root = os.environ.get(var, "")
    if not root:
        pytest.skip(f"set {var} to a checkout (or git mirror) of github.com/{repo} to compare with its "
                    f"released code at {commit}")
    for path in paths:
        if (Path(root) / path).is_file():
            text = (Path(root) / path).read_text()
        else:
            r = subprocess.run(["git", "-C", root, "show", f"{commit}:{path}"], capture_output=True, text=True)
            if r.returncode:
                pytest.fail(f"{var}={root}: no {path} at {commit} ({r.stderr.strip()})")
            text = r.stdout
        (dest / path).parent.mkdir(parents=True, exist_ok=True)
        (dest / path).write_text(text)
    return dest


def functions(source: Path, names, module_name: str) -> types.ModuleType:
    """A module made of some top-level functions of a reference file, for a file whose imports (gym,
    scikit-image, ...) are not installed here: its other code is not run."""
    tree = ast.parse(source.read_text())
    tree.body = [node for node in tree.body if isinstance(node, ast.FunctionDef) and node.name in names]
    missing = set(names) - {node.name for node in tree.body}
    if missing:
        pytest.fail(f"{source}: no function {', '.join(sorted(missing))}")
    module = types.ModuleType(module_name)
    exec(compile(tree, str(source), "exec"), module.__dict__)
    return module


def load(folder: Path, path: str, name: str, stand_ins=None) -> types.ModuleType:
    """Import folder/path as module `name`, with `folder` first on sys.path and `stand_ins` ({module name:
    module}) importable, for that import only. Skips when the file imports a package not installed here."""
    saved_path, saved_modules = list(sys.path), dict(sys.modules)
    sys.path.insert(0, str(folder))
    sys.modules.update(stand_ins or {})
    try:
        spec = importlib.util.spec_from_file_location(name, folder / path)
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
    except ModuleNotFoundError as e:
        pytest.skip(f"the released {path} imports {e.name}, which is not installed here")
    finally:
        sys.path[:] = saved_path
        for key in set(sys.modules) - set(saved_modules) | set(stand_ins or ()):  # theirs and the stand-ins go
            mod = sys.modules[key]
            if key in (stand_ins or {}) or str(folder) in str(getattr(mod, "__file__", None) or getattr(mod, "__path__", "")):
                del sys.modules[key]
        sys.modules.update({k: v for k, v in saved_modules.items() if k not in sys.modules})
    return module
