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
