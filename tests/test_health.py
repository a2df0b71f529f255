"""A first hour that tells the truth: the progress line's ETA and the run's cost, the
health checks (a value that is not finite stops the run in one line; a collapsed actor or a
diverging critic is warned of, once), the disk a run needs, and no run directory left without a
snapshot. Unit tests of experiment.Progress / Health / FiniteActions, and `python sear.py ...` end
to end (tiny budgets, CPU): drivers patch sear.py's agent to make a failure happen on cue."""
import math
import os
import re
import subprocess
import sys

import numpy as np
import pytest

from tests.test_firstweek import ENV, ROOT, TINY, one_line, only_dir, rows, run

# No evaluations but at frame 0 and the end, episodes of 8 steps.
QUIET = [*TINY, "--eval-every", "100000", "--log-every", "0"]


def patched_run(tmp_path, patch: str, args, timeout=600):
    """sear.py's main with `patch` (Python, run after `import cli, experiment, sear, torch, train`) applied."""
    script = tmp_path / "patched_sear.py"
    script.write_text("import sys\nimport sear, torch, train\nfrom harness import cli, experiment\n" + patch
                      + "\nsys.exit(train.main(sys.argv[1:]))\n")
    return subprocess.run([sys.executable, str(script), *map(str, args)], capture_output=True, text=True,
                          timeout=timeout, cwd=tmp_path, env={**ENV, "PYTHONPATH": str(ROOT)})


def snapshot(run_dir):
    import torch
    return torch.load(run_dir / "snapshot.pt", weights_only=False)


# ----------------------------------------------------------------------------------- the ETA
def test_the_eta_counts_only_the_updates_and_evaluations_it_has_timed(capsys):
    from harness import experiment
    now, frame = [0.0], [0]
    p = experiment.Progress(total=100_000, every=0, eval_every=10_000, clock=lambda: now[0])

    def steps(n, seconds, updates=0):  # n env steps of 2 frames, `updates` updates in each
        for _ in range(n):
            now[0] += seconds
            p.updates += updates
            frame[0] += 2
            p.measure(frame[0])

    steps(500, 0.01)  # the seed phase: the env alone, 100x faster than training with updates
    p.eval_seconds = [60.0]
    assert p.learning_fps() is None and p.eta(frame[0], next_eval=10_000) == math.inf
    p.show(frame[0], "ep 3 step 10", p.eta(frame[0], next_eval=10_000))
    assert "| ETA measuring | ep 3 step 10" in capsys.readouterr().out
    steps(2, 30.0, updates=1)  # the first updates build kernels: not timed
    steps(9, 1.0, updates=1)  # 9 updates timed over 9 s: not yet MEASURE_UPDATES (10 after the warm-up) ...
    assert p.learning_fps() is None and p.cost(frame[0], 10_000) is None
    steps(1, 1.0, updates=1)  # ... now: 2 frames/s
    assert p.learning_fps() == 2.0
    left = 100_000 - frame[0]
    assert p.eta(frame[0], next_eval=10_000) == left / 2.0 + 10 * 60.0  # 10k, 20k, ..., 90k and the final one
    assert p.cost(frame[0], 10_000) == (f"cost on this device: 2 frames/s with updates (timed over 10 updates), so "
                                        f"the {left:,} frames left take 13h 44m, and the 10 evaluations left 10m 00s "
                                        f"(1m 00s each): about 13h 54m in all")
    assert p.cost(frame[0], 10_000) is None  # said once
    # What a snapshot keeps: a resumed run has an ETA at once, in days where it is days.
    resumed = experiment.Progress(total=1_000_000, every=0, eval_every=10_000, saved=p.state())
    assert resumed.eta(20_000, next_eval=20_000) == 980_000 / 2.0 + 99 * 60.0
    assert experiment.duration(resumed.eta(20_000, next_eval=20_000)) == "5d 17h"
    assert [experiment.duration(s) for s in (7.4, 125, 3 * 3600 + 61, math.inf)] == ["7s", "2m 05s", "3h 01m",
                                                                                    "measuring"]


