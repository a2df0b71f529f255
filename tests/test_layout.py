"""The layout's budgets: sear.py is the file people copy, short, all algorithm, on the ground floor
(torch, numpy and the standard library, nothing of the project); the loop (train.py), the baselines,
DrM and the harness (cli.py, experiment.py) stand on it. `python tests/test_layout.py` prints the
numbers.

How lines are counted: physical lines of the file. sear.py's sections start at their banner
(`# ====` over `# N. Title`); sections 1-6 (Config, networks, augmentation, auxiliary losses,
agent, replay buffer) are the algorithm, the docstring and imports before section 1 are not. A
function's length runs from its `def` line to its last line, docstring included, decorators not.
"""
import ast
import re
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SEAR = ROOT / "sear.py"
TRAIN = ROOT / "train.py"
HARNESS = ("harness.cli", "harness.experiment", "harness.group", "harness.runenvs", "harness.speed")
PACKAGES = ("harness", "methods")  # the harness (command line, run directory, speed) and the successor methods
SEAR_LINES = 620
MODULES = sorted([p.stem for p in ROOT.glob("*.py")]  # the importable modules: the top level's and the packages'
                 + [f"{pkg}.{p.stem}" for pkg in PACKAGES for p in (ROOT / pkg).glob("*.py") if p.stem != "__init__"])


def module_path(m: str) -> Path:
    return ROOT / (m.replace(".", "/") + ".py")
ALGORITHM_SECTIONS = range(1, 7)
LOOP = "train"
FUNCTION_LINES, LOOP_LINES = 60, 60  # every function outside tests; the loop (train.py's train)
LINE_CHARS = 100  # sear.py's and train.py's lines, comments on lines of their own
# Over the budget, each held at its length until it is split.


def sections(path=SEAR):
    """[(number, title, first line, last line)] of sear.py's numbered sections, plus the header (0)."""
    lines = path.read_text().splitlines()
    starts = [(int(m[1]), m[2], i) for i, line in enumerate(lines, 1) if (m := re.fullmatch(r"# (\d+)\. (.+)", line))]
    starts = [(n, title, i - 1 if lines[i - 2].startswith("# ====") else i) for n, title, i in starts]
    bounds = [(0, "header", 1), *starts]
    return [(n, title, first, (bounds[k + 1][2] - 1) if k + 1 < len(bounds) else len(lines))
            for k, (n, title, first) in enumerate(bounds)]


def functions(path):
    """(qualified name, first line, length) of every function and method of a file."""
    out = []

    def visit(node, prefix):
        for child in ast.iter_child_nodes(node):
            if isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef)):
                out.append((prefix + child.name, child.lineno, child.end_lineno - child.lineno + 1))
                visit(child, prefix + child.name + ".")
            elif isinstance(child, ast.ClassDef):
                visit(child, prefix + child.name + ".")
    visit(ast.parse(path.read_text()), "")
    return out


def budgets() -> dict:
    parts = sections()
    total = parts[-1][3]
    algorithm = sum(last - first + 1 for n, _, first, last in parts if n in ALGORITHM_SECTIONS)
    tree = ast.parse(SEAR.read_text())
    encoders = [node.lineno for node in tree.body if isinstance(node, ast.ClassDef) and node.name.endswith("Encoder")]
    sear_functions = functions(SEAR)
    return {"lines": total, "algorithm lines": algorithm, "algorithm share": algorithm / total,
            "first encoder at line": min(encoders), "sections": parts,
            "training loop lines": next(n for name, _, n in functions(TRAIN) if name == LOOP),
            "longest function in sear.py": max((n, name) for name, _, n in sear_functions),
            "longest function in the project": max((n, f"{p.relative_to(ROOT)}:{name}") for p in project_files()
                                                   for name, _, n in functions(p)),
            "longest function outside tests and the loop": max(function_lengths().items(), key=lambda kv: kv[1])}


