"""sear.py end to end on CPU with tiny budgets: outputs, snapshots, --resume, bad input."""
import csv
import dataclasses
import hashlib
import io
import json
import os
import platform
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
# Small networks and budgets: the full-size architecture is covered by test_sear.py.
TINY = ["--frames", "48", "--seed-frames", "12", "--batch-size", "4", "--eval-every", "24",
        "--eval-episodes", "1", "--max-episode-steps", "8", "--replay-size", "400",
        "--latent-dim", "64", "--hidden-dim", "32", "--render-quality", "fast"]


def tiny(method="sear"):
    """TINY for `method`: --latent-dim only where it acts (SEAR's pooled encoder; drq and rgbm flatten)."""
    from harness import cli
    if method in cli.POOLED_METHODS:
        return list(TINY)
    i = TINY.index("--latent-dim")
    return TINY[:i] + TINY[i + 2:]


def run(args, tmp_path, timeout=600):
    env = {**os.environ, "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl")}
    return subprocess.run([sys.executable, str(ROOT / "sear.py"), "--run-root", str(tmp_path / "runs"), *args],
                          capture_output=True, text=True, timeout=timeout, cwd=tmp_path, env=env)


def test_help_all_shows_every_flag_in_its_group(tmp_path):
    """--help-all lists every flag, the experiment's settings by the dataclass that holds them."""
    from harness import cli
    import train
    r = run(["--help-all"], tmp_path)
    assert r.returncode == 0, r.stderr[-2000:]
    assert all(name in r.stdout for name in cli.flag_names(train.Config))
    groups = [line for line in r.stdout.splitlines() if line.startswith("the ")]
    assert groups == ["the experiment (train.py Config):", "the experiment (sear.py Config):",
                      "the experiment (methods/baselines.py BaselineConfig):",
                      "the experiment (methods/foresight.py ForesightConfig):",
                      "the experiment (methods/drm.py DrMConfig):",
                      "the experiment (harness/experiment.py EnvConfig):", "the run (harness/cli.py RunConfig):"]


def help_flags(text: str) -> list[str]:
    """The flags a help text documents, in order: each entry's first --flag."""
    return [m[1] for m in re.finditer(r"^  (--[a-z0-9-]+)", text, re.M) if m[1] not in ("--help", "--help-all")]


def test_help_shows_the_flags_that_matter_in_named_groups_and_help_all_the_rest(tmp_path):
    """--help: docs/flags.md's flags (those whose field has a group=, cli.GROUPS), under their
    group titles, with where each acts; --help-all: every flag. Both parse every flag."""
    from harness import cli
    import train
    r = run(["--help"], tmp_path)
    assert r.returncode == 0, r.stderr[-2000:]
    groups = cli.help_sections(train.Config, full=False)[:-1]
    wanted = [cli.flag(name) for _, names in groups for name in names]
    assert help_flags(r.stdout) == wanted
    titles = [line[:-1] for line in r.stdout.splitlines()
              if line.endswith(":") and not line.startswith(" ") and line != "options:"]
    assert list(cli.GROUPS) == [title for title, _ in groups] == titles
    assert "only for --method dear" in " ".join(r.stdout.split())  # --dear-feature: acts=("dear",)
    every = {f.name for f in (*dataclasses.fields(train.Config), *dataclasses.fields(cli.RunConfig))}
    assert f"all {len(every)}: python sear.py --help-all" in " ".join(r.stdout.split())
    full = run(["--help-all"], tmp_path)
    assert sorted(help_flags(full.stdout)) == sorted(cli.flag(name) for name in every)
    # docs/flags.md lists the same flags as --help, and says how to see the others
    doc = (ROOT / "docs" / "flags.md").read_text()
    table = [m for line in doc.split("\n## ")[0].splitlines() if line.startswith("| `--")
             for m in re.findall(r"`(--[a-z0-9-]+)", line.split("|")[1])]
    assert sorted(set(table)) == sorted(wanted) and "--help-all" in doc


