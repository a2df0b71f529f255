"""--drm on DrM's dm_control tasks takes DrM's task config (cli.DRM_TASKS; docs/drm.md, "Per-task values"):
the hard tasks' exploration schedule, lr and feature_dim where its task files set them, its replay size and
walker_run's batch; checked by hand here and, with SEAR_DRM_REFERENCE, against DrM's cfgs themselves."""
import contextlib
import io
import os
import re
import subprocess
from pathlib import Path

import pytest

from harness import cli
import envs
import sear
import train
from tests import reference

DRM_COMMIT = "317116a"  # docs/drm.md's


def parse(*argv):
    with contextlib.redirect_stdout(io.StringIO()):
        return cli.parse_args(list(argv), train.Config, sear.METHODS)[0]


def drm_values(cfg) -> tuple:
    return (cfg.std_steps, cfg.lr, cfg.feature_dim, cfg.replay_size, cfg.batch_size, cfg.nstep, cfg.drm_max_perturb)


@pytest.mark.parametrize("env, values", [
    # std steps, lr, feature, replay, batch, nstep, max perturb factor
    ("dog-run", (2_000_000, 8e-5, 100, 1_000_000, 256, 3, 0.6)),
    ("dog-trot", (2_000_000, 8e-5, 100, 1_000_000, 256, 3, 0.9)),
    ("humanoid-run", (2_000_000, 8e-5, 100, 1_000_000, 256, 3, 0.6)),
    ("humanoid-stand", (2_000_000, 8e-5, 100, 1_000_000, 256, 3, 0.9)),
    ("manipulator-bring_ball", (2_000_000, 8e-5, 50, 1_000_000, 256, 3, 0.9)),
    ("acrobot-swingup_sparse", (2_000_000, 1e-4, 50, 1_000_000, 256, 3, 0.9)),
    ("walker-run", (500_000, 1e-4, 50, 1_000_000, 512, 3, 1.0)),
    ("quadruped-walk", (500_000, 1e-4, 50, 100_000, 256, 3, 1.0)),
    ("quadruped-run", (500_000, 1e-4, 50, 100_000, 256, 3, 1.0)),
    ("cheetah-run", (500_000, 1e-4, 50, 1_000_000, 256, 3, 1.0)),
])
def test_a_drm_run_takes_drms_task_config(env, values, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    for method in ("drq", "sear"):
        assert drm_values(parse("--env", env, "--method", method, "--drm")) == values, method


def test_without_drm_or_off_drms_tasks_nothing_changes_and_explicit_flags_win(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert drm_values(parse("--env", "dog-run", "--method", "drq")) == (500_000, 1e-4, 50, 250_000, 256, 3, 1.0)
    assert drm_values(parse("--env", "walker-walk", "--method", "drq", "--drm")) == (100_000, 1e-4, 50, 250_000, 256,
                                                                                     3, 1.0)
    assert drm_values(parse("--env", "dog-run", "--drm", "--lr", "1e-4", "--replay-size", "250000",
                            "--std-steps", "500000")) == (500_000, 1e-4, 100, 250_000, 256, 3, 0.6)
    # --recipe authors still applies its rows on top: sear-rl's walker cfg (DrQ-v2's) is n-step 1
    authors = parse("--env", "walker-run", "--drm", "--recipe", "authors")
    assert (authors.nstep, authors.batch_size, authors.replay_size) == (1, 512, 1_000_000)


def test_the_run_says_which_drm_values_it_took(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    cli.parse_args(["--env", "dog-walk", "--method", "drq", "--drm"], train.Config, sear.METHODS)
    line = capsys.readouterr().out
    for said in ("std_steps=2000000 (DrM's cfgs/task/hard.yaml", "lr=8e-05 (DrM's cfgs/task/<task>.yaml: lr)",
                 "feature_dim=100", "replay_size=1000000 (DrM's cfgs/config.yaml: replay_buffer_size",
                 "drm_max_perturb=0.6"):
        assert said in line, line


# ---------------------------------------------------------------- against DrM's own cfgs
def read_cfg(path: Path) -> dict:
    """A hydra task/config file of DrM's, flat: 'key: value' lines, `agent:` keys as agent.KEY, and the
    `defaults` list under 'defaults'."""
    values, section = {"defaults": []}, None
    for line in path.read_text().splitlines():
        if not line.strip() or line.lstrip().startswith("#"):
            continue
        if line.startswith("  - ") and section == "defaults":
            values["defaults"].append(line[4:].strip())
            continue
        key, _, value = line.strip().partition(":")
        if not line.startswith(" "):
            section = key if not value.strip() else None
        if value.strip():
            values[f"{section}.{key}" if line.startswith(" ") and section else key] = value.strip().strip("'\"")
    return values


def drm_task_files(tmp_path) -> tuple[Path, list[str]]:
    root = os.environ.get("SEAR_DRM_REFERENCE", "")
    if not root:
        pytest.skip("set SEAR_DRM_REFERENCE to a checkout (or git mirror) of github.com/XuGW-Kevin/DrM to compare "
                    f"with its cfgs at {DRM_COMMIT}")
    if (Path(root) / "cfgs" / "task").is_dir():
        names = sorted(p.name for p in (Path(root) / "cfgs" / "task").glob("*.yaml"))
    else:
        names = subprocess.run(["git", "-C", root, "ls-tree", "--name-only", f"{DRM_COMMIT}:cfgs/task"],
                               capture_output=True, text=True, check=True).stdout.split()
    paths = ["cfgs/config.yaml", "cfgs/agent/drm.yaml", *(f"cfgs/task/{n}" for n in names)]
    return reference.materialise("SEAR_DRM_REFERENCE", "XuGW-Kevin/DrM", DRM_COMMIT, paths, tmp_path), names


def test_every_dm_control_task_of_drm_resolves_to_its_cfgs(tmp_path, monkeypatch):
    """Each of DrM's dm_control task cfgs (a task file over its easy/medium/hard group over config.yaml), as
    `--method drq --drm --env <task>` resolves it: every value the files set that a flag here holds."""
    folder, names = drm_task_files(tmp_path)
    base = read_cfg(folder / "cfgs" / "config.yaml")
    tasks = 0
    for name in names:
        task = read_cfg(folder / "cfgs" / "task" / name)
        env = name[:-len(".yaml")].replace("_", "-", 1)
        if env not in envs.env_names() or "agent.max_perturb_factor" not in task:
            continue  # a group (easy, medium, hard), Meta-World's and Adroit's (drm_mw, drm_adroit), soccer
        group = read_cfg(folder / "cfgs" / "task" / f"{task['defaults'][0]}.yaml")
        drm = {**base, **group, **task}
        monkeypatch.chdir(tmp_path)
        cfg = parse("--env", env, "--method", "drq", "--drm")
        steps = int(re.fullmatch(r"linear\(1\.0,0\.1,(\d+)\)", drm["stddev_schedule"])[1])
        want = (steps, float(drm["lr"]), int(drm["feature_dim"]), int(drm["replay_buffer_size"]),
                int(drm["batch_size"]), int(drm["nstep"]), float(drm["agent.max_perturb_factor"]),
                float(drm["agent.target_lambda"]), int(drm["action_repeat"]), int(drm["frame_stack"]),
                float(drm["discount"]), int(drm["num_seed_frames"]), int(drm["update_every_steps"]))
        have = (*drm_values(cfg), cfg.drm_lambda, cfg.action_repeat or envs.default_action_repeat(env),
                cfg.frame_stack, cfg.discount, cfg.seed_frames, cfg.update_every)
        assert have == want, env
        tasks += 1
    assert tasks == len(cli.DRM_TASKS) == 18


def test_docs_table_is_cli_drm_tasks():
    """docs/drm.md says DrM's per-task values once, in one table: the same as cli.DRM_TASKS."""
    doc = (Path(__file__).resolve().parents[1] / "docs" / "drm.md").read_text()
    assert doc.count("## Per-task values") == 1
    section = doc.split("## Per-task values")[1].split("\n\n**")[0]
    columns = ("std_steps", "lr", "feature_dim", "replay_size", "batch_size", "drm_max_perturb")
    documented = {}
    for line in section.splitlines():
        cells = [c.strip() for c in line.strip("|").split("|")]
        if not line.startswith("| ") or cells[0] in ("task (`--env`)", "this project's default"):
            continue
        values = {k: float(v.replace(",", "")) for k, v in zip(columns, cells[1:]) if v}
        documented.update(dict.fromkeys((t.strip() for t in cells[0].split(",")), values))
    assert documented == cli.DRM_TASKS
