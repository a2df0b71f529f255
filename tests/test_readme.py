"""Every command README.md shows works as written: sear.py's command lines pass its flag parsing and
checks (cli.parse_args, which starts nothing; a <run dir> is a real one), and every other script
takes the flags README gives it (its --help, or its subcommand's, lists each)."""
import re
import shlex
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
FIXTURE = ROOT / "tests" / "fixtures" / "run_ca5eab9"


def commands() -> list[list[str]]:
    """README's `python ...` command lines, one per command (`a && b` gives two), comments cut."""
    found = []
    for block in re.findall(r"```bash\n(.*?)```", (ROOT / "README.md").read_text(), re.S):
        for line in block.splitlines():
            for part in line.split("  #")[0].split("&&"):
                # a placeholder path (runs/<run dir>) as one word: the tests put a real one there
                words = shlex.split(re.sub(r"\S*<[^>]*>\S*", "RUN_DIR", part.strip()))
                if words[:1] == ["python"] and words[1:2] != ["-m"]:
                    found.append(words[1:])
    return found


def test_readme_shows_commands():
    scripts = {c[0] for c in commands()}
    assert {"sear.py", "plot.py", "sweep.py", "segment.py", "envs.py", "toy_pointmass.py"} <= scripts


@pytest.mark.parametrize("command", [c for c in commands() if c[0] == "sear.py"], ids=" ".join)
def test_sear_py_takes_it(command, tmp_path):
    from harness import cli
    import train
    run_dir = tmp_path / "run"
    shutil.copytree(FIXTURE, run_dir)
    argv = [str(run_dir) if a == "RUN_DIR" else a for a in command[1:]]
    argv += ["--run-root", str(tmp_path / "runs")] if "--resume" not in argv and "--evaluate" not in argv else []
    cli.parse_args(argv, train.Config, train.METHODS)


@pytest.mark.parametrize("command", [c for c in commands() if c[0] != "sear.py"], ids=" ".join)
def test_the_other_scripts_take_their_flags(command):
    script, rest = command[0], command[1:]
    sub = [rest[0]] if rest and not rest[0].startswith("-") and script in ("segment.py", "plot.py") \
        and rest[0] in ("train", "maps") else []
    r = subprocess.run([sys.executable, str(ROOT / script), *sub, "--help"], capture_output=True, text=True,
                       timeout=120, cwd=ROOT)
    assert r.returncode == 0, r.stderr[-2000:]
    for flag in (a.split("=")[0] for a in rest if a.startswith("--")):
        assert flag in r.stdout, (script, flag)