def _sigint_default():
    """A suite started in the background (`cmd &`, nohup) hands its children SIGINT ignored: undo that."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def interrupt_when(args, tmp_path, line_pattern, timeout=120):
    """Start sear.py, send SIGINT (Ctrl-C) once a stdout line matches, return (code, stdout, stderr)."""
    env = {**os.environ, "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl")}
    p = subprocess.Popen([sys.executable, str(ROOT / "sear.py"), "--run-root", str(tmp_path / "runs"), *args],
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=tmp_path, env=env,
                         preexec_fn=_sigint_default)
    seen, deadline = [], time.time() + timeout
    try:
        for line in p.stdout:
            seen.append(line)
            if re.search(line_pattern, line):
                p.send_signal(signal.SIGINT)
                break
            assert time.time() < deadline, "".join(seen[-20:])
        out, err = p.communicate(timeout=timeout)
    finally:
        if p.poll() is None:
            p.kill()
    return p.returncode, "".join(seen) + out, err


# Mid-episode long enough (40 steps) for a Ctrl-C sent at step 3 to land well inside the episode.
LONG_EPISODES = [*TINY, "--frames", "100000", "--max-episode-steps", "40", "--log-every", "0",
                 "--eval-every", "100000"]


def rows(path):
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def only_run_dir(tmp_path):
    dirs = sorted((tmp_path / "runs").iterdir())
    assert len(dirs) == 1, dirs
    return dirs[0]


def tree_digest(path):
    h = hashlib.sha256()
    for p in sorted(Path(path).rglob("*")):
        if p.is_file():
            h.update(str(p.relative_to(path)).encode() + p.read_bytes())
    return h.hexdigest()


def test_smoke_run_writes_csvs_and_snapshot_then_resume_continues(tmp_path):
    r = run(["--env", "walker-walk", "--seed", "3", "--save-buffer", *TINY], tmp_path)
    assert r.returncode == 0, r.stderr[-2000:]
    run_dir = only_run_dir(tmp_path)
    assert run_dir.name.startswith("walker-walk__sear__3__")
    for name in ("train.csv", "eval.csv", "snapshot.pt", "config.json", "buffer.npz"):
        assert (run_dir / name).exists(), name
    train = rows(run_dir / "train.csv")
    evals = rows(run_dir / "eval.csv")
    assert [int(r["frame"]) for r in evals] == [0, 24, 48]  # the last one: the end of the budget
    assert [int(r["frame"]) for r in train] == [16, 32, 48]  # 8-step episodes, action repeat 2
    assert {"return", "critic_loss", "actor_loss", "actor_saturated", "action_spread", "recon_loss", "mask_loss", "fps", "wall_time"} <= set(train[0])
    assert train[-1]["mask_loss"] != ""  # learning happened after the seed frames
    assert json.loads((run_dir / "config.json").read_text())["action_repeat"] == 2
    assert "snapshot at frame" not in r.stdout  # evaluations do not trigger snapshots: the clock does

    # Resume from the last snapshot (written at the end, frame 48) and train further.
    r = run(["--resume", str(run_dir), "--frames", "80"], tmp_path)
    assert r.returncode == 0, r.stderr[-2000:]
    assert "resumed at frame 48" in r.stdout
    assert "no saved replay buffer" not in r.stdout  # --save-buffer: the buffer came back
    evals = rows(run_dir / "eval.csv")
    assert [int(r["frame"]) for r in evals] == [0, 24, 48, 72, 80]
    assert [int(r["frame"]) for r in rows(run_dir / "train.csv")] == [16, 32, 48, 64, 80]
    assert only_run_dir(tmp_path) == run_dir  # no second run directory

    # plot.py draws the real run's eval.csv
    r = subprocess.run([sys.executable, str(ROOT / "plot.py"), str(tmp_path / "runs"), "--out", str(tmp_path / "c.png")],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    assert (tmp_path / "c.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and "sear" in r.stdout


@pytest.mark.parametrize("args, message", [
    (["--env", "no-such-env"], "unknown env"),
    (["--batch-size", "0"], "--batch-size must be > 0"),
    (["--discount", "1.5"], "--discount must be in [0, 1]"),
    (["--method", "nope"], "invalid choice"),
    (["--frames", "ten"], "invalid int value"),
    (["--resume", "does/not/exist"], "no such run directory"),
    (["--env", "walker-walk-distracting", "--backgrounds", "does/not/exist"], "does not exist"),
    (["--mask-downsample", "every-other"], "argument --mask-downsample: invalid choice: 'every-other'"),
    (["--snapshot-minutes", "-1"], "--snapshot-minutes must be >= 0"),
    (["--env", "walker-walk", "--pole-inertia", "2021"], "--pole-inertia 2021 does nothing in this run (sear on "
                                                         "walker-walk): it is for cartpole (cartpole-* and"),
    # Each of these used to start a run (TINY: a short one): inf passes every range, and a run that
    # cannot learn or ends in a PhysicsError traceback is worse than a refusal.
    ([*TINY, "--recon-coef", "inf"], "--recon-coef must be a finite number, got inf"),
    ([*TINY, "--mask-coef", "-inf"], "--mask-coef must be a finite number, got -inf"),
    ([*TINY, "--lr", "0"], "--lr must be > 0, got 0.0"),
    ([*TINY, "--lr", "-1e-4"], "--lr must be > 0, got -0.0001"),  # a value, not "expected one argument"
])
def test_bad_input_is_one_line_and_creates_nothing(tmp_path, args, message):
    r = run(args, tmp_path)
    assert r.returncode != 0
    assert len(r.stderr.strip().splitlines()) == 1, r.stderr
    assert message in r.stderr and "Traceback" not in r.stderr
    assert not (tmp_path / "runs").exists()


def truncated_torch_file():
    import torch
    data = io.BytesIO()
    torch.save({"agent": torch.zeros(1000)}, data)
    return data.getvalue()[:2000]  # a copy cut short


@pytest.mark.parametrize("content, reason", [
    (b"this is not a torch file", "UnpicklingError: could not find MARK."),
    (truncated_torch_file(), "is cut short (RuntimeError: PytorchStreamReader failed reading zip archive: failed "
                             "finding central directory): sear.py writes a snapshot whole or not at all, so this is a "
                             "copy or move that did not finish; copy snapshot.pt again from the run's original "
                             "folder, where its last snapshot stands (this folder keeps no other)"),
    (b"", "is cut short (EOFError: Ran out of input)"),
])
def test_unreadable_snapshot_is_reported_and_left_untouched(tmp_path, content, reason):
    run_dir = tmp_path / "runs" / "walker-walk__sear__1__x"
    run_dir.mkdir(parents=True)
    (run_dir / "snapshot.pt").write_bytes(content)
    (run_dir / "train.csv").write_text("frame,return\n2,1.0\n")
    before = tree_digest(run_dir)
    r = run(["--resume", str(run_dir)], tmp_path)
    assert r.returncode != 0
    assert len(r.stderr.strip().splitlines()) == 1, r.stderr
    if content.startswith(b"this"):
        assert "cannot read" in r.stderr and r.stderr.rstrip().endswith(reason), r.stderr  # whole sentences
    else:  # cut short: what to do about it
        assert f"--resume: '{run_dir / 'snapshot.pt'}' {reason}" in r.stderr, r.stderr
    assert tree_digest(run_dir) == before


def test_interrupt_before_the_first_snapshot_says_there_is_nothing_to_resume_and_leaves_no_folder(tmp_path):
    code, out, err = interrupt_when(["--env", "walker-walk", *LONG_EPISODES], tmp_path, r"\| ep 0 step 3$")
    assert code == 130, err
    run_dir = re.search(r"^run dir: (.+)$", out, re.M)[1]
    message = err.strip().splitlines()
    assert len(message) == 1 and "Traceback" not in err, err
    assert re.fullmatch(r"sear.py: interrupted at frame \d+ \(mid-episode\), before its first snapshot \(the first is "
                        r"written at the first episode end after 10 minutes\): nothing to resume, so "
                        + re.escape(run_dir) + " was removed", message[0]), message
    assert list((tmp_path / "runs").iterdir()) == []


def test_interrupt_mid_episode_after_a_snapshot_names_it_and_the_run_dir(tmp_path):
    args = ["--env", "walker-walk", *LONG_EPISODES, "--snapshot-minutes", "0"]  # a snapshot every episode
    code, out, err = interrupt_when(args, tmp_path, r"\| ep 1 step 3$")
    assert code == 130, err
    run_dir = only_run_dir(tmp_path)
    m = re.fullmatch(r"sear.py: interrupted at frame (\d+) \(mid-episode\): the last snapshot \(frame 80\) stands, "
                     r"the (\d+) frames after it will be re-run; continue with: python sear.py --resume (\S+)",
                     err.strip())
    assert m, err
    assert int(m[1]) - 80 == int(m[2]) > 0 and m[3] == str(run_dir)  # the real path, resumable as printed
    import torch
    assert torch.load(run_dir / "snapshot.pt", weights_only=False)["counters"]["step"] * 2 == 80


def test_interrupt_between_episodes_writes_a_snapshot(tmp_path):
    """Ctrl-C while the loop sits between episodes (here: while the first snapshot is being
    written) saves that exact state; a deterministic stand-in for a well-timed SIGINT."""
    driver = (
        "import sys, train\nfrom harness import experiment\n"
        "real, calls = experiment.save_snapshot, []\n"
        "def ctrl_c_once(run_dir, payload):\n"
        "    calls.append(payload['counters']['step'])\n"
        "    if len(calls) == 1:\n"
        "        raise KeyboardInterrupt\n"
        "    real(run_dir, payload)\n"
        "experiment.save_snapshot = ctrl_c_once\n"
        "sys.exit(train.main(sys.argv[1:]))\n")
    r = subprocess.run([sys.executable, "-c", driver, "--run-root", str(tmp_path / "runs"), "--env", "walker-walk",
                        *TINY, "--frames", "1000", "--snapshot-minutes", "0"],
                       capture_output=True, text=True, timeout=300, cwd=ROOT,
                       env={**os.environ, "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl")})
    assert r.returncode == 130, r.stderr[-2000:]
    run_dir = only_run_dir(tmp_path)
    assert r.stderr.strip() == (f"sear.py: interrupted at frame 16 (between episodes): snapshot.pt holds this frame; "
                                f"continue with: python sear.py --resume {run_dir}")
    import torch
    counters = torch.load(run_dir / "snapshot.pt", weights_only=False)["counters"]
    assert counters["step"] == 8 and counters["episode"] == 1 and not counters["mid_episode"]


def test_snapshots_follow_their_own_clock_and_the_budget_ends_with_an_evaluation(tmp_path):
    """--snapshot-minutes 0: a snapshot at every episode end, though evaluations are far apart;
    the budget (40 frames, mid-episode) still ends with an evaluation at frame 40."""
    r = run(["--env", "walker-walk", *TINY, "--frames", "40", "--eval-every", "100000", "--snapshot-minutes", "0"],
            tmp_path)
    assert r.returncode == 0, r.stderr[-2000:]
    assert re.findall(r"^snapshot at frame (\d+)", r.stdout, re.M) == ["16", "32"]
    run_dir = only_run_dir(tmp_path)
    assert [int(row["frame"]) for row in rows(run_dir / "eval.csv")] == [0, 40]
    import torch
    counters = torch.load(run_dir / "snapshot.pt", weights_only=False)["counters"]
    assert counters["step"] == 20 and counters["mid_episode"] and counters["last_eval_frame"] == 40


def test_evaluation_shows_which_episode_it_is_on_and_that_frame_0_scores_the_untrained_policy(tmp_path):
    r = run(["--env", "walker-walk", *TINY, "--frames", "16", "--eval-episodes", "2", "--log-every", "0"], tmp_path)
    assert r.returncode == 0, r.stderr[-2000:]
    lines = [line for line in r.stdout.splitlines() if " | eval " in line]
    evals = [re.sub(r", ends in ~\S+( \S+)?$", "", line.split(" | ")[-1]) for line in lines]
    # Two evaluations (frame 0 and the final one at frame 16), each 2 episodes x 8 steps.
    assert evals == ([f"eval {i}/2 step {t} (the untrained policy)" for i in (1, 2) for t in range(1, 9)]
                     + [f"eval {i}/2 step {t}" for i in (1, 2) for t in range(1, 9)]), r.stdout
    assert all(", ends in ~" in line for line in lines[8:16]) and ", ends in" not in lines[0]  # once one is timed
    assert all("| ETA measuring |" in line for line in lines[:16])  # nothing trained yet: no speed to go by
    assert "evaluating at frame 0 (2 episodes): the untrained policy, before any update" in r.stdout


def test_help_shows_per_task_defaults_as_such():
    from harness import cli
    import sear
    import train
    text = " ".join(cli.build_parser(train.Config, sear.METHODS, full=True).format_help().split())
    assert "(default: 4096; per task: 512 on the task sets (metaworld-mt3, -mt10, -mt50); 2048 with --method ef)" in text
    assert ("(default: 500000; per task: 2000000 on the task sets; on dm_control tasks DrQ-v2's by task: 100000 "
            "(easy), 500000") in text
    assert "frames between evaluations (snapshots follow --snapshot-minutes) (default: 10000)" in text
    assert "(default: 1.0; per task: 0.9 or 0.6 with --drm on DrM's tasks" in text  # max-perturb


def test_resume_refuses_to_change_the_experiment(tmp_path):
    r = run(["--env", "cup-catch", *TINY, "--frames", "16", "--eval-every", "100"], tmp_path)
    assert r.returncode == 0, r.stderr[-2000:]
    run_dir = only_run_dir(tmp_path)
    before = tree_digest(run_dir)
    r = run(["--resume", str(run_dir), "--method", "drq"], tmp_path)
    assert r.returncode != 0 and "cannot change on --resume" in r.stderr
    assert len(r.stderr.strip().splitlines()) == 1
    assert tree_digest(run_dir) == before


SUITES = ["walker-walk-distracting", "metaworld-door-open", "kitchen-kettle", "adroit-door"]
EVERY_SUITE = """
import contextlib, io, json, sys
import train
said = {}
for name, root in json.loads(sys.argv[1]):
    err = io.StringIO()
    with contextlib.redirect_stderr(err):
        code = train.main(["--run-root", root, "--env", name, *json.loads(sys.argv[2])])
    said[name] = [code, err.getvalue()]
