"""The quick tier (QUICK in tests/conftest.py) and the line per finished test file."""
import os
import re
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

from tests import conftest  # noqa: E402  (the conftest pytest loaded: the same module)


def collected_everywhere(request) -> list[str]:
    """The node ids of every file QUICK names: this session's collection, plus (when this run
    collected only part of the suite) a --collect-only of the files it did not."""
    nodeids = list(request.config.stash[conftest.COLLECTED])
    seen = {n.split("::")[0] for n in nodeids}
    others = sorted({entry.split("::")[0].split("[")[0] for entry in conftest.QUICK} - seen)
    others = [path for path in others if (ROOT / path).is_file()]
    if others:
        r = subprocess.run([sys.executable, "-m", "pytest", "--collect-only", "-q", "-p", "no:cacheprovider", *others],
                           cwd=ROOT, capture_output=True, text=True, timeout=300)
        assert r.returncode == 0, r.stdout[-2000:] + r.stderr[-2000:]
        nodeids += [line for line in r.stdout.splitlines() if "::" in line]
    return nodeids


def test_every_quick_entry_selects_a_test(request):
    """A test renamed, moved or re-parametrised would drop out of the tier without a sound."""
    nodeids = collected_everywhere(request)
    unmatched = [entry for entry in conftest.QUICK if not any(conftest.selects(entry, n) for n in nodeids)]
    assert unmatched == [], f"QUICK entries in tests/conftest.py that select no test: {unmatched}"
    assert len(set(conftest.QUICK)) == len(conftest.QUICK)


def test_selects_a_test_by_id_function_or_file():
    node = "tests/test_cli.py::test_smoke_run_on_every_suite[adroit-door]"
    for entry in ("tests/test_cli.py", "tests/test_cli.py::test_smoke_run_on_every_suite", node):
        assert conftest.selects(entry, node), entry
    for entry in ("tests/test_cl", "tests/test_cli.py::test_smoke_run", node + "x"):
        assert not conftest.selects(entry, node), entry


PASSING = """
import pytest
def test_one(): pass
def test_two(): pass
def test_skipped(): pytest.skip("not here")
"""
FAILING = """
import pytest
@pytest.fixture
def broken(): raise RuntimeError("setup")
def test_fails(): assert False
def test_errors(broken): pass
"""


def test_a_line_per_finished_file_between_the_dots_and_pytests_summary_unchanged(tmp_path):
    (tmp_path / "test_a.py").write_text(PASSING)
    (tmp_path / "test_b.py").write_text(FAILING)
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    r = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-p", "tests.conftest",
                        "test_a.py", "test_b.py"], cwd=tmp_path, env=env, capture_output=True, text=True, timeout=120)
    assert r.returncode == 1, r.stdout + r.stderr
    lines = r.stdout.splitlines()
    ours = [i for i, line in enumerate(lines) if line.startswith("[")]
    assert len(ours) == 2, r.stdout
    assert re.fullmatch(r"\[1/2\] test_a\.py: 2 passed, 1 skipped in \d+ s \(3/5 tests, \d+ s so far\)",
                        lines[ours[0]]), r.stdout
    assert re.fullmatch(r"\[2/2\] test_b\.py: 1 failed, 1 error in \d+ s \(5/5 tests, \d+ s so far\)",
                        lines[ours[1]]), r.stdout
    # -q's dots and its [100%] stay on lines of their own, before each file's line.
    assert lines[ours[0] - 1] == "..s" and re.fullmatch(r"FE +\[100%\]", lines[ours[1] - 1]), r.stdout
    assert re.fullmatch(r"1 failed, 2 passed, 1 skipped, 1 error in [\d.]+s", lines[-1]), r.stdout


def test_files_are_numbered_in_the_order_they_finish_under_two_workers(tmp_path):
    """With -n 2 the files finish out of their alphabetical order: each line's [k/N] counts the files
    finished so far, so k rises line by line, and its tests-so-far count never goes down."""
    (tmp_path / "test_a.py").write_text("import time\ndef test_slow(): time.sleep(3)\n")
    for name in "bcd":
        (tmp_path / f"test_{name}.py").write_text("def test_fast(): pass\n")
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    r = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-p", "tests.conftest",
                        "-n", "2", "test_a.py", "test_b.py", "test_c.py", "test_d.py"], cwd=tmp_path, env=env,
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stdout + r.stderr
    lines = [line for line in r.stdout.splitlines() if line.startswith("[")]
    assert [int(re.match(r"\[(\d+)/4\]", line)[1]) for line in lines] == [1, 2, 3, 4], r.stdout
    done = [int(re.search(r"\((\d+)/4 tests", line)[1]) for line in lines]
    assert done == sorted(done), r.stdout
    # the slow first file finishes after another: alphabetical numbers would have gone 2, 3, 1, ...
    assert lines[0].split()[1] != "test_a.py:", r.stdout