def test_the_eta_counts_the_final_evaluation_down_as_it_runs(capsys, monkeypatch):
    """README's first run (1,300 frames, an evaluation of one 500-step episode every 1,000 and the
    final one at 1,300) read the same ETA all through a final evaluation three times as long as the
    one before: the evaluation under way, the final one as a scheduled one, counts at its own pace,
    step by step."""
    import types
    from harness import experiment
    now = [0.0]
    monkeypatch.setattr(experiment.time, "time", lambda: now[0])
    cfg = types.SimpleNamespace(frames=1300, eval_every=1000, seed_frames=1000, action_repeat=2)
    console = experiment.Console(cfg, types.SimpleNamespace(log_every=0), {"learning_fps": 2.0})

    def evaluate(frame, seconds, next_eval):  # one episode of 500 steps: the ETA at every step
        console.start_eval(frame, 1, "")
        for t in range(1, 501):
            now[0] += seconds / 500
            console.show_eval(frame, 0, t, "", next_eval)
        console.end_eval(frame, 1)
        return re.findall(r"\| ETA (.+?) \| eval 1/1 step", capsys.readouterr().out)

    evaluate(1000, 60.0, next_eval=1000)
    console.show_step(1200, 1, 100, next_eval=2000)
    # 100 frames at 2 frames/s, and the final evaluation at the length of the one before
    assert re.findall(r"\| ETA (.+?) \|", capsys.readouterr().out) == ["1m 50s"]
    final = evaluate(1300, 180.0, next_eval=2000)  # three times as long: at its own pace
    assert (final[0], final[249], final[449], final[-1]) == ("3m 00s", "1m 30s", "18s", "0s")


def test_off_a_terminal_the_line_is_whole_and_printed_every_log_every_seconds(capsys, monkeypatch):
    """A log file, SLURM, a pipe: each line whole (tqdm's redraws, no carriage return, no trim to
    the width), at most every --log-every seconds, and at every episode end."""
    import tqdm.std
    from harness import experiment
    now = [0.0]
    monkeypatch.setattr(tqdm.std, "time", lambda: now[0])
    monkeypatch.setenv("COLUMNS", "40")
    p = experiment.Progress(total=100_000, every=10, eval_every=10_000, clock=lambda: now[0])
    for step in range(1, 31):  # 30 s, a step a second; an episode ends at step 25
        now[0] += 1.0
        p.measure(2 * step)
        text = "ep 0 return 1.0" if step == 25 else f"ep 0 step {step}"
        p.show(2 * step, text, math.inf, force=step == 25)
    p.say("snapshot at frame 60")
    p.close()
    assert capsys.readouterr().out.splitlines() == [
        f"frame {frame}/100000 ({frame / 1000:.1f}%) | 2.0 fps | ETA measuring | ep 0 {what}"
        for frame, what in ((2, "step 1"), (22, "step 11"), (42, "step 21"), (50, "return 1.0"))
    ] + ["snapshot at frame 60"]


def test_on_a_terminal_the_bar_stays_in_place_under_the_lines_said(monkeypatch):
    """A terminal: the bar redrawn in place and trimmed to its width; a line said goes above it."""
    import io
    from harness import experiment

    class Terminal(io.StringIO):  # 60 columns
        encoding = "utf-8"

        def isatty(self):
            return True

        def fileno(self):
            return 1
    monkeypatch.setattr(sys, "stdout", Terminal())
    monkeypatch.setattr(os, "get_terminal_size", lambda fd: os.terminal_size((61, 24)))
    p = experiment.Progress(total=1000, every=10, eval_every=100)
    p.show(500, "ep 0 step 250", 60.0)
    p.say("snapshot at frame 500")
    p.close()
    screen = []  # what the terminal shows: each carriage return writes over the line from its start
    for line in sys.stdout.getvalue().split("\n"):
        text = ""
        for part in line.split("\r"):
            text = part + text[len(part):]
        screen.append(text.rstrip())
    bar = "frame 500/1000 (50.0%) ██████       | 0.0 fps | ETA 1m 00s |"  # trimmed to the width
    assert screen == ["snapshot at frame 500", bar, ""]


