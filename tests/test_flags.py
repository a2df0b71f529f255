"""Each setting is declared once, as its dataclass field (harness/cli.py reads the parser, the help,
the ranges and where it acts from there); every flag of sear.py given a value it cannot take ends in
one line, exit 2, before anything is built; --resume of a finished run says so, building nothing."""
import ast
import dataclasses
import json
import os

import pytest
import torch

from harness import cli, runenvs
import train

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
FIELDS = {f.name: f
          for f in (*dataclasses.fields(train.Config), *dataclasses.fields(cli.RunConfig))}
# The tables that may name settings: the recipes and the per-task defaults, each row with its
# source (harness/recipes.py holds them; cli.py re-exports them).
PER_TASK_TABLES = {"RECIPES", "TASK_DEFAULTS", "DRM_TASKS", "DRM_MAX_PERTURB"}


def strings_listed(node) -> set[str]:
    """The string keys of the dicts and the strings listed in the tuples, lists and sets in node."""
    strings = set()
    for part in ast.walk(node):
        items = (part.keys if isinstance(part, ast.Dict) else
                 part.elts if isinstance(part, (ast.Tuple, ast.List, ast.Set)) else [])
        strings |= {i.value for i in items
                    if isinstance(i, ast.Constant) and isinstance(i.value, str)}
    return strings


def names_in_tables(path: str) -> dict[str, set[str]]:
    """{table: the settings it names} of a module's top-level assignments (but the per-task
    tables)."""
    named = {}
    for node in ast.parse(open(path).read()).body:
        if not isinstance(node, (ast.Assign, ast.AnnAssign)) or node.value is None:
            continue
        targets = node.targets if isinstance(node, ast.Assign) else [node.target]
        table = next((t.id for t in targets if isinstance(t, ast.Name)), "?")
        settings = strings_listed(node.value) & set(FIELDS)
        if settings and table not in PER_TASK_TABLES:
            named[table] = settings
    return named


@pytest.mark.parametrize("module", ["cli", "files", "process"])
def test_no_setting_is_named_in_a_table_of_the_command_line(module):
    """A setting's doc, range, group, metavar and where it acts are keys of its field, not rows of
    tables keyed by its name (the recipes and per-task defaults excepted)."""
    assert names_in_tables(os.path.join(ROOT, "harness", f"{module}.py")) == {}


def test_cli_reads_what_the_fields_declare_without_importing_them():
    """cli.declared reads the keys plot.py and sweep.py need from the classes' source (no torch);
    they are the keys the imported fields carry. Every key is one cli knows, every group one of
    cli.GROUPS."""
    declared = cli.declared()
    assert set(declared) == set(FIELDS)
    for name, f in FIELDS.items():
        assert declared[name] == {k: f.metadata[k] for k in cli.STATIC if k in f.metadata}, name
        assert set(f.metadata) <= {"doc", "choices", *cli.META}, name
        assert f.metadata.get("group") in (None, *cli.GROUPS), name
    assert cli.RESUME_MAY_CHANGE >= {"frames", "device", "tf32", "resume"}
    assert cli.EVALUATE_MAY_SET == {"evaluate", "eval_episodes", "eval_episodes_per_task",
                                    "save_video", "device", "threads"}


def bad_values(f) -> list[list[str]]:
    """Command lines giving field f a value it cannot take: one of the wrong type (or not a
    choice), and for a flag that names a device, devices that are not this machine's or none."""
    kind = f.type if isinstance(f.type, str) else f.type.__name__
    name = cli.flag(f.name)
    if kind == "bool":
        return [[f"{name}=abc"], [f"--no-{name[2:]}=abc"]]
    if f.metadata.get("metavar") == "DEVICE":
        return [[name, value] for value in ("abc", "tpu", "banana", "cuda:7", "cuda:x", "")]
    if f.name == "run_root":  # any text is a folder name: a folder inside a file is not one
        return [[name, os.path.join(__file__, "runs")]]
    return [[name, "abc"]]


def no_envs(*args, **kwargs):
    raise AssertionError("sear.py built an env or an agent")


@pytest.mark.parametrize("name", sorted(FIELDS))
def test_every_flag_with_a_value_it_cannot_take_ends_in_one_line(name, tmp_path, monkeypatch,
                                                                    capsys):
    """Every flag of `python sear.py`: exit 2, at most 2 lines on stderr, no traceback, and no
    env or network built (the checks come first)."""
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(runenvs, "SeedEnvs", no_envs)
    monkeypatch.setattr(train, "make_agent", no_envs)
    for argv in bad_values(FIELDS[name]):
        code = train.main(["--frames", "10", *argv])
        err = capsys.readouterr().err
        assert code == 2 and len(err.splitlines()) <= 2, (argv, code, err)
        assert err.startswith("sear.py: error: ") and "Traceback" not in err, (argv, err)
    assert not (tmp_path / "runs").exists()


