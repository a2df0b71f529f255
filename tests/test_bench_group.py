"""benchmarks/bench_group.py --quick measures real frames/s of a group and of separate processes, and
stops with a run's error when one fails."""
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "benchmarks" / "bench_group.py"


def test_quick_measures_both_sides():
    r = subprocess.run([sys.executable, str(SCRIPT), "--quick"], capture_output=True, text=True, timeout=900, cwd=ROOT)
    assert r.returncode == 0, r.stderr[-2000:]
    row = [line for line in r.stdout.splitlines() if line.startswith("| 2 |")]
    assert row, r.stdout
    together, apart = (float(x) for x in row[0].split("|")[2:4])
    assert together > 0 and apart > 0, row


def test_a_failing_run_stops_it_with_its_error(monkeypatch):
    sys.path.insert(0, str(ROOT / "benchmarks"))
    import bench_group
    monkeypatch.setattr(bench_group, "QUICK", [*bench_group.QUICK, "--latent-dim", "64"])  # refused for drq
    assert bench_group.main(["--quick"]) == 1