def project_files():
    return sorted(p for p in ROOT.rglob("*.py") if not {".venv", ".git", "fixtures"} & set(p.parts))


def function_lengths() -> dict[str, int]:
    """{file:function: lines} of every function outside tests/ but the loop."""
    return {f"{p.relative_to(ROOT)}:{name}": n for p in project_files() if p.relative_to(ROOT).parts[0] != "tests"
            for name, _, n in functions(p) if (p, name) != (TRAIN, LOOP)}


def test_sear_py_is_at_most_620_lines_and_nine_tenths_algorithm():
    b = budgets()
    assert [n for n, *_ in b["sections"]] == [0, *ALGORITHM_SECTIONS], b["sections"]
    assert b["lines"] <= SEAR_LINES, b["lines"]
    assert b["algorithm share"] >= 0.9, b


def test_the_encoder_is_defined_within_the_first_200_lines():
    assert budgets()["first encoder at line"] <= 200


def test_functions_are_short():
    b = budgets()
    assert b["training loop lines"] <= LOOP_LINES
    assert b["longest function in sear.py"][0] <= FUNCTION_LINES, b["longest function in sear.py"]
    assert b["longest function in the project"][0] <= 100, b["longest function in the project"]


def test_every_function_outside_tests_is_at_most_60_lines_and_the_loop_80():
    over = {name: n for name, n in function_lengths().items() if n > FUNCTION_LINES}
    assert over == {}, over
    assert budgets()["training loop lines"] <= LOOP_LINES


def test_the_harness_builds_its_state_in_init():
    """A class of cli.py and experiment.py makes every attribute it has in __init__ (None or empty
    until it is known): what an object holds is read in one place."""
    late = []
    for module in HARNESS:
        for cls in (n for n in ast.walk(ast.parse(module_path(module).read_text())) if isinstance(n, ast.ClassDef)):
            made = {}
            for fn in (n for n in cls.body if isinstance(n, ast.FunctionDef)):
                for node in ast.walk(fn):
                    targets = (node.targets if isinstance(node, ast.Assign) else
                               [node.target] if isinstance(node, (ast.AugAssign, ast.AnnAssign)) else [])
                    for t in (e for t in targets for e in (t.elts if isinstance(t, ast.Tuple) else [t])):
                        if isinstance(t, ast.Attribute) and isinstance(t.value, ast.Name) and t.value.id == "self":
                            made.setdefault(t.attr, set()).add(fn.name)
            late += [f"{module}.{cls.name}.{attr} ({', '.join(sorted(where))})" for attr, where in made.items()
                     if "__init__" not in where]
    assert late == []


def test_one_one_line_parser():
    """The commands' argument parser whose errors are one line is cli.OneLineParser; envs.py (below cli,
    which imports it) and toy_pointmass.py (standing apart on purpose) keep a small one of their own."""
    parsers = sorted(f"{p.relative_to(ROOT)}:{node.name}" for p in project_files()
                     for node in ast.walk(ast.parse(p.read_text())) if isinstance(node, ast.ClassDef)
                     and any(ast.unparse(base) in ("argparse.ArgumentParser", "ArgumentParser") for base in node.bases))
    assert parsers == ["envs.py:_OneLineParser", "harness/cli.py:OneLineParser", "toy_pointmass.py:_Parser"]


def loaded_after(statement: str) -> set[str]:
    code = f"import sys; {statement}; print(' '.join(sorted({{m.split('.')[0] for m in sys.modules}})))"
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, timeout=300)
    assert r.returncode == 0, r.stderr
    return set(r.stdout.split())


def test_import_sear_loads_no_plotting_video_sweep_or_tensorboard_and_cli_no_torch():
    assert not {"matplotlib", "imageio", "submitit", "tensorboard"} & loaded_after("import sear")
    # sweep.py and plot.py read flags and configs through cli without torch.
    assert not {"numpy", "torch"} & loaded_after("from harness import cli")


