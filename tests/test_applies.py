"""Every setting acts or is refused: its field's keys (acts=, envs=, when=; cli.scope) say where
each flag acts; sear.py refuses a flag given anywhere else (or, with --drop-inapplicable, drops it),
and the keys tell the truth."""
import contextlib
import dataclasses
import io
import json

import numpy as np
import pytest
import torch

from harness import cli
import envs
import train

# One env of every suite kind the table tells apart (cartpole: --pole-inertia).
SUITE_ENVS = ("walker-walk", "cartpole-swingup", "walker-walk-distracting", "cartpole-swingup-distracting",
              "metaworld-door-open", "metaworld-mt10", "kitchen-kettle", "adroit-door")
FIELDS = {f.name: f for f in (*dataclasses.fields(train.Config), *dataclasses.fields(cli.RunConfig))}
DEFAULTS = {**vars(train.Config()), **vars(cli.RunConfig())}


def never_train(*args):
    raise AssertionError("sear.py accepted the flags and started training")


def parse(argv):
    with contextlib.redirect_stdout(io.StringIO()):  # the recipe's line
        return cli.parse_args(argv, train.Config, train.METHODS)


def typed(name, value) -> list[str]:
    """A flag as a user (or sweep.py) types it, with this value."""
    if isinstance(value, bool):
        return [cli.flag(name) if value else "--no-" + cli.flag(name)[2:]]
    return [cli.flag(name), str(value)]


def test_every_scope_names_methods_envs_and_conditions_that_exist():
    """A field's acts= names --method values (or a set of cli.METHOD_SETS), envs= a set of
    cli.ENV_SETS, when= a setting or one of cli.CONDITIONS; a field without them acts in every
    run."""
    for name, f in FIELDS.items():
        acts, envs_, when = (f.metadata.get(k) for k in ("acts", "envs", "when"))
        if isinstance(acts, str):
            assert acts in cli.METHOD_SETS, name
        elif acts is not None:
            assert {m.split()[0] for m in acts} <= set(train.METHODS), name
        assert envs_ is None or envs_ in cli.ENV_SETS, name
        assert when is None or when in cli.CONDITIONS or when in FIELDS, name
    assert not set(cli.CONDITIONS) & set(FIELDS)  # when="drm" means --drm, never a condition


def test_the_method_lists_are_the_methods_table():
    assert set(cli.MASK_METHODS) == {m for m, row in train.METHODS.items() if row.uses_mask}
    pooled = {m for m, row in train.METHODS.items() if row.encoder == "pooled"}
    assert set(cli.POOLED_METHODS) == pooled


def test_suite_of_reads_every_env_name_as_envs_does():
    kinds = {"dmc": "dmc", "distracting": "distracting", "kitchen": "kitchen", "adroit": "adroit"}
    for name in envs.env_names():
        suite, _ = envs._parse_name(name)
        want = ("task-set" if envs.is_task_set(name) else "metaworld") if suite == "metaworld" else kinds[suite]
        assert cli.suite_of(name) == want, name


CONTEXTS = [(method, env, False) for method in train.METHODS for env in SUITE_ENVS] + \
           [(method, "walker-walk", True) for method in train.METHODS]


@pytest.mark.parametrize("name", sorted(set(FIELDS) - {"resume", "evaluate", "init_from"}))
def test_a_flag_given_where_it_does_nothing_is_refused_and_anywhere_else_taken(name, tmp_path, monkeypatch):
    """Every flag (at its default value, as a sweep passes it) x every method x every suite kind (and --drm):
    one line naming the flag and where it acts exactly where its keys say it does nothing; with
    --drop-inapplicable the run goes on with the default. (--resume, --evaluate, --init-from are commands
    and sources: tested on their own.)"""
    monkeypatch.chdir(tmp_path)
    for method, env, drm in CONTEXTS:
        base = ["--env", env, "--method", method] + (["--drm"] if drm else [])
        argv = base + typed(name, DEFAULTS[name])
        settings = {**DEFAULTS, "env": env, "method": method, "drm": drm}
        if cli.acts(name, settings):
            cfg, run, _ = parse(argv)
            continue
        with pytest.raises(cli.ConfigError) as refused:
            parse(argv)
        message = str(refused.value)
        assert message.startswith(f"{' '.join(typed(name, DEFAULTS[name]))} does nothing in this run ("), message
        assert f"it is for {cli.scope(name)[1]}" in message and "\n" not in message
        cfg, run, _ = parse([*argv, "--drop-inapplicable"])
        assert getattr(cfg if name in vars(cfg) else run, name) == DEFAULTS[name]