print(json.dumps(said))
"""


def test_smoke_run_on_every_suite(tmp_path):
    """One run of every rendering suite (an episode ends before the last step: updates run), the four
    in one process (one start of torch and MuJoCo)."""
    args = [*TINY, "--frames", "16", "--seed-frames", "8", "--eval-every", "100", "--max-episode-steps", "4"]
    roots = [(name, str(tmp_path / name)) for name in SUITES]
    env = {**os.environ, "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl"), "PYTHONPATH": str(ROOT)}
    r = subprocess.run([sys.executable, "-c", EVERY_SUITE, json.dumps(roots), json.dumps(args)], capture_output=True,
                       text=True, timeout=900, cwd=tmp_path, env=env)
    assert r.returncode == 0, r.stderr[-2000:]
    said = json.loads(r.stdout.strip().splitlines()[-1])
    for name in SUITES:
        code, err = said[name]
        assert code == 0, (name, err[-2000:])
        (run_dir,) = (tmp_path / name).iterdir()
        train = rows(run_dir / "train.csv")
        assert train and train[-1]["mask_loss"] != ""
        if not name.endswith("distracting"):  # the manipulation suites report success
            assert "success" in train[0] and "success" in rows(run_dir / "eval.csv")[0]
        # Without --backgrounds, every Distracting Control run says its backgrounds are not the paper's.
        assert ("not the paper's DAVIS-2017 videos" in err) == name.endswith("distracting"), (name, err)


def straight_and_resumed(common, tmp_path):
    """(run dir, run dir, the resume's result): sear.py `common` for 80 frames in one go, and for 48
    frames then --resume to 80."""
    straight, split = tmp_path / "straight", tmp_path / "split"
    for d in (straight, split):
        d.mkdir()
    assert run([*common, "--frames", "80"], straight).returncode == 0
    assert run([*common, "--frames", "48"], split).returncode == 0
    split_dir = only_run_dir(split)
    r = run(["--resume", str(split_dir), "--frames", "80"], split)
    assert r.returncode == 0, r.stderr[-2000:]
    return only_run_dir(straight), split_dir, r


@pytest.mark.parametrize("method, terms", [("sear", ["recon_loss", "mask_loss"]), ("curl", ["curl_loss"])])
def test_resume_replays_exactly_what_an_uninterrupted_run_does(tmp_path, method, terms):
    """Snapshots sit between episodes and every episode's reset seed follows from its number, so
    48 frames + resume to 80 must equal 80 frames in one go: same evaluations, losses, weights (CURL:
    also its key's EMA phase and its own Adam, saved with its networks)."""
    import torch

    common = ["--env", "walker-walk", "--method", method, "--seed", "5", "--save-buffer", *TINY]
    straight_dir, split_dir, _ = straight_and_resumed(common, tmp_path)

    def table(run_dir, name, cols):
        return [[r[c] for c in cols] for r in rows(run_dir / name)]

    losses = ["frame", "return", "critic_loss", "actor_loss", *terms]
    assert table(split_dir, "eval.csv", ["frame", "return"]) == table(straight_dir, "eval.csv", ["frame", "return"])
    assert table(split_dir, "train.csv", losses) == table(straight_dir, "train.csv", losses)
    a = torch.load(straight_dir / "snapshot.pt", weights_only=False)["agent"]
    b = torch.load(split_dir / "snapshot.pt", weights_only=False)["agent"]
    assert all(torch.equal(a["encoder"][k], b["encoder"][k]) for k in a["encoder"])
    if method == "curl":
        assert all(torch.equal(v, b["aux"][k]) for k, v in a["aux"].items() if k != "_extra_state")
        assert a["aux"]["_extra_state"][0] == b["aux"]["_extra_state"][0] > 0  # the updates so far


@pytest.mark.parametrize("action_repeat", [1, 2])
def test_training_loop_gives_the_agent_agent_steps(tmp_path, monkeypatch, action_repeat):
    """As DrQ-v2 (train.py train, drqv2.py act): the agent acts from step 0, uniformly for the first
    --exploration-steps AGENT steps, then with the actor plus noise; updates start once the seed
    FRAMES are in and an episode has ended (DrQ-v2's loader draws from stored episodes only). At action
    repeat 2 the 12 seed frames are the 6 uniform steps, and the first 8-step episode ends at step 8;
    at 1 the actor, not yet updated, acts for the seed frames' second half."""
    import numpy as np
    import torch

    from harness import cli
    import sear
    import train
    seen = {"act": [], "update": [], "actions": []}
    act, update, add, sample = sear.Agent.act, sear.Agent.update, sear.ReplayBuffer.add, sear.TruncatedNormal.sample
    monkeypatch.setattr(sear.Agent, "act", lambda self, p, m, step, eval_mode: (
        None if eval_mode else seen["act"].append(step), act(self, p, m, step, eval_mode))[1])
    monkeypatch.setattr(sear.Agent, "update", lambda self, batch, step: (
        seen["update"].append(step), update(self, batch, step))[1])
    monkeypatch.setattr(sear.ReplayBuffer, "add", lambda self, action, *rest: (
        seen["actions"].append(np.array(action)), add(self, action, *rest))[1])
    # Acting (clip None), the actor's sample is a constant: an action equal to it came from the actor.
    monkeypatch.setattr(sear.TruncatedNormal, "sample", lambda self, clip=None, noise=None: (
        torch.full_like(self.loc, 0.125) if clip is None else sample(self, clip, noise)))
    cfg, run, _ = cli.parse_args(["--env", "cartpole-swingup", "--method", "drq", "--action-repeat",
                                  str(action_repeat), "--run-root", str(tmp_path / "runs"), "--threads", "1",
                                  *tiny("drq"),
                                  "--seed-frames", "12", "--exploration-steps", "6"],
                                 train.Config, sear.METHODS)
    train.train(cfg, run)
    last = cfg.frames // action_repeat - 1
    assert seen["act"] == list(range(last + 1))
    source = ["actor" if np.all(a == 0.125) else "uniform" for a in seen["actions"]]
    assert source == ["uniform"] * 6 + ["actor"] * (last + 1 - 6)
    first = max(cfg.seed_frames // action_repeat, 8)  # after the seed frames and episode 0: 12 (repeat 1), 8 (2)
    assert seen["update"] and seen["update"][0] == first and seen["update"][-1] <= last
    assert all(s % cfg.update_every == 0 for s in seen["update"])
    (run_dir,) = (tmp_path / "runs").iterdir()
    assert json.loads((run_dir / "config.json").read_text())["std_steps"] == 100_000   # DrQ-v2: easy task


def test_prefetch_on_cpu_trains(tmp_path):
    """--prefetch on (CUDA's default) runs the same loop with the sampler in a background thread."""
    r = run(["--env", "cup-catch", "--method", "sear", "--prefetch", "on", "--threads", "1", *TINY], tmp_path)
    assert r.returncode == 0, r.stderr[-2000:]
    train = rows(only_run_dir(tmp_path) / "train.csv")
    assert train[-1]["critic_loss"] != "" and train[-1]["mask_loss"] != ""


def test_resume_from_a_snapshot_before_its_frames_evaluation_evaluates_once(tmp_path):
    """A snapshot at an episode end precedes that frame's evaluation. If the run died after the
    evaluation's row was written, the resumed run evaluates that frame again: the old row goes to the
    side file, so eval.csv has every frame once."""
    import torch
    r = run(["--env", "walker-walk", "--method", "drq", *tiny("drq"), "--eval-every", "16"], tmp_path)  # evaluations
    # at the episode ends (8 steps x action repeat 2)
    assert r.returncode == 0, r.stderr[-2000:]
    run_dir = only_run_dir(tmp_path)
    assert [int(x["frame"]) for x in rows(run_dir / "eval.csv")] == [0, 16, 32, 48]
    snap = torch.load(run_dir / "snapshot.pt", weights_only=False)
    # As if killed after the snapshot at the frame-16 episode end and the frame-16 evaluation's row:
    snap["counters"].update(step=8, episode=1, next_eval=16, last_eval_frame=0, mid_episode=False)
    torch.save(snap, run_dir / "snapshot.pt")
    r = run(["--resume", str(run_dir)], tmp_path)
    assert r.returncode == 0, r.stderr[-2000:]
    assert [int(x["frame"]) for x in rows(run_dir / "eval.csv")] == [0, 16, 32, 48]
    side = list(run_dir.glob("eval.after_snapshot_*.csv"))
    assert len(side) == 1 and [int(x["frame"]) for x in rows(side[0])] == [16, 32, 48]


def test_runs_started_in_the_same_second_get_their_own_run_dirs(tmp_path, monkeypatch):
    """Two seeds-alike runs launched together: the second must not crash on the first's directory,
    even when the other process creates it between a check and the mkdir (the race is simulated)."""
    sys.path.insert(0, str(ROOT))
    from harness import experiment, runenvs
    monkeypatch.setattr(experiment.time, "strftime", lambda fmt: "20261123-000000")
    first = experiment.new_run_dir(str(tmp_path), "walker-stand__sear__1")
    monkeypatch.setattr(experiment.os.path, "exists", lambda p: False)  # the other process wins the race
    second = experiment.new_run_dir(str(tmp_path), "walker-stand__sear__1")
    third = experiment.new_run_dir(str(tmp_path), "walker-stand__sear__1")
    assert len({first, second, third}) == 3 and all(os.path.isdir(p) for p in (first, second, third))


@pytest.mark.skipif(platform.libc_ver()[0] != "glibc", reason="mallopt's settings are glibc's")
def test_configure_allocator_keeps_a_freed_block_for_the_next_malloc():
    """cli.configure_allocator (called first by cli.main): a freed 64 MB block stays in the heap and the
    next malloc of that size reuses it, where glibc's defaults unmap it and fault a new one in (16384
    pages of 4 KB): what the update's activations would pay at every update."""
    code = """
import ctypes, resource, sys
from harness import cli
libc = ctypes.CDLL(None)
libc.malloc.restype, libc.free.argtypes = ctypes.c_void_p, [ctypes.c_void_p]
def touch_and_free():
    p = libc.malloc(64 << 20)
    ctypes.memset(p, 1, 64 << 20)
    libc.free(p)
configured = cli.configure_allocator() if sys.argv[1] == "on" else None
touch_and_free()
before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
touch_and_free()
print(configured, resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
"""
    faults = {}
    for setting in ("on", "off"):
        env = {k: v for k, v in os.environ.items() if k != "GLIBC_TUNABLES"}
        r = subprocess.run([sys.executable, "-c", code, setting], capture_output=True, text=True, cwd=ROOT, env=env,
                           timeout=120)
        assert r.returncode == 0, r.stderr
        configured, faults[setting] = r.stdout.split()
        assert configured == {"on": "True", "off": "None"}[setting]
    assert int(faults["on"]) < 100 and int(faults["off"]) > 10_000, faults


# ---------------------------------------------------------------- what a newcomer types
def never_train(*args):
    raise AssertionError("sear.py accepted the flags and started training")


def main_in_process(argv, capsys, tmp_path, monkeypatch):
    """sear.py's exit code and stderr, in this process, for inputs it refuses before training."""
    import train
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(train, "train", never_train)
    code = train.main(argv)
    return code, capsys.readouterr().err


def test_every_seed_a_user_can_type_is_one_line_or_works(tmp_path, capsys, monkeypatch):
    """numpy's legacy seeds (np.random.seed, dm_control's and Meta-World's RandomState) are below 2^32 and the
    eval env's seed is --seed + 100000: outside [0, 2^32 - 1 - 100000] a seed is one line, inside it trains."""
    from harness import cli
    from harness import experiment, runenvs
    assert cli.MAX_SEED + runenvs.EVAL_SEED == 2**32 - 1
    for seed in ("-1", "4294967296", str(cli.MAX_SEED + 1), "1" + "0" * 30):
        code, err = main_in_process(["--seed", seed], capsys, tmp_path, monkeypatch)
        assert code == 2 and err == f"sear.py: error: --seed must be in [0, {cli.MAX_SEED}] (numpy seeds below 2^32, " \
                                    f"and the eval env's is --seed + 100000), got {int(seed)}\n", err
    assert not (tmp_path / "runs").exists()
    r = run(["--env", "cup-catch", *TINY, "--frames", "16", "--eval-every", "100", "--seed", str(cli.MAX_SEED)],
            tmp_path)
    assert r.returncode == 0, r.stderr[-2000:]


def test_an_unknown_env_gets_the_nearest_name_before_anything_starts(tmp_path, capsys, monkeypatch):
    import envs
    code, err = main_in_process(["--env", "walkr-walk"], capsys, tmp_path, monkeypatch)
    assert code == 2 and err.count("\n") == 1
    assert err.startswith("sear.py: error: unknown env 'walkr-walk'; did you mean walker-walk? valid: walker-walk, ")
    assert envs.main(["--list", "--envs", "cheetah-rn"]) == 2
    assert "unknown env 'cheetah-rn'; did you mean cheetah-run? valid: " in capsys.readouterr().err


def test_int_flags_take_whole_numbers_written_as_floats(tmp_path, capsys, monkeypatch):
    from harness import cli
    import sear
    import train
    monkeypatch.chdir(tmp_path)
    cfg, _, _ = cli.parse_args(["--frames", "1e6", "--replay-size", "2.5e5", "--seed", "1E3"], train.Config,
                               sear.METHODS)
    assert (cfg.frames, cfg.replay_size, cfg.seed) == (1_000_000, 250_000, 1000)
    assert all(type(v) is int for v in (cfg.frames, cfg.replay_size, cfg.seed))
    for value, message in (("1.5", "argument --frames: invalid int value: '1.5' is not a whole number"),
                           ("2.5e0", "argument --frames: invalid int value: '2.5e0' is not a whole number"),
                           ("inf", "argument --frames: invalid int value: 'inf' is not a whole number"),
                           ("ten", "argument --frames: invalid int value: 'ten'")):
        code, err = main_in_process(["--frames", value], capsys, tmp_path, monkeypatch)
        assert code == 2 and err == f"sear.py: error: {message}\n", err


def test_a_replay_smaller_than_the_seed_phase_is_refused_in_one_line(tmp_path, capsys, monkeypatch):
    """Learning starts once the replay holds the seed frames' steps: a smaller replay would run to the end
    without one update."""
    code, err = main_in_process(["--replay-size", "10"], capsys, tmp_path, monkeypatch)
    assert code == 2 and err == ("sear.py: error: --replay-size 10 is smaller than the 2000 steps of --seed-frames "
                                 "4000 (action repeat 2): learning would never start\n"), err
    code, err = main_in_process(["--env", "kitchen-kettle", "--replay-size", "3999"], capsys, tmp_path, monkeypatch)
    assert code == 2 and "than the 4000 steps of --seed-frames 4000 (action repeat 1)" in err
    assert not (tmp_path / "runs").exists()


def test_one_episode_is_said_in_the_singular(tmp_path):
    r = subprocess.run([sys.executable, str(ROOT / "toy_pointmass.py"), "--quick", "--eval-episodes", "1",
                        "--train-episodes", "20", "--out", str(tmp_path / "toy")], capture_output=True, text=True,
                       timeout=300)
    assert r.returncode == 0, r.stderr
    assert "(1 eval episode each)" in r.stdout and "episodes" not in r.stdout.splitlines()[0]


def test_make_env_defaults_are_the_runs():
    """envs.make_env called without a setting builds what sear.py builds by default (Distracting Control:
    medium, 8 backgrounds, not all of them)."""
    import inspect

    import envs
    from harness import experiment, runenvs
    params = inspect.signature(envs.make_env).parameters
    run = experiment.EnvConfig()
    shared = [name for name in params if hasattr(run, name) and name != "backgrounds"]  # None there, '' here
    assert "difficulty" in shared and len(shared) >= 8
    assert {name: params[name].default for name in shared} == {name: getattr(run, name) for name in shared}