def test_import_sear_needs_only_torch_numpy_and_the_standard_library():
    """A reader's `import sear` (to take the agent into a notebook or another codebase) works where the
    suites' packages are missing: gymnasium, PIL, scipy and mujoco cannot be imported in this process."""
    blocked = ("gymnasium", "PIL", "scipy", "mujoco", "dm_control", "metaworld", "matplotlib", "imageio")
    code = ("import importlib.abc, sys\n"
            "class Block(importlib.abc.MetaPathFinder):\n"
            "    def find_spec(self, name, path=None, target=None):\n"
            f"        if name.split('.')[0] in {blocked!r}:\n"
            "            raise ImportError(f'blocked: {name}')\n"
            "sys.meta_path.insert(0, Block())\n"
            "import sear\n"
            "agent = sear.Agent(sear.Config(method='sear', latent_dim=64, hidden_dim=32), 1, sear.torch.device('cpu'))\n"
            "print(sorted({m.split('.')[0] for m in sys.modules} & set(" + repr(blocked) + ")))")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    assert r.stdout.split()[-1] == "[]"


def test_the_loop_owns_its_schedule_and_the_run_dir_only_writes():
    """train.train decides when to evaluate, snapshot and stop; experiment.RunDir (and the console it
    is made of) never moves the loop's counters (it is handed them to save) and keeps no clock of
    when to snapshot."""
    tree = ast.parse((ROOT / "harness" / "experiment.py").read_text())
    parts = [n for n in tree.body if isinstance(n, ast.ClassDef) and n.name in ("RunDir", "Console")]
    assert len(parts) == 2

    def counters(node):  # c.step, counters.step, self.counters.step
        return (isinstance(node, ast.Name) and node.id in ("c", "counters")
                or isinstance(node, ast.Attribute) and node.attr == "counters")
    moved = sorted({t.attr for part in parts for node in ast.walk(part)
                    if isinstance(node, (ast.Assign, ast.AugAssign))
                    for t in (node.targets if isinstance(node, ast.Assign) else [node.target])
                    for t in (t.elts if isinstance(t, ast.Tuple) else [t])
                    if isinstance(t, ast.Attribute) and counters(t.value)})
    assert moved == [], f"RunDir moves the loop's counters: {moved}"
    methods = {n.name for part in parts for n in part.body if isinstance(n, ast.FunctionDef)}
    assert not {"snapshot_due"} & methods
    loop = next(n for n in ast.parse(TRAIN.read_text()).body if isinstance(n, ast.FunctionDef) and n.name == LOOP)
    called = {n.func.id for n in ast.walk(loop) if isinstance(n, ast.Call) and isinstance(n.func, ast.Name)}
    assert "eval_due" in called


def imports(path) -> set[str]:
    """The project modules a file imports anywhere (top level or inside a function)."""
    names = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            names |= {a.name if a.name.split(".")[0] in PACKAGES else a.name.split(".")[0] for a in node.names}
        elif isinstance(node, ast.ImportFrom) and node.module and not node.level:
            if node.module in PACKAGES:  # from harness import cli
                names |= {f"{node.module}.{a.name}" for a in node.names}
            else:
                names.add(node.module if node.module.split(".")[0] in PACKAGES else node.module.split(".")[0])
    return names & set(MODULES)


def test_sear_py_imports_torch_numpy_and_the_standard_library_only():
    """The ground floor: at any level (inside functions too), sear.py imports nothing of the project and
    no package but torch and numpy; `python sear.py` reaches train.py by its path (runpy), not an import."""
    tree = ast.parse(SEAR.read_text())
    modules = {a.name.split(".")[0] for node in ast.walk(tree) if isinstance(node, ast.Import) for a in node.names}
    modules |= {node.module.split(".")[0] for node in ast.walk(tree)
                if isinstance(node, ast.ImportFrom) and node.module and not node.level}
    allowed = set(sys.stdlib_module_names) | {"torch", "numpy", "__future__"}
    assert modules - allowed == set(), modules - allowed
    assert not any(isinstance(node, ast.ImportFrom) and node.level for node in ast.walk(tree))


