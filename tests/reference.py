"""Released reference code for the equivalence tests, read at test time: this project ships none of it.
The end of this file holds the pieces of an update-for-update comparison with it.

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
import torch


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


def package(folder: Path, name: str) -> types.ModuleType:
    """A stand-in for the reference's own top-level package `name` (folder/name), for a `load`
    whose files import from it by a name this project holds (sear-rl's `sear`: our sear.py)."""
    module = types.ModuleType(name)
    module.__path__ = [str(folder / name)]
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


# ---------------------------------------------------------------- update for update
class Contiguous(torch.nn.Module):
    """x.contiguous(), appended to a reference encoder's convolutions when they run in our
    channels_last layout: the reference flattens their output with .view, which needs the logical
    (NCHW) order that our flatten(1) copies it into."""

    def forward(self, x):
        return x.contiguous()


def adopt(theirs: dict, ours: dict, layout: bool) -> None:
    """The reference's networks ({name: module}) take our weights, parameter by parameter in order
    (the same shapes; the names as each spells them). `layout`: our tensors' memory layout too
    (clones keep our strides), else their values only, in the reference's own layout."""
    with torch.no_grad():
        for name, module in theirs.items():
            mine = ours[name].named_parameters()
            for (kt, pt), (ko, po) in zip(module.named_parameters(), mine, strict=True):
                assert pt.shape == po.shape, (name, kt, ko)
                if layout:
                    pt.data = po.detach().clone()
                else:
                    pt.copy_(po)


def optimisers(agent) -> dict:
    """The reference agent's optimisers by attribute name (encoder_opt, critic_opt, ...)."""
    return {k: v for k, v in vars(agent).items() if isinstance(v, torch.optim.Optimizer)}


def take_our_implementation(agent, encoder, ours, utils, monkeypatch) -> None:
    """The exact case: a released agent given three implementation choices of ours, each equal to
    its own in exact arithmetic. Each of its optimisers rebuilt with our optimisers' settings
    (`ours.optimiser`): one per network as it has them, per parameter the same as our one over
    several networks, Adam being per-parameter. Our memory layout, which `adopt(layout=True)` gave
    its parameters, through its `encoder`'s flatten. Our Polyak arithmetic (`ours.polyak`) as its
    utils.soft_update_params."""
    encoder.convnet.append(Contiguous())
    for name, opt in optimisers(agent).items():
        params = [p for group in opt.param_groups for p in group["params"]]
        setattr(agent, name, ours.optimiser(params))
    monkeypatch.setattr(utils, "soft_update_params", ours.polyak)


def put_wrong(agent, case: str) -> None:
    """The controls: each optimiser of the agent with its learning rate x 1.01, or its sign
    flipped (torch's `maximize`)."""
    for opt in optimisers(agent).values():
        for group in opt.param_groups:
            group["lr"] *= 1.01 if case == "control: lr x 1.01" else 1.0
            group["maximize"] = case == "control: wrong sign"


def _flat(module):
    return torch.cat([p.detach().flatten() for p in module.parameters()])


def flat(modules: dict) -> dict:
    """{name: the network's parameters, flattened into one tensor}: `drift`'s start."""
    return {k: _flat(m) for k, m in modules.items()}


def max_abs_diffs(theirs: dict, ours: dict) -> dict:
    """{name: the largest |their parameter - ours| over that network}."""
    return {k: (_flat(theirs[k]) - _flat(ours[k])).abs().max().item() for k in theirs}


def drift(theirs: dict, ours: dict, start: dict) -> dict:
    """{name: ||theirs - ours|| / ||ours - ours at the start||}: the agents' distance as a part of
    how far our updates moved that network (2-norms over all its parameters)."""
    out = {}
    for k in theirs:
        mine = _flat(ours[k])
        out[k] = ((_flat(theirs[k]) - mine).norm() / (mine - start[k]).norm()).item()
    return out


def report(case, update, mine, theirs, names, diffs, drifts) -> None:
    """One line per update, which `pytest -s` shows: each loss's difference (absolute, relative),
    each network's largest |parameter difference| and its drift."""
    gaps = {k: abs(mine[k] - theirs[v]) for k, v in names.items()}
    losses = ", ".join(f"{k} {g:.3g} ({g / abs(theirs[names[k]]):.2g})" for k, g in gaps.items())
    networks = ", ".join(f"{k} {d:.3g} ({drifts[k]:.2g})" for k, d in diffs.items())
    print(f"{case}, update {update + 1}: |loss difference| (relative) {losses}; "
          f"max |parameter difference| (drift) {networks}")