def test_speeds_survive_a_resume_and_the_cost_is_said_once_measured(tmp_path):
    """A run measures its learning speed (here from its first updates: MEASURE_SECONDS 0) and says what
    the rest costs; its snapshot keeps the speeds, and the resumed run has an ETA from its first line."""
    r = patched_run(tmp_path, "experiment.Progress.MEASURE_SECONDS = 0.0",
                    ["--run-root", tmp_path / "runs", "--env", "walker-walk", *QUIET, "--frames", "64"])
    assert r.returncode == 0, r.stderr[-3000:]
    assert len(re.findall(r"^cost on this device: [\d.]+ frames/s with updates \(timed over 10 updates\), so the "
                          r"[\d,]+ frames left take .+ in all$", r.stdout, re.M)) == 1, r.stdout
    assert re.search(r"^ETA: measuring; the cost of this run is said once its first updates are timed \(they start at "
                     r"frame 12, after the frame-0 evaluation of the untrained policy\)$", r.stdout, re.M), r.stdout
    run_dir = only_dir(tmp_path / "runs")
    speeds = snapshot(run_dir)["progress"]
    assert speeds["learning_fps"] > 0 and speeds["eval_seconds"] > 0
    r = run(["--resume", run_dir, "--frames", "96"], tmp_path)
    assert r.returncode == 0, r.stderr[-3000:]
    assert re.search(r"^speed when last run: [\d.]+ frames/s with updates, \S+ per evaluation; ETA \S+", r.stdout, re.M)
    first = next(line for line in r.stdout.splitlines() if line.startswith("frame "))
    assert "ETA measuring" not in first, r.stdout


# ---------------------------------------------------------------------- health: unit checks
def test_a_collapsed_actor_is_warned_of_once_and_the_recorded_healthy_runs_are_not():
    """The thresholds against EXPERIMENTS.md's Rung PC: the official seed 2 after its collapse (every
    mean action at the bound, spread below 4e-9) is warned of; our DrQ seed 2 at 8k-16k frames (97-99%
    saturated but spread 0.15-0.25; it recovered), seed 3 solving the task bang-bang (22-44% / 0.83-0.89)
    and SEAR's early phase (one action in every state, none at the bound; it recovered) are not."""
    from harness import experiment
    window = experiment.Health.COLLAPSE_WINDOW
    health = experiment.Health(discount=0.99)
    fired = [health.check({"actor_saturated": 1.0, "action_spread": 3e-9, "q": 20.0}) for _ in range(window + 50)]
    assert [i for i, f in enumerate(fired) if f] == [window - 1]
    (kind, message), = fired[window - 1]
    assert kind == "actor collapsed" and "100.0% of its mean actions sat at exactly +-1" in message
    for saturated, spread in ((0.99, 0.154), (0.44, 0.83), (0.0, 1e-7)):
        health = experiment.Health(discount=0.99)
        assert not any(health.check({"actor_saturated": saturated, "action_spread": spread, "q": 20.0})
                       for _ in range(2 * window))


def test_a_diverging_critic_is_warned_of_against_the_largest_return_any_policy_can_have():
    from harness import experiment
    window = experiment.Health.DIVERGE_WINDOW
    health = experiment.Health(discount=0.99)
    health.see_rewards(np.array([0.0, 2.0, 1.5]))  # cartpole at action repeat 2: at most 2 per agent step
    assert health.q_bound() == pytest.approx(200.0)
    assert not any(health.check({"q": 190.0}) for _ in range(2 * window))  # a solved run is near the bound
    health = experiment.Health(discount=0.99)
    health.see_rewards(np.array([2.0]))
    fired = [health.check({"q": -1e16 if i % 10 else 50.0}) for i in range(2 * window)]  # --lr 10's size of Q
    assert [i for i, f in enumerate(fired) if f] == [window - 1]
    assert fired[window - 1][0][0] == "critic diverging"
    health = experiment.Health(discount=0.99)
    health.see_rewards(np.array([20.0]))  # Meta-World: up to 10 per env step, 20 per agent step
    assert not any(health.check({"q": 500.0}) for _ in range(2 * window))


