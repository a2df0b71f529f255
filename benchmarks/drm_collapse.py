"""DrM on the collapse case (EXPERIMENTS.md, "DrM on the collapse case"): a DrM run of the published-curve
rung's DrQ seed 2 beside that seed's record, the criterion fixed before the result applied to it, one figure.

    python benchmarks/drm_collapse.py RUN_DIR [--results benchmarks/published_curve_results.csv] [--out FIG]

The criterion: DrM prevents the collapse if (a) no 4k-frame block from 4k to 40k frames has a mean
`actor_saturated` >= 0.9 and (b) the evaluation return at 40k is >= 900. (a) without (b): prevented, the task
not learned; not (a): not prevented. A block counts once the run has passed its end; until 40k is evaluated
and no block has failed, the verdict is RUNNING. DrQ seed 2's returns come from the results file; its
blocks from its train.csv as recorded in docs/published-curve.md (its run directory is not kept).
Errors are one line on stderr, exit code 2.
"""
from __future__ import annotations

import argparse
import os
import sys

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path[:0] = [HERE, os.path.dirname(HERE)]
import plot  # noqa: E402
import published_curve  # noqa: E402

BLOCK, FIRST, LAST = 4000, 4000, 40000
SATURATED, LEARNED = 0.9, 900.0
# DrQ seed 2 (commit ca5eab9), actor_saturated / action_spread per 4k block: docs/published-curve.md,
# "How a seed collapses" (official_compare.py saturation ... --block 4000 on its train.csv).
DRQ_SEED2_BLOCKS = {4000: (0.32, 0.112), 8000: (0.98, 0.154), 12000: (0.99, 0.25), 16000: (0.56, 0.641)}


def fail(message):
    print(f"drm_collapse.py: error: {message}", file=sys.stderr)
    sys.exit(2)


TASK = "cartpole_balance_sparse"
COLUMNS = ("return", "actor_saturated", "action_spread", "dormant_ratio", "expl_std", "drm_lambda")


def read_train(run_dir: str) -> dict[int, dict[str, float]]:
    """{frame: {column: value}} of train.csv's COLUMNS that have a value there (plot.load_run: a frame
    repeated by a resume keeps its last row)."""
    rows = {}
    for column in COLUMNS:
        try:
            run = plot.load_run(run_dir, "train", column)
        except plot.NoLogYet:
            raise
        except plot.PlotError:  # a column without values yet (no update before the seed phase ends)
            continue
        for f, v in zip(run["frames"], run["values"]):
            rows.setdefault(int(f), {})[column] = float(v)
    return rows


def blocks(train: dict[int, dict]) -> dict[int, tuple[float, float, bool]]:
    """Per 4k block from FIRST: (mean actor_saturated, mean action_spread, complete) over the episodes
    that ended in it with an update (an episode's row sits at its last frame, so frame - 1 places it)."""
    last = max(train, default=0)
    out = {}
    for lo in range(FIRST, LAST, BLOCK):
        rows = [r for f, r in train.items() if lo <= f - 1 < lo + BLOCK and "actor_saturated" in r]
        if rows:
            sat = sum(r["actor_saturated"] for r in rows) / len(rows)
            spread = sum(r["action_spread"] for r in rows) / len(rows)
            out[lo] = (sat, spread, last >= lo + BLOCK)
    return out


def verdict(block_means: dict, returns: dict[int, float]) -> str:
    """The criterion on a run's blocks and evaluation returns."""
    if saturated_blocks(block_means):
        return "NOT PREVENTED"
    if LAST not in returns:
        return "RUNNING"
    return "PREVENTED" if returns[LAST] >= LEARNED else "PREVENTED, TASK NOT LEARNED"


def saturated_blocks(block_means: dict) -> list[int]:
    """The complete blocks that fail (a): their mean actor_saturated >= SATURATED."""
    return [lo for lo, (sat, _, complete) in block_means.items() if complete and sat >= SATURATED]


def span(lo: int) -> str:
    return f"{lo / 1000:g}k–{(lo + BLOCK) / 1000:g}k"


