"""The official DrQ-v2 code's train.py, unmodified, on today's stack.

    python benchmarks/run_official.py --official DRQV2_CHECKOUT [--tf32] -- task@_global_=cartpole_balance_sparse \
        seed=1 device=cuda save_video=false use_tb=false hydra.run.dir=runs/official-1 num_train_frames=40002

Runs DRQV2_CHECKOUT/train.py (facebookresearch/drqv2, c0c650b; never copied here) in this process with the
hydra overrides after `--`, as `python train.py OVERRIDES` would, after adapting today's stack to it from
outside. Nothing the runs compute changes; each adaptation, and why:

- Stand-ins in sys.modules for modules the runs never use with save_video=false save_train_video=false
  use_tb=false: `torchvision` always (logger.py imports it and uses none of it; a torchvision built for
  another torch fails at import); where not installed, `cv2` (video.py draws frames with it only when a
  video is recorded: the stand-in raises on any use), termcolor's `colored` (the console's colours only: it
  returns the text as is) and `torch.utils.tensorboard`'s SummaryWriter (use_tb=true only: it raises when
  made).
- The action spec's dtype. dm_control's action_scale.Wrapper reports np.result_type(its bounds, the wrapped
  spec's dtype): float32 under NumPy 1 (0-d bounds cast by value), float64 under NumPy 2, and the replay
  storage then asserts that the agent's float32 actions are float64. dmc.py's wrapper is given a subclass
  that reports the wrapped spec's dtype (float32: the ActionDTypeWrapper under it), as under NumPy 1;
  its transform of the actions is the wrapper's own. So the replay's action spec and the reset's zero
  action are float32, as in 2021.
- The loader workers' seed. replay_buffer._worker_init_fn seeds Python's `random` with a numpy uint32,
  which Python 3.11 refuses; replay_buffer's `random` is the module itself but for seed(), which passes
  int(seed): the state Python 3.10 made from that number (it seeded with hash(seed), that int), and
  random.choice draws from the same module state. The workers are forked (Linux's default before Python
  3.14), so they inherit this.
- torch.load's weights_only default (True from torch 2.6, which refuses load_snapshot's pickled agent):
  TORCH_FORCE_NO_WEIGHTS_ONLY_LOAD=1, torch's own switch back to False where a call does not say (a resume
  only).
- hydra's launcher. config.yaml overrides hydra/launcher with submitit_local, a config of the
  hydra-submitit-launcher plugin; without the plugin, an empty stand-in of that name is stored so that the
  config composes. Only a multirun (-m) launches through it; a single run, as here, never does.
- TF32 (not a stack change: arithmetic). Off by default, the reference arithmetic (DrQ-v2's published curves
  ran on V100s, which have none; torch turns it on for cuDNN's convolutions), as sear.py's --tf32; --tf32
  turns it on in convolutions and matmuls (cli.set_tf32).

Errors before the run (no checkout, no hydra): one line on stderr, exit code 2. After that, train.py's own
exit status (hydra prints its errors).
"""
from __future__ import annotations

import argparse
import importlib.util
import os
import runpy
import sys
import types

# this project's cli (standard library only: no name the checkout's modules use), after the checkout's on the path
sys.path.append(os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))
from harness import cli  # noqa: E402

HYDRA_PACKAGES = "hydra-core omegaconf antlr4-python3-runtime PyYAML hydra-submitit-launcher"


class OfficialError(Exception):
    """Bad input: one line on stderr, exit code 2."""


def parse(argv: list[str]) -> tuple[argparse.Namespace, list[str]]:
    """(our arguments, the hydra overrides after `--`)."""
    p = cli.OneLineParser(description=__doc__.split("\n\n")[0],
                                usage="run_official.py --official DIR [--tf32] [--check] -- HYDRA_OVERRIDES...")
    p.add_argument("--official", required=True, metavar="DIR", help="a checkout of facebookresearch/drqv2")
    p.add_argument("--check", action="store_true", help="check the checkout and hydra, run nothing (exit 0 or 2)")
    p.add_argument("--tf32", action="store_true",
                   help="CUDA: TF32 in float32 convolutions and matmuls (off: the reference arithmetic)")
    cut = argv.index("--") if "--" in argv else len(argv)
    return p.parse_args(argv[:cut]), argv[cut + 1:]