def test_a_value_that_is_not_finite_raises_and_a_non_finite_action_never_reaches_the_env():
    import gymnasium as gym
    from harness import cli
    from harness import experiment, runenvs
    health = experiment.Health(discount=0.99)
    health.check({"critic_loss": 1.0, "q": 1.0})
    with pytest.raises(cli.NonFinite, match=r"^critic_loss is inf at update 2 of this process$"):
        health.check({"critic_loss": math.inf, "q": 1.0})

    class Env(gym.Env):
        action_space = gym.spaces.Box(-1, 1, (3,))
        observation_space = gym.spaces.Box(-1, 1, (1,))
        steps = 0

        def step(self, action):
            self.steps += 1
            return np.zeros(1), 0.0, False, False, {}

    env = runenvs.FiniteActions(Env())
    env.step(np.zeros(3, np.float32))
    with pytest.raises(cli.NonFinite, match=r"^2 of the 3 entries of the actor's action are not finite$"):
        env.step(np.array([np.nan, 0.5, np.inf], np.float32))
    assert env.unwrapped.steps == 1


# ------------------------------------------------------------------------ health: end to end
def test_a_loss_that_is_not_finite_stops_the_run_in_one_line_and_the_last_snapshot_stands(tmp_path):
    """c1 = 1e38 (a finite flag) makes Eq. 6 overflow at the first update: the second update's losses
    are NaN (frame 24). The metrics stay on the device until a log line, but the encoder went NaN with
    them: the next action (frame 26) is NaN and stops the run before it reaches MuJoCo (no PhysicsError),
    with exit 1 and the first value that was not finite as the cause; the snapshot of frame 16 (before
    the first update) stands and holds finite weights."""
    r = run(["--run-root", tmp_path / "runs", "--env", "walker-walk", *QUIET, "--frames", "400", "--recon-coef", "1e38",
             "--seed-frames", "20", "--exploration-steps", "0", "--snapshot-minutes", "0"], tmp_path)
    run_dir = only_dir(tmp_path / "runs")
    assert r.returncode == 1, r.stderr[-3000:]
    assert re.fullmatch(r"sear.py: error: the run diverged at frame 26: recon_loss is nan at update 2 of this process "
                        r"\(parameters no longer finite: encoder, aux\); it stopped before that reached the simulator; "
                        r"the last snapshot \(frame 16\) stands: python sear.py --resume " + re.escape(str(run_dir))
                        + r" continues from it \(with --save-buffer it replays the same updates\): docs/health.md",
                        one_line(r)), r.stderr
    import torch
    assert all(torch.isfinite(t).all() for part in ("encoder", "actor", "critic", "aux")
               for t in snapshot(run_dir)["agent"][part].values())
    assert all("nan" not in row.values() for row in rows(run_dir / "train.csv"))


def test_an_action_that_is_not_finite_stops_the_run_and_a_run_without_a_snapshot_leaves_no_folder(tmp_path):
    """An actor whose weights went NaN while its losses still looked finite: the action it gives is
    refused before env.step (FiniteActions), where MuJoCo would raise PhysicsError (mjWARN_BADCTRL)."""
    patch = ("real = sear.Agent.update\n"
             "def poisoned(self, batch, step):\n"
             "    metrics = real(self, batch, step)\n"
             "    with torch.no_grad():\n"
             "        for p in self.actor.parameters():\n"
             "            p.fill_(float('nan'))\n"
             "    return metrics\n"
             "sear.Agent.update = poisoned\n")
    r = patched_run(tmp_path, patch, ["--run-root", tmp_path / "runs", "--env", "walker-walk", *QUIET,
                                      "--frames", "400", "--exploration-steps", "0"])
    assert r.returncode == 1, r.stderr[-3000:]
    assert re.fullmatch(r"sear.py: error: the run diverged at frame 18: 6 of the 6 entries of the actor's action are "
                        r"not finite \(parameters no longer finite: actor\); it stopped before that reached the "
                        r"simulator; \S+ had no snapshot yet and was removed; start again with other settings "
                        r"\(a lower --lr, smaller loss weights\): docs/health.md", one_line(r)), r.stderr
    assert list((tmp_path / "runs").iterdir()) == []  # nothing to resume: no dead run directory


