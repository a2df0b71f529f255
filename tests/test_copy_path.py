"""README's copy path: the definitions it lists, taken out of sear.py by name and put in a module of
their own with only torch, numpy and the standard library, run README's block: one SEAR update of a
minimal critic on random data. A name missing from the list is a NameError here."""
import ast
import re
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
MARK = "# Copied from sear.py:"


def readme_block() -> tuple[list[str], str]:
    """The names README's copy block lists, and the block's code."""
    blocks = re.findall(r"```python\n(.*?)```", (ROOT / "README.md").read_text(), re.S)
    block = next(b for b in blocks if MARK in b)
    head, code = block.split(MARK, 1)[1].split("\n#", 1)[0], block
    names = head.split() + [w for line in code.split(MARK, 1)[1].splitlines()[1:]
                            if line.startswith("#  ") for w in line[1:].split()]
    return names, code


def copied_module(names: list[str]) -> dict:
    """exec() of exactly the named top-level definitions of sear.py, in file order, after plain imports."""
    source = (ROOT / "sear.py").read_text()
    defs = [node for node in ast.parse(source).body
            if isinstance(node, (ast.FunctionDef, ast.ClassDef)) and node.name in names]
    assert sorted(d.name for d in defs) == sorted(names), f"not top-level definitions of sear.py: {names}"
    header = "import copy, math\nimport numpy as np\nimport torch\nimport torch.nn as nn\nimport torch.nn.functional as F\n"
    code = header + "\n\n".join(ast.get_source_segment(source, d, padded=False) for d in defs)
    namespace = {"__name__": "copied"}
    exec(compile(code, "copied_from_sear.py", "exec"), namespace)
    return namespace


def test_readme_lists_every_definition_sear_on_another_agent_needs():
    names, code = readme_block()
    assert {"SearAux", "shift_together", "PooledEncoder"} <= set(names)  # the block is found
    namespace = copied_module(names)
    torch.manual_seed(0)
    b = 4
    critic = torch.nn.Linear(4096, 1)  # a minimal critic: a TD loss on the same latent
    namespace.update(torch=torch, critic=critic, critic_loss=lambda latent: critic(latent).pow(2).mean(),
                     obs=torch.randint(0, 256, (b, 9, 84, 84)).float(),
                     mask=(torch.rand(b, 3, 84, 84) < 0.1).float())
    exec(compile(code, "README.md", "exec"), namespace)
    assert torch.isfinite(namespace["loss"])
    assert set(namespace["terms"]) == {"recon_loss", "mask_loss"}
    # One Adam step moved the encoder, both decoders and the critic.
    moved = [p.grad is not None and p.grad.abs().sum() > 0 for p in
             (namespace["encoder"].fc.weight, namespace["aux"].mask_decoder.fc[0].weight,
              namespace["aux"].recon_decoder.fc[0].weight, critic.weight)]
    assert all(moved)


def free_names(names: list[str]) -> set[str]:
    """The names the listed definitions of sear.py load that they neither define, nor bind themselves,
    nor take from the modules sear.py imports at its top (torch, numpy, the standard library), nor
    from Python's builtins: what a reader's copy would lack, even in a line no test runs."""
    import builtins
    tree = ast.parse((ROOT / "sear.py").read_text())
    imported = set()
    for node in tree.body:
        if isinstance(node, ast.Import):
            imported |= {(a.asname or a.name).split(".")[0] for a in node.names}
        elif isinstance(node, ast.ImportFrom):
            imported |= {a.asname or a.name for a in node.names}
    known = set(names) | imported | set(dir(builtins)) | {"__class__"}
    free = set()
    for node in (n for n in tree.body if getattr(n, "name", None) in names):
        bound = set()
        for sub in ast.walk(node):
            if isinstance(sub, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda)):
                a = sub.args
                bound |= {x.arg for x in [*a.posonlyargs, *a.args, *a.kwonlyargs, a.vararg, a.kwarg] if x}
            if isinstance(sub, (ast.FunctionDef, ast.ClassDef)):
                bound.add(sub.name)
            if isinstance(sub, ast.Name) and isinstance(sub.ctx, (ast.Store, ast.Del)):
                bound.add(sub.id)
            if isinstance(sub, ast.ExceptHandler) and sub.name:
                bound.add(sub.name)
        free |= {f"{sub.id} (in {node.name})" for sub in ast.walk(node)
                 if isinstance(sub, ast.Name) and isinstance(sub.ctx, ast.Load) and sub.id not in known | bound}
    return free


def test_the_copy_list_closes():
    """Every name the listed definitions use is defined by the list or comes from torch, numpy or
    the standard library: a copied AuxLoss that named ReplayBuffer, say, fails here."""
    names, _ = readme_block()
    assert free_names(names) == set()
    assert free_names([n for n in names if n != "Decoder"]) == {"Decoder (in SearAux)"}