@pytest.mark.skipif(torch.cuda.is_available(), reason="this machine has CUDA: --tf32 acts")
def test_tf32_without_cuda_is_refused_as_every_flag_that_does_nothing(tmp_path, monkeypatch,
                                                                       capsys):
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(runenvs, "SeedEnvs", no_envs)
    assert train.main(["--tf32"]) == 2
    assert capsys.readouterr().err == (
        "sear.py: error: --tf32 does nothing in this run (device cpu): it is for CUDA devices "
        "(--device cuda, cuda:N, or auto on a machine with CUDA)\n")
    assert train.main(["--tf32", "--device", "cpu"]) == 2
    assert capsys.readouterr().err.startswith(
        "sear.py: error: --tf32 does nothing in this run (sear on walker-walk): it is for CUDA")
    run = cli.RunConfig(tf32=True, drop_inapplicable=True, threads=torch.get_num_threads())
    assert cli.torch_setup(run) == torch.device("cpu") and not run.tf32
    assert capsys.readouterr().err == ("sear.py: warning: --drop-inapplicable: ignored what does "
                                       "nothing in this run (device cpu): --tf32\n")


def finished_run(tmp_path, frames=48, step=24, last_eval_frame=48) -> str:
    """A run directory as sear.py leaves one at the end of its budget (action repeat 2), without
    training."""
    cfg = train.Config(env="walker-walk", frames=frames, action_repeat=2)
    saved = cli.config_dict(cfg, cli.RunConfig())
    run_dir = tmp_path / "runs" / "walker-walk__sear__1__x"
    run_dir.mkdir(parents=True)
    (run_dir / "config.json").write_text(json.dumps(saved))
    (run_dir / "eval.csv").write_text("frame,return\n0,1.0\n48,2.0\n")
    counters = {"step": step, "episode": 3, "last_eval_frame": last_eval_frame,
                "mid_episode": False, "wall_time": 1.0}
    torch.save({"config": saved, "counters": counters}, run_dir / "snapshot.pt")
    return str(run_dir)


def test_resume_of_a_finished_run_says_so_and_builds_nothing(tmp_path, monkeypatch, capsys):
    run_dir = finished_run(tmp_path)
    before = {p: os.path.getmtime(os.path.join(run_dir, p)) for p in os.listdir(run_dir)}
    monkeypatch.setattr(runenvs, "SeedEnvs", no_envs)
    monkeypatch.setattr(train, "make_agent", no_envs)
    assert train.main(["--resume", run_dir]) == 0
    out, err = capsys.readouterr()
    assert err == "" and out == (
        f"{run_dir} is done: it trained to frame 48 (--frames 48) and was evaluated there; its "
        f"results are in {run_dir} (eval.csv, train.csv); to train further: python sear.py "
        f"--resume {run_dir} --frames N, with N > 48\n")
    assert {p: os.path.getmtime(os.path.join(run_dir, p)) for p in os.listdir(run_dir)} == before


@pytest.mark.parametrize("frames, step, last_eval_frame", [
    (80, 24, 48),   # a larger budget: it trains on
    (48, 24, 40),   # a SIGTERM cut the final evaluation short: the resumed run evaluates
    (48, 20, 40),   # stopped before the end of its budget
])
def test_resume_of_a_run_that_is_not_finished_goes_on(tmp_path, frames, step, last_eval_frame):
    run_dir = finished_run(tmp_path, 48, step, last_eval_frame)
    argv = ["--resume", run_dir, "--frames", str(frames)]
    cfg, run, snapshot = cli.parse_args(argv, train.Config, train.METHODS)
    assert cli.finished(cfg, run, snapshot) is None


def test_a_seed_group_resumes_its_runs_itself(tmp_path):
    """A run inside a seed group's folder is its group's to resume (harness/group.py)."""
    from harness import group
    run_dir = finished_run(tmp_path)
    (tmp_path / "runs" / group.GROUP_FILE).write_text("{}")
    cfg, run, snapshot = cli.parse_args(["--resume", run_dir], train.Config, train.METHODS)
    assert cli.GROUP_FILE == group.GROUP_FILE and cli.finished(cfg, run, snapshot) is None


def test_seeds_is_a_flag_of_this_command_only():
    assert cli.parse_seeds("1-3,7") == [1, 2, 3, 7]
    for spec, message in [("abc", "--seeds takes seeds like 1-16 or 1,3,5, got 'abc'"),
                          ("4", "--seeds takes two or more different seeds, got '4'")]:
        with pytest.raises(cli.ConfigError, match=f"^{message}$"):
            cli.parse_seeds(spec)
    assert "seeds" not in cli.config_dict(train.Config(), cli.RunConfig(seeds="1-4"))
