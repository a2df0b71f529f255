"""The values a run takes where its flags leave them: the per-task defaults (TASK_DEFAULTS: the paper's multi-task
settings, DrQ-v2's exploration schedule by task, DEAR's coefficients, DrM's task configs in DRM_TASKS) and the
authors' recipe (RECIPES), every row with its source; cli.apply_recipe sets them. No numpy, torch or MuJoCo at import.
"""
from __future__ import annotations


def _walker(cfg):
    return cfg.env.startswith("walker-")


def _humanoid(cfg):
    return cfg.env in ("humanoid-run", "humanoid-stand", "humanoid-walk")


def _manipulation(cfg):
    return cfg.env.split("-")[0] in ("metaworld", "kitchen", "adroit")


def _multitask(cfg):
    import envs  # imported late so --help needs no MuJoCo
    return envs.is_task_set(cfg.env)


def _dear(cfg):
    return cfg.method == "dear"


def _authors_discount(cfg):
    import envs  # the suite's default action repeat; imported late so --help needs no MuJoCo
    return round(0.99 ** (1 + (cfg.action_repeat or envs.default_action_repeat(cfg.env))), 6)


# Every value where the paper's hyper-parameter table and the authors' released code (github.com/sear-rl/sear-rl)
# differ: (field, applies to, authors' value, source). The Config defaults are the paper's values; --recipe authors
# replaces these unless the flag is given explicitly.
RECIPES = {"authors": (
    # (DEAR's c1 and c2 are its own under both recipes: TASK_DEFAULTS)
    ("recon_coef", lambda cfg: not _dear(cfg), 1.0, "sear/cfgs/agent/sear.yaml: reconstruction_loss_coeff"),
    ("mask_coef", lambda cfg: not _dear(cfg), 0.25, "sear/cfgs/agent/sear.yaml: mask_loss_coeff"),
    ("nstep", _walker, 1, "sear/cfgs/task/distracting_walker_walk.yaml: nstep (DrQ-v2's walker config)"),
    ("batch_size", _walker, 512, "sear/cfgs/task/distracting_walker_walk.yaml: batch_size"),
    ("lr", _humanoid, 8e-5, "sear/cfgs/task/humanoid_{run,stand,walk}.yaml: lr (DrQ-v2's)"),
    ("feature_dim", _humanoid, 100, "sear/cfgs/task/humanoid_{run,stand,walk}.yaml: feature_dim (DrQ-v2's)"),
    ("replay_size", lambda cfg: cfg.env == "quadruped-run", 100_000,
     "sear/cfgs/task/quadruped_run.yaml: replay_buffer_size (DrQ-v2's)"),
    # Their Meta-World / Kitchen / Adroit wrappers return discount 0.99 for every env step, and the replay multiplies
    # by 0.99 again per agent step: gamma = 0.99^(action repeat + 1) per step.
    ("discount", _manipulation, _authors_discount,
     "sear/environments/{metaworld,kitchen,adroit}_dm_env.py step(), sear/replay_buffer.py"),
    ("mask_downsample", _manipulation, "stride", "sear/environments/wrappers.py: SegmentationFilter [::3, ::3]"),
    # The paper's multi-task latent is 512 (TASK_DEFAULTS below); the authors' code keeps 4096 there too.
    ("latent_dim", lambda cfg: _multitask(cfg) and cfg.method != "ef", 4096,
     "sear/cfgs/agent/sear.yaml: latent_dim 4096 (no task cfg overrides it)"),
)}


def _drqv2_std_steps(cfg):
    import envs  # DrQ-v2's per-task table lives with the other suite facts; late so --help needs no MuJoCo
    return envs.exploration_std_steps(cfg.env)