@pytest.mark.parametrize("argv, message", [
    (["--method", "drq", "--recon-coef", "1.0"], "--recon-coef 1.0 does nothing in this run (drq on walker-walk): "
                                                 "it is for --method sear, sear-nosplit, ae (2 x c1), mae and dear"),
    (["--method", "drq", "--mask-approx"], "--mask-approx does nothing in this run (drq on walker-walk): it is for "
                                           "methods that use the robot mask (--method sear, sear-nosplit, rgbm and "
                                           "dear)"),
    (["--method", "curl", "--mask-noise", "0.5"], "--mask-noise 0.5 does nothing in this run (curl on walker-walk)"),
    (["--method", "sear", "--curl-lr", "0.1"], "--curl-lr 0.1 does nothing in this run (sear on walker-walk): it is "
                                               "for --method curl"),
    (["--method", "drq", "--dear-feature", "push"], "--dear-feature push does nothing in this run (drq on "
                                                    "walker-walk)"),
    (["--difficulty", "hard"], "--difficulty hard does nothing in this run (sear on walker-walk): it is for "
                               "Distracting Control (*-distracting envs)"),
    (["--eval-episodes-per-task", "3"], "--eval-episodes-per-task 3 does nothing in this run (sear on walker-walk): "
                                        "it is for the task sets (metaworld-mt3, -mt10, -mt50)"),
    (["--drm-lambda", "0.5"], "--drm-lambda 0.5 does nothing in this run (sear on walker-walk): it is for runs with "
                              "--drm"),
    (["--env", "metaworld-mt10", "--eval-episodes", "20", "--eval-episodes-per-task", "2"],
     "--eval-episodes 20 does nothing in this run (sear on metaworld-mt10)"),
    (["--method", "drq", "--latent-dim", "64", "--mask-approx"],
     "--latent-dim 64 and --mask-approx do nothing in this run (drq on walker-walk): --latent-dim is for SEAR's "
     "pooled encoder"),
])
def test_the_issues_cases_are_one_line(argv, message, tmp_path, monkeypatch, capsys):
    """The nine settings that were recorded without acting, and more, as sear.py's users see them."""
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(train, "train", never_train)
    assert train.main(argv) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith(f"sear.py: error: {message}"), err
    assert not (tmp_path / "runs").exists()