def test_collapse_and_divergence_are_warned_of_once_on_the_progress_line_and_stderr(tmp_path):
    """The agent's metrics replaced by a collapsed actor's and a diverging critic's (windows of 20
    updates instead of 500 / 100): each warning comes once, on stderr, and stays on the progress line."""
    patch = ("experiment.Health.COLLAPSE_WINDOW = experiment.Health.DIVERGE_WINDOW = 20\n"
             "real = sear.Agent.update\n"
             "sear.Agent.update = lambda self, batch, step: {**real(self, batch, step), 'actor_saturated': 1.0, "
             "'action_spread': 0.0, 'q': 1e16}\n")
    r = patched_run(tmp_path, patch, ["--run-root", tmp_path / "runs", "--env", "walker-walk", *QUIET,
                                      "--frames", "96"])
    assert r.returncode == 0, r.stderr[-3000:]
    warnings = [line for line in r.stderr.splitlines() if line.startswith("sear.py: warning: ")]
    assert len(warnings) == 2, r.stderr
    assert warnings[0].startswith("sear.py: warning: the actor has collapsed: over the last 20 updates 100.0% of "
                                  "its mean actions sat at exactly +-1")
    assert warnings[1].startswith("sear.py: warning: the critic diverges: the median |Q| of the last 20 updates is "
                                  "1e+16, more than 2 x the largest return any policy can have here")
    lines = [line for line in r.stdout.splitlines() if line.startswith("frame ")]
    assert lines[-1].endswith("| warning: actor collapsed | warning: critic diverging"), lines[-1]


# --------------------------------------------------------------------------------- the disk
def test_a_disk_without_room_for_a_snapshot_is_refused_before_any_compute_and_leaves_nothing(tmp_path):
    patch = ("import collections\n"
             "usage = collections.namedtuple('usage', 'total used free')\n"
             "experiment.shutil.disk_usage = lambda path: usage(10**9, 10**9 - FREE, FREE)\n")
    args = ["--run-root", tmp_path / "runs", "--env", "walker-walk", *QUIET, "--frames", "16"]
    r = patched_run(tmp_path, "FREE = 10**6\n" + patch, args)
    assert r.returncode == 2
    assert re.fullmatch(r"sear.py: error: \S+: 1.0 MB free, but a snapshot.pt of this run takes 3.7 MB: free some "
                        r"space, or give --run-root on a larger disk", one_line(r)), r.stderr
    assert list((tmp_path / "runs").iterdir()) == [] and "evaluating" not in r.stdout

    r = patched_run(tmp_path, "FREE = 5 * 10**6\n" + patch, args)  # the first snapshot fits, two do not
    assert r.returncode == 0, r.stderr[-3000:]
    assert re.fullmatch(r"sear.py: warning: \S+: 5.0 MB free, but this run's files need up to 7.3 MB more \(two "
                        r"snapshot.pt of 3.7 MB while one replaces the other\): it will stop on a full disk before its "
                        r"end, its last snapshot standing", one_line(r)), r.stderr


def test_the_disk_line_says_the_snapshot_size_it_will_write(tmp_path):
    # 32 frames: the second episode updates (the first must end before replay draws), so the snapshot holds
    # Adam's moments as the estimate counts them.
    r = run(["--run-root", tmp_path / "runs", "--env", "walker-walk", *QUIET, "--frames", "32", "--save-buffer"],
            tmp_path)
    assert r.returncode == 0, r.stderr[-3000:]
    m = re.search(r"^disk: snapshot.pt ([\d.]+) MB, buffer.npz up to ([\d.]+) MB; \S+ \S+ free in ", r.stdout, re.M)
    assert m, r.stdout
    run_dir = only_dir(tmp_path / "runs")
    assert float(m[1]) * 1e6 == pytest.approx((run_dir / "snapshot.pt").stat().st_size, rel=0.05)
    assert float(m[2]) == pytest.approx(400 * 22080 / 1e6, abs=0.05)  # --replay-size 400 x bytes per transition