# DrM's dm_control task configs (github.com/XuGW-Kevin/DrM at 317116a, cfgs/): what a --drm run on each task takes
# where it differs from this project's defaults. Every task: its cfgs/task/<task>.yaml (the `hard` group's exploration
# schedule, lr, feature_dim, batch_size, replay_buffer_size, agent.max_perturb_factor) over cfgs/config.yaml
# (replay_buffer_size 1000000). agent.target_lambda is 0.6 in all of them (the --drm-lambda default); nstep is
# config.yaml's 3 everywhere (ours). docs/drm.md.
_DRM_HARD = {"std_steps": 2_000_000}                   # cfgs/task/hard.yaml: linear(1.0,0.1,2000000)
_DRM_BIG = {"lr": 8e-5, "feature_dim": 100}            # dog_* and humanoid_*
_DRM_REPLAY = {"replay_size": 1_000_000}               # cfgs/config.yaml: replay_buffer_size
DRM_TASKS = {
    "acrobot-swingup": {**_DRM_REPLAY},
    "acrobot-swingup_sparse": {**_DRM_REPLAY, **_DRM_HARD, "drm_max_perturb": 0.9},
    "cartpole-swingup_sparse": {**_DRM_REPLAY},
    "cheetah-run": {**_DRM_REPLAY},
    "dog-run": {**_DRM_REPLAY, **_DRM_HARD, **_DRM_BIG, "drm_max_perturb": 0.6},
    "dog-stand": {**_DRM_REPLAY, **_DRM_HARD, **_DRM_BIG, "drm_max_perturb": 0.6},
    "dog-trot": {**_DRM_REPLAY, **_DRM_HARD, **_DRM_BIG, "drm_max_perturb": 0.9},
    "dog-walk": {**_DRM_REPLAY, **_DRM_HARD, **_DRM_BIG, "drm_max_perturb": 0.6},
    "hopper-hop": {**_DRM_REPLAY},
    "humanoid-run": {**_DRM_REPLAY, **_DRM_HARD, **_DRM_BIG, "drm_max_perturb": 0.6},
    "humanoid-stand": {**_DRM_REPLAY, **_DRM_HARD, **_DRM_BIG, "drm_max_perturb": 0.9},
    "humanoid-walk": {**_DRM_REPLAY, **_DRM_HARD, **_DRM_BIG, "drm_max_perturb": 0.9},
    "manipulator-bring_ball": {**_DRM_REPLAY, **_DRM_HARD, "lr": 8e-5, "drm_max_perturb": 0.9},
    "quadruped-run": {"replay_size": 100_000},
    "quadruped-walk": {"replay_size": 100_000},
    "reacher-easy": {**_DRM_REPLAY},
    "reacher-hard": {**_DRM_REPLAY},
    "walker-run": {**_DRM_REPLAY, "batch_size": 512},
}
DRM_MAX_PERTURB = {env: task["drm_max_perturb"] for env, task in DRM_TASKS.items() if "drm_max_perturb" in task}
_DRM_SOURCE = {"std_steps": "cfgs/task/hard.yaml: stddev_schedule linear(1.0,0.1,2000000)",
               "lr": "cfgs/task/<task>.yaml: lr", "feature_dim": "cfgs/task/<task>.yaml: feature_dim",
               "batch_size": "cfgs/task/walker_run.yaml: batch_size",
               "replay_size": "cfgs/config.yaml: replay_buffer_size; cfgs/task/quadruped_{run,walk}.yaml",
               "drm_max_perturb": "cfgs/task/<task>.yaml: agent.max_perturb_factor"}


_DRM_ON = "with --drm on DrM's tasks (DRM_TASKS in harness/recipes.py, docs/drm.md)"


def _drm_row(name):
    """The TASK_DEFAULTS row of DrM's value of `name` (DRM_TASKS) for --drm runs on its tasks."""
    values = " or ".join(dict.fromkeys(str(task[name]) for task in DRM_TASKS.values() if name in task))
    return (name, lambda cfg: cfg.drm and name in DRM_TASKS.get(cfg.env, {}),
            lambda cfg: DRM_TASKS[cfg.env][name], f"DrM's {_DRM_SOURCE[name]}", f"{values} {_DRM_ON}")


# Per-task (and per-method) defaults, applied under both recipes before the recipe's own rows; a later row
# wins over an earlier one. The paper's multi-task settings (its hyper-parameter table): the task sets
# (metaworld-mt3, -mt10, -mt50) train with a smaller latent and a 4x longer exploration schedule; the
# authors' code keeps latent 4096 there (its row in RECIPES). Plain dm_control tasks (the paper is silent)
# take DrQ-v2's exploration schedule by task. DEAR takes c1 (its cosine term) and c2 from its released
# dear.yaml (docs/dear.md). --drm runs on DrM's dm_control tasks take DrM's task config (DRM_TASKS).
# (field, applies to, value, source, what --help says of it: the field's default is the value elsewhere)
TASK_DEFAULTS = (
    ("recon_coef", _dear, 1.0, "DEAR's dear/cfgs/agent/dear.yaml: reconstruction_loss_coeff (its cosine term)",
     "1.0 with --method dear"),
    ("mask_coef", _dear, 0.25, "DEAR's dear/cfgs/agent/dear.yaml: mask_loss_coeff", "0.25 with --method dear"),
    ("latent_dim", _multitask, 512, "paper, hyper-parameter table, multi-task",
     "512 on the task sets (metaworld-mt3, -mt10, -mt50)"),
    ("latent_dim", lambda cfg: cfg.method == "ef", 2048, "efrl cfgs/agent/drqv2ef.yaml: hs_dim (docs/foresight.md)",
     "2048 with --method ef"),
    ("std_steps", _multitask, 2_000_000, "paper, hyper-parameter table, multi-task; the authors' "
                                         "multi-task task cfgs: stddev_schedule linear(1.0,0.1,2000000)",
     "2000000 on the task sets"),
    ("std_steps", lambda cfg: _drqv2_std_steps(cfg) is not None, _drqv2_std_steps,
     "DrQ-v2's and the authors' cfgs/task/{easy,medium,hard}.yaml: stddev_schedule by task",
     "on dm_control tasks DrQ-v2's by task: 100000 (easy), 500000 (medium, and every task not in its "
     "table), 2000000 (hard: humanoid)"),
    *map(_drm_row, _DRM_SOURCE),
)