def test_drop_inapplicable_records_the_default_and_says_so_in_one_line(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    cfg, run, _ = cli.parse_args(["--method", "drq", "--recon-coef", "1.0", "--dear-feature", "push", "--lr", "3e-4",
                                  "--drop-inapplicable"], train.Config, train.METHODS)
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("sear.py: warning: --drop-inapplicable: ignored what does nothing "
                                                   "in this run (drq on walker-walk), config.json records the default: "
                                                   "--recon-coef 1.0 (for --method sear"), err
    config = cli.config_dict(cfg, run)
    assert (config["recon_coef"], config["dear_feature"], config["lr"]) == (0.01, "pull", 3e-4)
    assert "drop_inapplicable" not in config  # a command of this process, not a setting of the run


def test_recipes_and_per_task_rows_set_no_value_that_does_nothing(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    drq, _, _ = parse(["--method", "drq", "--env", "metaworld-door-open", "--recipe", "authors"])
    assert (drq.recon_coef, drq.mask_coef, drq.mask_downsample) == (0.01, 0.0025, "majority")
    assert drq.discount == pytest.approx(0.99 ** 3)  # what acts is still set
    mt10, _, _ = parse(["--method", "drq", "--env", "metaworld-mt10"])
    assert (mt10.latent_dim, mt10.std_steps) == (4096, 2_000_000)
    sear_mt10, _, _ = parse(["--env", "metaworld-mt10"])
    assert sear_mt10.latent_dim == 512


def saved_run(tmp_path, **config) -> str:
    """A run directory as sear.py leaves it (config.json, snapshot.pt with its config), without training."""
    cfg, run = cli.split_config({**DEFAULTS, **config}, train.Config)
    saved = cli.config_dict(cfg, run)
    run_dir = tmp_path / "run"
    run_dir.mkdir()
    (run_dir / "config.json").write_text(json.dumps(saved))
    torch.save({"config": saved}, run_dir / "snapshot.pt")
    return str(run_dir)


def test_resume_and_evaluate_refuse_a_flag_that_does_nothing(tmp_path):
    run_dir = saved_run(tmp_path, method="drq", env="cup-catch")
    with pytest.raises(cli.ConfigError, match=r"^--recon-coef 0.01 does nothing in this run \(drq on cup-catch\)"):
        parse(["--resume", run_dir, "--recon-coef", "0.01"])  # the saved value: still does nothing
    with pytest.raises(cli.ConfigError, match=r"^--eval-episodes-per-task 2 does nothing in this run \(drq on "
                                              r"cup-catch\): it is for the task sets"):
        parse(["--evaluate", run_dir, "--eval-episodes-per-task", "2"])
    cfg, run, _ = parse(["--resume", run_dir, "--drop-inapplicable", "--recon-coef", "0.01"])
    assert cfg.method == "drq"


def test_acting_settings_leave_out_what_did_not_act_in_old_runs():
    old = {**DEFAULTS, "method": "drq", "env": "walker-walk", "dear_feature": "push", "difficulty": "hard",
           "recon_coef": 1.0, "lr": 3e-4}
    acting = cli.acting_settings(old)
    assert not {"dear_feature", "difficulty", "recon_coef", "latent_dim", "drm_lambda"} & set(acting)
    assert (acting["method"], acting["lr"], acting["env"]) == ("drq", 3e-4, "walker-walk")
    assert cli.acting_settings({"method": "dear", "env": "cup-catch-distracting", "dear_feature": "push",
                                "difficulty": "hard"}) == {"method": "dear", "env": "cup-catch-distracting",
                                                           "dear_feature": "push", "difficulty": "hard"}


# ---------------------------------------------------------------- the table tells the truth
# A value other than the default for each setting that some methods read: one that changes an update
# wherever the setting acts.
CHANGED = {"recon_coef": 0.5, "mask_coef": 0.5, "latent_dim": 32, "ae_latent_lambda": 0.1, "mae_ratio": 0.5,
           "mae_patch": 7, "curl_tau": 0.5, "curl_lr": 0.1, "dear_feature": "push", "drm_lambda": 0.3,
           "drm_expectile": 0.6}


def weights_after_updates(cfg) -> dict:
    """The agent's tensors after two updates on one batch, from the same seeds."""
    torch.manual_seed(0)
    agent = train.make_agent(cfg, action_dim=2, device=torch.device("cpu"))
    rng = np.random.default_rng(0)
    batch = (rng.integers(0, 256, (4, 9, 84, 84), dtype=np.uint8), (rng.random((4, 3, 84, 84)) > 0.7).astype(np.uint8),
             rng.uniform(-1, 1, (4, 2)).astype(np.float32), rng.normal(size=(4, 1)).astype(np.float32),
             np.full((4, 1), 0.97, np.float32), rng.integers(0, 256, (4, 9, 84, 84), dtype=np.uint8),
             (rng.random((4, 3, 84, 84)) > 0.7).astype(np.uint8))
    torch.manual_seed(1)
    for step in (10**5 + 2, 10**5 + 4):
        agent.update(batch, step=step)
    networks = {"encoder": agent.encoder, "critic": agent.critic, "actor": agent.actor, "aux": agent.aux,
                "value": getattr(agent, "value", None)}
    return {f"{part}.{k}": v.detach().clone() for part, net in networks.items() if net is not None
            for k, v in net.state_dict().items() if torch.is_tensor(v)}  # CURL's extra state: its Adam, a count


def same(a: dict, b: dict) -> bool:
    return a.keys() == b.keys() and all(a[k].shape == b[k].shape and torch.equal(a[k], b[k]) for k in a)


@pytest.fixture
def one_thread():
    """Tiny updates: one torch thread is ~50x faster than two on cores other jobs are using (they spin)."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


@pytest.mark.parametrize("method", list(train.METHODS))
def test_a_setting_changes_the_update_exactly_where_the_table_says_it_acts(method, one_thread):
    tiny = dict(method=method, latent_dim=64, hidden_dim=32, feature_dim=8, batch_size=4, action_repeat=2,
                **({"ef_agent_dim": 8} if method == "ef" else {}))  # EF's agent part below any latent tried
    for drm in (False, True) if method == "drq" else (False,):
        base = weights_after_updates(train.Config(**tiny, drm=drm))
        for name, value in CHANGED.items():
            if drm and not name.startswith("drm_"):  # with --drm, its own settings; the others were seen without
                continue
            settings = {**DEFAULTS, **tiny, "drm": drm}
            changed = weights_after_updates(train.Config(**{**tiny, "drm": drm, name: value}))
            assert same(base, changed) != cli.acts(name, settings), (method, drm, name)