def check(checkout: str) -> str:
    """train.py of the checkout, or an OfficialError naming what is missing."""
    train = os.path.join(checkout, "train.py")
    needed = [train, os.path.join(checkout, "cfgs", "config.yaml"), os.path.join(checkout, "dmc.py")]
    missing = [p for p in needed if not os.path.isfile(p)]
    if missing:
        raise OfficialError(f"--official {checkout}: not a checkout of facebookresearch/drqv2 (no {missing[0]})")
    try:  # imported, not looked up: an install without its dependencies (omegaconf without yaml) fails here
        import hydra  # noqa: F401
        import omegaconf  # noqa: F401
    except ImportError as e:
        raise OfficialError(f"the official code needs hydra: {e} (pip install {HYDRA_PACKAGES})") from None
    return os.path.abspath(train)


def module_with(module: types.ModuleType, **replaced) -> types.ModuleType:
    """A copy of `module`'s namespace with `replaced` attributes (the module itself is left as it is)."""
    copy = types.ModuleType(module.__name__)
    copy.__dict__.update({**vars(module), **replaced})
    return copy


def stub(name: str, why: str, **attributes) -> types.ModuleType:
    """A module that holds `attributes` and raises AttributeError on any other use, saying `why` it is a stub."""
    module = types.ModuleType(name)
    module.__dict__.update(attributes)

    def missing(attribute):
        raise AttributeError(f"{name}.{attribute}: {name} is a stand-in of run_official.py ({why})")
    module.__getattr__ = missing
    return module


def installed(name: str) -> bool:
    try:
        return importlib.util.find_spec(name) is not None
    except (ImportError, ValueError):
        return False


def stub_unused_modules():
    """Stand-ins for the modules the runs never use (the docstring: why each)."""
    sys.modules["torchvision"] = stub("torchvision", "logger.py imports it and uses none of it")
    if not installed("cv2"):
        sys.modules["cv2"] = stub("cv2", "videos need opencv-python-headless: save_video=false save_train_video=false")
    if not installed("termcolor"):
        sys.modules["termcolor"] = stub("termcolor", "console colours", colored=lambda text, *_, **__: text)
    if not installed("tensorboard"):
        def no_tensorboard(*_, **__):
            raise ImportError("use_tb=true needs tensorboard (pip install tensorboard), or use_tb=false")
        sys.modules["torch.utils.tensorboard"] = stub("torch.utils.tensorboard", "use_tb=false",
                                                      SummaryWriter=no_tensorboard)


def float32_action_spec(dmc):
    """dmc.py's action_scale.Wrapper reporting the wrapped spec's dtype, as under NumPy 1 (the docstring)."""
    base = dmc.action_scale.Wrapper

    class Wrapper(base):
        def __init__(self, env, minimum, maximum):
            super().__init__(env, minimum, maximum)
            self._action_spec = self._action_spec.replace(dtype=env.action_spec().dtype)

    dmc.action_scale = module_with(dmc.action_scale, Wrapper=Wrapper)


def int_worker_seed(replay_buffer):
    """replay_buffer's `random`: the module, but seed() takes the int of a numpy integer (the docstring)."""
    import random
    replay_buffer.random = module_with(random, seed=lambda a=None, version=2: random.seed(
        None if a is None else int(a), version))


def stand_in_launcher():
    """Without hydra-submitit-launcher: an empty hydra/launcher=submitit_local config, so config.yaml composes."""
    if installed("hydra_plugins.hydra_submitit_launcher"):
        return
    from hydra.core.config_store import ConfigStore
    ConfigStore.instance().store(group="hydra/launcher", name="submitit_local",
                                 node={"_target_": "hydra._internal.core_plugins.basic_launcher.BasicLauncher"})


def adapt(checkout: str, tf32: bool):
    """Every adaptation of the docstring, before train.py imports anything of its own."""
    os.environ["MUJOCO_GL"] = "egl"  # what train.py sets first; set here as dmc is imported before it
    os.environ.setdefault("TORCH_FORCE_NO_WEIGHTS_ONLY_LOAD", "1")
    stub_unused_modules()
    sys.path.insert(0, checkout)  # as `python train.py` puts it first: train.py imports dmc, train, ...
    import dmc
    import replay_buffer
    float32_action_spec(dmc)
    int_worker_seed(replay_buffer)
    stand_in_launcher()
    cli.set_tf32(tf32)


def main(argv=None) -> int:
    try:
        args, overrides = parse(sys.argv[1:] if argv is None else list(argv))
        train = check(args.official)
    except (OfficialError, cli.ConfigError) as e:
        print(f"run_official.py: error: {e}", file=sys.stderr)
        return 2
    if args.check:
        return 0
    adapt(os.path.dirname(train), args.tf32)
    sys.argv = [train, *overrides]
    try:
        runpy.run_path(train, run_name="__main__")
    except SystemExit as e:  # hydra's errors: it has printed them
        return e.code if isinstance(e.code, int) else 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