def drq_seed2_returns(results: str) -> dict[int, float]:
    run = published_curve.load_results(results, TASK).get("drq", {}).get(2)
    if run is None:
        fail(f"{results}: no evaluations of drq seed 2 on {TASK}")
    return {int(f): float(v) for f, v in zip(run["frames"], run["values"])}


def figure(path, returns, drq_returns, train, block_means):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    fig, ax = plt.subplots(1, 4, figsize=(16, 3.6))
    ax[0].plot(list(returns), list(returns.values()), "o-", label="drq+drm seed 2")
    ax[0].plot(list(drq_returns), list(drq_returns.values()), "s--", label="drq seed 2 (recorded)")
    ax[0].axhline(LEARNED, color="grey", lw=0.8, ls=":")
    ax[0].set(title="evaluation return", ylabel="return (10 episodes)")
    for k, (name, i) in enumerate((("actor_saturated", 0), ("action_spread", 1)), start=1):
        mids = [lo + BLOCK / 2 for lo in block_means]
        ax[k].plot(mids, [v[i] for v in block_means.values()], "o-", label="drq+drm seed 2")
        ax[k].plot([lo + BLOCK / 2 for lo in DRQ_SEED2_BLOCKS], [v[i] for v in DRQ_SEED2_BLOCKS.values()], "s--",
                   label="drq seed 2 (recorded)")
        ax[k].set(title=f"{name}, mean per 4k frames")
    ax[1].axhline(SATURATED, color="grey", lw=0.8, ls=":")
    frames = [f for f, r in train.items() if "dormant_ratio" in r]
    for name in ("dormant_ratio", "expl_std", "drm_lambda"):
        ax[3].plot(frames, [train[f][name] for f in frames], label=name)
    ax[3].set(title="DrM: dormant ratio, std, lambda")
    for a in ax:
        a.set_xlabel("frames")
        a.set_xlim(0, LAST)
        a.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("run_dir", help="the DrM run's directory (train.csv, eval.csv)")
    p.add_argument("--results", default="benchmarks/published_curve_results.csv", help="DrQ seed 2's returns")
    p.add_argument("--out", help="write the figure here (PNG)")
    args = p.parse_args(argv)
    try:
        train = read_train(args.run_dir)
        run = plot.load_run(args.run_dir, "eval")
        drq_returns = drq_seed2_returns(args.results)
    except (plot.PlotError, published_curve.CurveError) as e:
        fail(f"{args.run_dir}: {e}" if isinstance(e, plot.NoLogYet) else str(e))
    returns = {int(f): float(v) for f, v in zip(run["frames"], run["values"])}
    block_means = blocks(train)
    print("| frames | drq+drm seed 2 | drq seed 2 |\n|---|---|---|")
    for f in sorted(set(returns) | set(drq_returns)):
        print(f"| {f / 1000:g}k | {returns.get(f, '')} | {drq_returns.get(f, '')} |")
    print("\n| block | drq+drm seed 2: actor_saturated / action_spread | drq seed 2 |\n|---|---|---|")
    for lo in sorted(set(block_means) | set(DRQ_SEED2_BLOCKS)):
        mine = block_means.get(lo)
        cell = f"{mine[0]:.3f} / {mine[1]:.3g}{'' if mine[2] else ' (running)'}" if mine else ""
        theirs = DRQ_SEED2_BLOCKS.get(lo)
        print(f"| {span(lo)} | {cell} | {f'{theirs[0]:.2f} / {theirs[1]:.3g}' if theirs else ''} |")
    why = "; ".join(f"{span(lo)}: mean actor_saturated {block_means[lo][0]:.3f} >= {SATURATED}"
                    for lo in saturated_blocks(block_means))
    print(f"\nDoes DrM prevent the collapse here? {verdict(block_means, returns)}{f' ({why})' if why else ''} "
          f"(to frame {max(train, default=0)}; criterion: EXPERIMENTS.md, \"DrM on the collapse case\")")
    if args.out:
        figure(args.out, returns, drq_returns, train, block_means)
        print(f"figure: {args.out}")


if __name__ == "__main__":
    main()
