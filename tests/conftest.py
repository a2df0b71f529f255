"""Shared fixtures, the quick tier and the per-file progress lines.

`device`: the torch device of the tests that build agents and tensors, from SEAR_TEST_DEVICE (default
cpu). Those tests also carry the `device` marker, so `SEAR_TEST_DEVICE=cuda python -m pytest -m device`
runs exactly them on a GPU (benchmarks/gpu_check.sh); the sear.py subprocess tests pick CUDA by
themselves there (--device auto).

`quick`: `python -m pytest -q -m quick` checks an install end to end in under 3 minutes on 2 idle
cores (QUICK below). `FileProgress`: one line per test file as it finishes, so that a suite of an
hour or more says where it is.
"""
import os
import time

import pytest

# The quick tier, by node id (a function without its [params] takes every case; a file, every test).
# Listed here rather than as decorators in the test files, so that it reads as one list and changes
# in one place. tests/test_quick.py fails when an entry matches no test (a test renamed or moved):
# an entry that silently stopped selecting would shrink the tier without anyone seeing it.
QUICK = [
    # imports and the layering between the files
    "tests/test_layout.py",
    "tests/test_sear.py::test_encoder_shapes",
    # one act + update of every method on a tiny batch (in-process), and one with DrM
    "tests/test_baselines.py::test_every_method_builds_acts_and_updates",
    "tests/test_drm.py::test_perturb_mixes_every_linear_layer_with_a_fresh_init_and_resets_adam[sear]",
    # sear.py as a user runs it: dm_control (a run, its resume and plot.py on it), then one run per
    # rendering suite (Distracting Control, Meta-World, Kitchen, Adroit)
    "tests/test_cli.py::test_smoke_run_writes_csvs_and_snapshot_then_resume_continues",
    "tests/test_cli.py::test_smoke_run_on_every_suite",
    # one-line errors: sear.py (an env check, argparse, a value check), its did-you-mean, envs.py
    "tests/test_cli.py::test_bad_input_is_one_line_and_creates_nothing[args0-unknown env]",
    "tests/test_cli.py::test_bad_input_is_one_line_and_creates_nothing[args3-invalid choice]",
    "tests/test_cli.py::test_bad_input_is_one_line_and_creates_nothing[args10---recon-coef must be a finite "
    "number, got inf]",
    "tests/test_firstweek.py::test_a_misspelled_flag_gets_a_suggestion[--frams---frames]",
    "tests/test_envs.py::test_env_names_and_action_repeat",
    "tests/test_envs.py::test_bad_input_raises_one_line_env_error",
    "tests/test_envs.py::test_cli_bad_input_one_line_no_traceback",
    # segment.py: its command line, the IoU floor, the run's IoU watch
    "tests/test_segment.py::test_cli_process_exit_code_and_single_line",
    "tests/test_segment.py::test_train_refuses_a_model_below_the_iou_floor_unless_forced",
    "tests/test_segment.py::test_iou_watch_warns_once_when_two_evaluations_in_a_row_are_below_the_floor",
    # plot.py, sweep.py's parts that start no job (grids, keys, flag checks, the rliable report), the toy
    "tests/test_plot.py::test_cli_subprocess_writes_png_and_table",
    "tests/test_plot.py::test_no_runs_is_one_line_exit_2",
    "tests/test_sweep.py::test_named_grids_hold_the_papers_tasks_methods_seeds_and_budgets",
    "tests/test_sweep.py::test_job_key_depends_on_the_experiment_not_on_how_it_was_spelled",
    "tests/test_sweep.py::test_bad_input_fails_the_whole_sweep_up_front",
    "tests/test_sweep.py::test_report_success_rates_per_task_and_rliable_over_tasks",
    "tests/test_toy.py::test_quick_run_prints_table_and_writes_csv",
    "tests/test_toy.py::test_bad_input_one_line_nonzero_exit",
    # this list and the progress lines themselves
    "tests/test_quick.py",
]


def selects(entry: str, nodeid: str) -> bool:
    """Whether a QUICK entry (a node id, a function without its [params], a file) takes a test."""
    return nodeid == entry or nodeid.startswith((entry + "::", entry + "["))


def pytest_configure(config):
    config.addinivalue_line("markers", "device: takes the `device` fixture (SEAR_TEST_DEVICE)")
    config.addinivalue_line("markers", "quick: the install check, `python -m pytest -q -m quick` (QUICK in "
                                       "tests/conftest.py)")
    if not hasattr(config, "workerinput"):  # not inside a pytest-xdist worker: its output is not shown
        config.pluginmanager.register(FileProgress(config), "sear-file-progress")
    else:  # one of -n N workers: one torch thread each, as the sear.py runs the tests start
        import torch
        torch.set_num_threads(1)


