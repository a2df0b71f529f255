"""benchmarks/drqv2_loader.py: sear.py's training with batches drawn as the official DrQ-v2 loader draws
them (one worker's episodes per batch, ended episodes only, whole n-step windows)."""
import json
import sys

import numpy as np

from tests.test_official_compare import ROOT, TINY, run

sys.path.insert(0, str(ROOT / "benchmarks"))
import drqv2_loader  # noqa: E402

SCRIPT = ROOT / "benchmarks" / "drqv2_loader.py"


OBS = {"pixels": np.zeros((9, 2, 2), np.uint8), "mask": np.zeros((3, 2, 2), bool)}


def steps(b):
    """Agent steps so far: each episode adds a reset slot to the ring."""
    return b.t - int(b.first[:b.t].sum())


def until_worker(b, worker):
    """Steps of the running episode until it is `worker`'s turn (sampling comes at even agent steps)."""
    while (steps(b) // 2) % 4 != worker or steps(b) % 2:
        b.add(0.0, 1.0, False, OBS)


def filled(lengths, running):
    """A buffer holding ended episodes of the given lengths, then a running one of `running` steps."""
    b = drqv2_loader.LoaderReplay(200, (3, 2, 2), 1, frame_stack=3, nstep=3, discount=0.99)
    obs, spans = OBS, []
    for n in [*lengths, running]:
        spans.append((b.t, b.t + n))  # (reset slot, last step's slot)
        b.add_first(obs)
        for _ in range(n):
            b.add(0.0, 1.0, False, obs)
    return b, spans


def test_each_batch_is_one_workers_ended_episodes_and_whole_windows():
    lengths = [5, 6, 4, 7, 5, 2, 6]  # episode 5 (2 steps) has no whole 3-step window
    b, spans = filled(lengths, running=4)
    rng = np.random.default_rng(0)
    seen = []
    until_worker(b, 0)
    for update in range(4):  # one update every two agent steps: the workers take turns
        if update:
            b.add(0.0, 1.0, False, OBS), b.add(0.0, 1.0, False, OBS)
        starts = set(b.draw_starts(4000, rng, lo=0).tolist())
        worker = (steps(b) // 2) % 4
        allowed = {s for e, (first, last) in enumerate(spans[:-1]) if e % 4 == worker
                   for s in range(first, last - 3 + 1)}
        assert starts == allowed, (worker, sorted(starts), sorted(allowed))  # every whole window, nothing else
        seen.append(worker)
    assert seen == [0, 1, 2, 3]


def test_episodes_are_drawn_uniformly_not_their_steps():
    b, spans = filled([3, 30, 3, 3, 3], running=1)  # worker 0 holds episode 0 (1 window) and 4 (1 window)
    until_worker(b, 0)
    starts = b.draw_starts(20000, np.random.default_rng(1), lo=0)
    assert set(starts.tolist()) == {spans[0][0], spans[4][0]}
    assert abs(np.mean(starts == spans[0][0]) - 0.5) < 0.02
    b2, spans2 = filled([30, 3, 3, 3, 3], running=1)  # worker 0: episode 0 (28 windows) and 4 (1 window)
    until_worker(b2, 0)
    starts = b2.draw_starts(20000, np.random.default_rng(1), lo=0)
    assert abs(np.mean(starts == spans2[4][0]) - 0.5) < 0.02  # half the batch from the short episode


def test_no_sample_before_an_episode_ends():
    b, _ = filled([], running=20)
    assert not b.can_sample()
    b, _ = filled([3], running=0)
    assert b.can_sample()


def test_a_run_trains_marks_its_dir_and_resumes_only_through_the_script(tmp_path):
    common = ["--env", "cartpole-balance_sparse", "--save-buffer", "--run-root", tmp_path / "runs", *TINY]
    r = run(SCRIPT, "--workers", "2", "--", *common, cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    run_dir = next((tmp_path / "runs").iterdir())
    assert json.loads((run_dir / "drqv2_loader.json").read_text()) == {"workers": 2}
    rows = (run_dir / "train.csv").read_text().splitlines()
    assert len(rows) > 2 and rows[-1].split(",")[5] != ""  # updates ran: a critic loss is logged
    r = run(SCRIPT, "--", "--resume", run_dir, "--frames", "64", cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    plain = run(ROOT / "sear.py", *common, cwd=tmp_path)  # a run of sear.py itself has no marker
    assert plain.returncode == 0, plain.stderr
    other = next(d for d in (tmp_path / "runs").iterdir() if d != run_dir)
    r = run(SCRIPT, "--", "--resume", other, "--frames", "64", cwd=tmp_path)
    assert r.returncode == 2 and r.stderr.count("\n") == 1 and "drqv2_loader.json" in r.stderr, r.stderr
    r = run(SCRIPT, "--workers", "0", cwd=tmp_path)
    assert r.returncode == 2 and r.stderr.startswith("drqv2_loader.py: ") and r.stderr.count("\n") == 1


def test_an_interrupted_run_names_this_script_to_resume_with(tmp_path):
    code = ("import sys; sys.path.insert(0, 'benchmarks'); import drqv2_loader; from harness import experiment; drqv2_loader.install(4); "
            "print(experiment.interrupt_message('/r/x', 5000, 'between episodes', 5000, 10, 'stopped by SIGTERM'))")
    r = run("-c", code, cwd=ROOT)
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip().endswith("continue with: python benchmarks/drqv2_loader.py -- --resume /r/x"), r.stdout