def test_no_import_cycle_and_sear_on_the_ground_floor():
    graph = {m: imports(module_path(m)) - {m} for m in MODULES}

    def reach(m, seen):
        for n in graph[m] - seen:
            seen.add(n)
            reach(n, seen)
        return seen
    assert [m for m in MODULES if m in reach(m, set())] == []
    assert graph["sear"] == set()  # nothing of the project below it
    assert {"sear"} <= graph["methods.baselines"] & graph["methods.drm"] & graph["train"]
    # `python sear.py` and `python train.py` run train.py as __main__: nothing it imports may import a
    # second copy of it as `train`; the harness never imports the algorithm.
    assert "train" not in set().union(*(reach(m, {m}) for m in graph["train"]))
    # the speed layer stands on sear.py (its batched update runs the agent's own methods)
    assert all(not {"sear", "train"} & graph[m] for m in HARNESS if m != "harness.speed")
    assert "train" not in graph["harness.speed"]


def test_plot_sweep_and_benchmarks_take_only_algorithm_names_from_sear():
    tree = ast.parse(SEAR.read_text())
    own = set()
    for node in tree.body:
        if isinstance(node, (ast.FunctionDef, ast.ClassDef)):
            own.add(node.name)
        elif isinstance(node, ast.Assign):
            own |= {t.id for t in node.targets if isinstance(t, ast.Name)}
    users = [ROOT / "plot.py", ROOT / "sweep.py", *sorted((ROOT / "benchmarks").glob("*.py"))]
    used = {(p.name, node.attr) for p in users for node in ast.walk(ast.parse(p.read_text()))
            if isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name) and node.value.id == "sear"}
    assert {(f, name) for f, name in used if name not in own} == set()  # e.g. cli.X: take it from cli


if __name__ == "__main__":
    b = budgets()
    for n, title, first, last in b.pop("sections"):
        kind = "algorithm" if n in ALGORITHM_SECTIONS else "other"
        print(f"sear.py section {n} {title}: lines {first}-{last} ({last - first + 1}, {kind})")
    for name, value in b.items():
        print(f"{name}: {value:.3f}" if isinstance(value, float) else f"{name}: {value}")


def test_sear_and_train_read_in_lines_of_100_characters_with_comments_on_their_own():
    import io
    import tokenize
    for path in (SEAR, TRAIN):
        src = path.read_text()
        lines = src.splitlines()
        assert [i for i, line in enumerate(lines, 1) if len(line) > LINE_CHARS] == [], path.name
        trailing = [tok.start[0] for tok in tokenize.generate_tokens(io.StringIO(src).readline)
                    if tok.type == tokenize.COMMENT and lines[tok.start[0] - 1][:tok.start[1]].strip()]
        assert trailing == [], (path.name, trailing)


def test_sear_py_is_the_pytorch_every_reader_knows():
    """No call into torch's private API (torch._dynamo, torch._inductor, torch._C, torch._foreach_*) and
    no optimiser class of its own: torch.optim.Adam, stepped with zero_grad / backward / step."""
    src = SEAR.read_text()
    assert re.findall(r"torch\._[a-zA-Z]", src) == []
    tree = ast.parse(src)
    optimisers = [n.name for n in tree.body if isinstance(n, ast.ClassDef)
                  and any("Optimizer" in ast.unparse(b) or "Adam" in ast.unparse(b) for b in n.bases)]
    assert optimisers == []
    assert src.count("torch.optim.Adam(") == 2 and ".backward(" in src and ".zero_grad(" in src