COLLECTED = pytest.StashKey[list]()   # every test collected, before -m deselects: test_quick.py checks QUICK on it


def pytest_collection_modifyitems(config, items):
    config.stash[COLLECTED] = [item.nodeid for item in items]
    for item in items:
        if "device" in getattr(item, "fixturenames", ()):
            item.add_marker("device")
        if any(selects(entry, item.nodeid) for entry in QUICK):
            item.add_marker("quick")


class FileProgress:
    """After the last test of each file: `[ 3/26] tests/test_cli.py: 38 passed in 1 min 37 s (63/565
    tests, 4 min 2 s so far)`, the files numbered in the order they finish, the counts as pytest's
    summary counts them. Lines of their own between -q's dots; the summary and the exit code stay
    pytest's."""

    def __init__(self, config):
        self.config = config
        self.left, self.counts, self.began, self.files = {}, {}, {}, []
        self.done = self.total = self.finished = 0  # tests done, tests in all, files finished
        self.pending = None
        self.start = time.monotonic()

    @staticmethod
    def file_of(nodeid: str) -> str:
        return nodeid.split("::")[0]

    def pytest_collection_finish(self, session):
        if session.items:  # with -n N (pytest-xdist) the workers collect: see below
            self.count([item.nodeid for item in session.items])

    @pytest.hookimpl(optionalhook=True)
    def pytest_xdist_node_collection_finished(self, node, ids):
        if not self.total:  # every worker collects the same tests
            self.count(ids)

    def count(self, nodeids: list[str]) -> None:
        for nodeid in nodeids:
            path = self.file_of(nodeid)
            if path not in self.left:
                self.files.append(path)
            self.left[path] = self.left.get(path, 0) + 1
        self.total = len(nodeids)
        self.start = time.monotonic()

    def pytest_runtest_logstart(self, nodeid, location):
        self.began.setdefault(self.file_of(nodeid), time.monotonic())

    def pytest_runtest_logreport(self, report):
        category = self.config.hook.pytest_report_teststatus(report=report, config=self.config)[0]
        if category:  # "" is a passed setup or teardown
            counts = self.counts.setdefault(self.file_of(report.nodeid), {})
            counts[category] = counts.get(category, 0) + 1

    @pytest.hookimpl(trylast=True)  # after the terminal's own: its dot for this test is out
    def pytest_runtest_logfinish(self, nodeid, location):
        path = self.file_of(nodeid)
        self.done += 1
        self.left[path] = self.left.get(path, 1) - 1
        if self.left[path]:
            return
        line = self.line(path)
        if self.done == self.total:  # pytest writes -q's [100%] after the loop: this line goes after it
            self.pending = line
        else:
            self.write(line)

    @pytest.hookimpl(wrapper=True, tryfirst=True)  # outside the terminal's wrapper, which writes [100%]
    def pytest_runtestloop(self, session):
        result = yield
        if self.pending:
            self.write(self.pending)
        return result

    def line(self, path: str) -> str:
        counts = self.counts.get(path, {})
        order = [word for word in SUMMARY_ORDER if word in counts] + sorted(set(counts) - set(SUMMARY_ORDER))
        said = ", ".join(f"{counts[word]} {word}" for word in order) or "nothing run"
        now = time.monotonic()
        width = len(str(len(self.files)))
        self.finished += 1
        return (f"[{self.finished:{width}d}/{len(self.files)}] {path}: {said} in "
                f"{minutes(now - self.began.get(path, now))} ({self.done}/{self.total} tests, "
                f"{minutes(now - self.start)} so far)")

    def write(self, line: str) -> None:
        reporter = self.config.pluginmanager.get_plugin("terminalreporter")
        if reporter is None:  # -p no:terminal
            return
        reporter.ensure_newline()  # the default and -v layouts: ends the line of the file or test
        if getattr(reporter._tw, "width_of_current_line", 0):  # -q: ends the line of dots
            reporter._tw.line()
        reporter.write_line(line)


SUMMARY_ORDER = ("failed", "passed", "skipped", "xfailed", "xpassed", "error")   # as pytest's last line


def minutes(seconds: float) -> str:
    seconds = int(round(seconds))
    return f"{seconds // 60} min {seconds % 60} s" if seconds >= 60 else f"{seconds} s"


@pytest.fixture(scope="session")
def device():
    import torch  # here, not at the top: plot's and the toy's tests need no torch
    name = os.environ.get("SEAR_TEST_DEVICE", "cpu")
    try:
        dev = torch.device(name)
    except RuntimeError:
        pytest.exit(f"SEAR_TEST_DEVICE={name!r} is not a torch device (cpu, cuda, cuda:N)", returncode=2)
    if dev.type == "cuda" and not torch.cuda.is_available():
        pytest.exit(f"SEAR_TEST_DEVICE={name} but torch sees no CUDA device", returncode=2)
    return dev