def test_the_loop_evaluates_at_one_site_and_stops_at_one_point():
    loop = next(n for n in ast.parse(TRAIN.read_text()).body if isinstance(n, ast.FunctionDef) and n.name == LOOP)
    calls = [n.func for n in ast.walk(loop) if isinstance(n, ast.Call)]
    names = [f.id if isinstance(f, ast.Name) else f.attr for f in calls if isinstance(f, (ast.Name, ast.Attribute))]
    assert names.count("evaluate_and_log") == 1 and names.count("safe_point") == 1


# ---------------------------------------------------------------- the harness's weight
# The harness: the command line, the run directory, the seeds' group and envs, the speed layer
# (harness/*.py), the sweeps and the plots. Documents: docs/*.md, counted as `wc -w` counts. The
# harness is held at its length (the aim: 4,500 lines); the documents at their aim.
HARNESS_LINES, DOCS_WORDS = 5_732, 25_000
COMPLEX, MOST_COMPLEX, MOST_COMPLEX_FUNCTIONS = 11, 20, 45  # radon's C starts at 11, its D at 21


def harness_files() -> list[Path]:
    return [*sorted((ROOT / "harness").glob("*.py")), ROOT / "sweep.py", ROOT / "plot.py"]


def complexity(fn: ast.AST) -> int:
    """A function's cyclomatic complexity as radon counts it (`radon cc`; its closures apart): 1, and
    one more per if, ternary, assert, loop (and loop else), except (and try else), comprehension
    `for` and its ifs, match case, and each `and`/`or` beyond the first operand."""
    n, stack = 1, list(ast.iter_child_nodes(fn))
    while stack:
        node = stack.pop()
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
            continue
        if isinstance(node, (ast.If, ast.IfExp, ast.Assert, ast.match_case)):
            n += 1
        elif isinstance(node, (ast.For, ast.AsyncFor, ast.While)):
            n += 1 + bool(node.orelse)
        elif isinstance(node, ast.Try):
            n += len(node.handlers) + bool(node.orelse)
        elif isinstance(node, ast.comprehension):
            n += 1 + len(node.ifs)
        elif isinstance(node, ast.BoolOp):
            n += len(node.values) - 1
        stack.extend(ast.iter_child_nodes(node))
    return n


def complexities() -> dict[str, int]:
    """{file:function: complexity} of every function outside tests/ and benchmarks/."""
    out = {}
    for p in project_files():
        if p.relative_to(ROOT).parts[0] in ("tests", "benchmarks"):
            continue
        for node in ast.walk(ast.parse(p.read_text())):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                out[f"{p.relative_to(ROOT)}:{node.lineno}:{node.name}"] = complexity(node)
    return out


def test_the_harness_and_the_documents_keep_their_weight():
    lines = sum(len(p.read_text().splitlines()) for p in harness_files())
    words = sum(len(p.read_text().split()) for p in (ROOT / "docs").glob("*.md"))
    assert lines <= HARNESS_LINES, lines
    assert words <= DOCS_WORDS, words


def test_no_function_outside_tests_and_benchmarks_is_graded_d_or_worse():
    graded = complexities()
    assert max(graded.values()) <= MOST_COMPLEX, {k: v for k, v in graded.items() if v > MOST_COMPLEX}
    assert sum(v >= COMPLEX for v in graded.values()) <= MOST_COMPLEX_FUNCTIONS


def test_complexity_counts_as_radon_does():
    """Counted by hand as radon's rules do (radon cc gives these numbers)."""
    source = '''
def f(xs, a, b):
    if a and b or a:
        return [x for x in xs if x if a]
    for x in xs:
        while x:
            x -= 1
        else:
            pass
    try:
        pass
    except ValueError:
        pass
    except KeyError:
        pass
    else:
        pass
    assert a
    def inner():
        if a:
            pass
    return 1 if a else 2
'''
    (fn,) = ast.parse(source).body
    # 1 + if 1 + bool ops 2 + comprehension 3 + for 1 + while 2 + excepts 2 + try else 1 + assert 1 + ternary 1
    assert complexity(fn) == 15
