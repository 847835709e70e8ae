"""PNG plots of the benchmark results (matplotlib, Agg). Every figure names the scorer that made it."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt

COLORS = {"semantic": "tab:red", "fbe": "tab:blue", "no_lsv": "tab:orange", "no_gsv": "tab:green",
          "target_oracle": "black", "perfect_sv": "tab:purple",
          "vlfm": "tab:brown", "gain": "tab:olive", "topo": "tab:cyan",
          "perfect_vlfm": "indigo", "perfect_gain": "darkolivegreen",
          "cp": "tab:red", "entropy": "tab:blue", "relevance": "tab:green"}


EXTRA_COLORS = ("tab:brown", "tab:pink", "tab:olive", "tab:cyan", "tab:gray", "gold", "darkgreen", "navy",
                "salmon", "teal")


def strategy_colors(names: list[str]) -> dict[str, str]:
    """A colour per strategy: the fixed ones of :data:`COLORS`, then distinct others for any further strategy
    read from the results (a new strategy gets a colour no other line of the figure has)."""
    used = {COLORS[n] for n in names if n in COLORS}
    spare = iter([c for c in EXTRA_COLORS if c not in used])
    return {n: COLORS[n] if n in COLORS else next(spare, "black") for n in names}


def _paired_note(results: dict[str, Any], name: str, budget: float = 1.0, group: tuple[str, str] | None = None
                 ) -> str:
    """``vs semantic +0.050 (p 0.01), vs fbe ...`` at ``budget``: the pooled paired success differences of
    ``name`` against the two baselines (over one category / size class when ``group`` = (kind, name))."""
    parts = []
    for base, short in (("semantic", "sem"), ("fbe", "fbe")):
        if name == base:
            continue
        table = results.get(f"paired_vs_{base}", {}) if group is None else \
            results.get(f"paired_vs_{base}_by_group", {}).get(group[0], {}).get(group[1], {})
        row = next((r for r in table.get(name, []) if abs(r["budget"] - budget) < 1e-9), None)
        if row is None or not row.get("n"):
            continue
        # paired_vs_semantic holds semantic - other; show other - base in both cases
        d = (-row["diff"] if base == "semantic" else row["diff"]) + 0.0  # + 0.0: no "-0.000"
        parts.append(f"{short} {d:+.3f} (p {row['p_value']:.2g})")
    return ", ".join(parts)


def plot_evidence_and_success(results: dict[str, Any], out: Path) -> Path:
    """:func:`evidence_and_success_figure` saved as ``explore_evidence_and_success.png`` under ``out``."""
    fig = evidence_and_success_figure(results)
    path = out / "explore_evidence_and_success.png"
    fig.savefig(path, dpi=72)
    plt.close(fig)
    return path


def evidence_and_success_figure(results: dict[str, Any]) -> Any:
    """The exploration figure: per strategy read from the results, the first-evidence CDF over normalised steps
    (with the evidence ceiling when the results have it) and success vs normalised steps, pooled over the seeds;
    one row for all questions, one per question category and one per house-size class (small / medium /
    large), each strategy's legend entry with its paired success difference at T against semantic and fbe."""
    strategies = {k: v for k, v in results["strategies"].items() if not k.startswith("semantic_tau")}
    names = list(strategies)
    colors = strategy_colors(names)
    budgets, cdf_budgets = results["budgets"], results.get("cdf_budgets", [])
    ceiling = results.get("ceiling")
    rows: list[tuple[str, tuple[str, str] | None]] = [("all questions", None)]
    for kind, key in (("category", "by_category"), ("size", "by_size")):
        groups = sorted({g for r in strategies.values() for g in r.get(key, {})},
                        key=lambda g: (["small", "medium", "large"].index(g) if g in ("small", "medium", "large")
                                       else 0, g))
        rows += [(f"{kind}: {g}", (kind, g)) for g in groups]
    fig, axes = plt.subplots(len(rows), 2, figsize=(11, 3.1 * len(rows)), squeeze=False)
    cuts = results.get("size_cuts_m2")
    for (title, group), (ax_cdf, ax_succ) in zip(rows, axes, strict=True):
        key = None if group is None else ("by_category" if group[0] == "category" else "by_size")
        n_max = 0
        for name in names:
            r = strategies[name] if key is None else strategies[name].get(key, {}).get(group[1])  # type: ignore[index]
            if not r:
                continue
            n_max = max(n_max, r["n"])
            ls = "--" if strategies[name].get("bound") else "-"
            note = _paired_note(results, name, 1.0, group)
            label = f"{name}{' (bound)' if strategies[name].get('bound') else ''} n={r['n']}" + \
                (f"; at T vs {note}" if note else "")
            if r.get("evidence_cdf") and cdf_budgets:
                ax_cdf.step([0.0, *cdf_budgets], [0.0, *r["evidence_cdf"]], where="post", color=colors[name], ls=ls,
                            label=f"{name} n={r['n']}")
            ax_succ.plot(budgets, r["success"], marker=".", color=colors[name], ls=ls, label=label)
        if ceiling and cdf_budgets:
            c = ceiling if group is None else ceiling.get(key, {}).get(group[1])  # type: ignore[arg-type]
            if c:
                ax_cdf.step([0.0, *cdf_budgets], [0.0, *c["cdf"]], where="post", color="gray", lw=2.5, alpha=0.6,
                            label=f"ceiling: perceivable at all (n={c['n']})")
        size_note = ""
        if group is not None and group[0] == "size" and cuts:
            size_note = {"small": f" (<= {cuts[0]:.0f} m²)", "medium": f" ({cuts[0]:.0f}-{cuts[1]:.0f} m²)",
                         "large": f" (> {cuts[1]:.0f} m²)"}.get(group[1], "")
        ax_cdf.set(title=f"{title}{size_note}: first evidence (Rel >= 0.3)", ylim=(0, 1.02), xlim=(0, 1.02),
                   xlabel="normalised steps (fraction of T)", ylabel="share of episodes")
        ax_succ.set(title=f"{title}{size_note}: success (n={n_max})", ylim=(0, 1.02),
                    xlabel="normalised steps (fraction of T)", ylabel="success rate")
        for ax in (ax_cdf, ax_succ):
            ax.title.set_fontsize(8.5)
            ax.grid(alpha=0.3)
            if ax.get_legend_handles_labels()[0]:
                ax.legend(fontsize=6, loc="lower right")
    seeds = results.get("seeds", [0])
    fig.suptitle(f"Exploration: first evidence and success per strategy, pooled over seeds "
                 f"{' '.join(map(str, seeds))}; legend: paired success difference at T (exact sign-test p)\n"
                 f"{results['scorer']}, {results['size']}, runner {results.get('runner', 'fleet')}", fontsize=9)
    fig.tight_layout(rect=(0, 0, 1, 1 - 0.3 / len(rows)))
    return fig


def plot_explore(results: dict[str, Any], out: Path) -> list[Path]:
    """Fig. 7 (success vs normalised budget), Fig. A6 (per category) and Fig. A7 (by house size)."""
    budgets = results["budgets"]
    seeds = results.get("seeds", [0])
    sub = (f"{results['scorer']}, {results['size']}, seeds {' '.join(map(str, seeds))}, "
           f"runner {results.get('runner', 'fleet')}")
    paths = []
    everything = results["strategies"]
    tau_runs = {k: v for k, v in everything.items() if k.startswith("semantic_tau")}
    # Fig. 7a/b, A6 and A7 compare the strategies; the temperature runs get their own figure (Fig. 7c).
    results = {**results, "strategies": {k: v for k, v in everything.items() if k not in tau_runs}}

    def label(name: str, r: dict[str, Any]) -> str:
        return f"{name}{' (bound)' if r.get('bound') else ''} (n={r['n']})"

    colors = strategy_colors(list(results["strategies"]))

    curves = [(label(name, r), r["success"], colors[name]) for name, r in results["strategies"].items()]
    paths.append(_success_plot(budgets, curves, f"Exploration: success vs steps\n{sub}",
                               out / "explore_success_vs_steps.png",
                               [r.get("success_ci95") for r in results["strategies"].values()]))

    if all("evidence_cdf" in r for r in results["strategies"].values()) and "cdf_budgets" in results:
        fig, ax = plt.subplots(figsize=(6, 4.2))
        for name, r in results["strategies"].items():
            ax.step([0.0, *results["cdf_budgets"]], [0.0, *r["evidence_cdf"]], where="post", label=label(name, r),
                    color=colors[name], ls="--" if r.get("bound") else "-")
        if (c := results.get("ceiling")):
            ax.step([0.0, *results["cdf_budgets"]], [0.0, *c["cdf"]], where="post", color="gray", lw=2.5, alpha=0.6,
                    label=f"ceiling: evidence perceivable at all (n={c['n']})")
        ax.set(xlabel="normalised step budget (fraction of T)", ylabel="share of episodes that saw the evidence",
               ylim=(0, 1), xlim=(0, 1.02), title=f"First evidence (Rel >= 0.3) within the budget\n{sub}")
        ax.title.set_fontsize(7.5)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
        fig.tight_layout()
        paths.append(out / "explore_first_evidence_cdf.png")
        fig.savefig(paths[-1], dpi=120)
        plt.close(fig)

    if len(seeds) > 1 and all("per_seed" in r for r in results["strategies"].values()):
        fig, axes = plt.subplots(1, len(seeds), figsize=(3.4 * len(seeds), 3.4), sharey=True, squeeze=False)
        for ax, seed in zip(axes[0], seeds, strict=True):
            for name, r in results["strategies"].items():
                ps = r["per_seed"].get(str(seed))
                if ps:
                    ax.plot(budgets, ps["success"], marker=".", label=f"{name} (n={ps['n']})", color=colors[name],
                            ls="--" if r.get("bound") else "-")
            ax.set(title=f"seed {seed}", xlabel="normalised steps", ylim=(0, 1))
            ax.grid(alpha=0.3)
            ax.legend(fontsize=6)
        axes[0][0].set_ylabel("success rate")
        fig.suptitle(f"Per benchmark seed ({results['scorer']}, {results['size']})", fontsize=9)
        fig.tight_layout()
        paths.append(out / "explore_per_seed.png")
        fig.savefig(paths[-1], dpi=110)
        plt.close(fig)

    categories = sorted({c for r in results["strategies"].values() for c in r["by_category"]})
    if categories:
        fig, axes = plt.subplots(1, len(categories), figsize=(3.2 * len(categories), 3.2), sharey=True, squeeze=False)
        for ax, cat in zip(axes[0], categories, strict=True):
            for name, r in results["strategies"].items():
                c = r["by_category"].get(cat)
                if c:
                    ax.plot(budgets, c["success"], marker=".", label=name, color=colors[name])
            n = max((r["by_category"].get(cat, {}).get("n", 0) for r in results["strategies"].values()), default=0)
            ax.set(title=f"{cat} (n={n})", xlabel="normalised steps", ylim=(0, 1))
            ax.grid(alpha=0.3)
        axes[0][0].set_ylabel("success rate")
        axes[0][-1].legend(fontsize=7)
        fig.suptitle(f"Per question category ({sub})", fontsize=9)
        fig.tight_layout()
        paths.append(out / "explore_by_category.png")
        fig.savefig(paths[-1], dpi=110)
        plt.close(fig)

    bins = sorted({b for r in results["strategies"].values() for b in r["by_area"]}, key=lambda b: int(b.split("-")[0]))
    if bins:
        fig, ax = plt.subplots(figsize=(6, 3.6))
        width = 0.8 / max(len(results["strategies"]), 1)
        for k, (name, r) in enumerate(results["strategies"].items()):
            xs = [i + k * width for i in range(len(bins))]
            ys = [r["by_area"].get(b, {}).get("success_full_budget", 0.0) for b in bins]
            ax.bar(xs, ys, width=width, label=name, color=colors[name])
        ax.set_xticks([i + 0.4 - width / 2 for i in range(len(bins))], [f"{b} m²" for b in bins], fontsize=7)
        ax.set(ylabel="success at full budget", ylim=(0, 1), title=f"Success by house size\n{sub}")
        ax.title.set_fontsize(9)
        ax.legend(fontsize=7)
        fig.tight_layout()
        paths.append(out / "explore_by_house_size.png")
        fig.savefig(paths[-1], dpi=110)
        plt.close(fig)

    paths.append(plot_evidence_and_success(results, out))

    if tau_runs:
        by_label: dict[str, Any] = {}
        if "semantic" in everything:
            by_label["semantic, tau 1 (default)"] = everything["semantic"]
        by_label.update({f"semantic, tau {k.removeprefix('semantic_tau')}": v for k, v in tau_runs.items()})
        if "fbe" in everything:
            by_label["fbe (no semantic value)"] = everything["fbe"]
        extra = iter(["tab:orange", "tab:green", "tab:purple", "tab:brown", "tab:pink", "tab:olive"])
        lines = [(f"{name} (n={r['n']})", r["success"], COLORS.get("fbe") if name.startswith("fbe") else (
            COLORS.get("semantic") if "default" in name else next(extra, None))) for name, r in by_label.items()]
        paths.append(_success_plot(budgets, lines, f"Semantic value temperature (tau_LSV = tau_GSV)\n{sub}",
                                   out / "explore_temperature.png"))
    return paths


def _success_plot(budgets: list[float], curves: list[tuple[str, list[float], str | None]], title: str,
                  path: Path, intervals: list[Any] | None = None) -> Path:
    """Success rate against the normalised step budget, one line per (label, values, colour); ``intervals``:
    per line, the 95 % interval per budget (shaded) or None."""
    fig, ax = plt.subplots(figsize=(6, 4.2))
    for k, (label, values, color) in enumerate(curves):
        line = ax.plot(budgets, values, marker="o", label=label, color=color)[0]
        ci = intervals[k] if intervals and k < len(intervals) else None
        if ci:
            ax.fill_between(budgets, [c[0] for c in ci], [c[1] for c in ci], color=line.get_color(), alpha=0.08)
    ax.set(xlabel="normalised step budget (fraction of T)", ylabel="success rate", ylim=(0, 1), title=title)
    ax.title.set_fontsize(7.5)
    ax.grid(alpha=0.3)
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def plot_stop(results: dict[str, Any], out: Path) -> Path:
    """Fig. 9: success vs mean normalised steps for the CP eps sweep and the two threshold sweeps."""
    fig, ax = plt.subplots(figsize=(6, 4.2))
    rules = (("cp", "CP (eps sweep)"), ("entropy", "entropy threshold"), ("relevance", "relevance threshold"))
    for rule, label in rules:
        pts = sorted(results[rule], key=lambda p: p["mean_normalized_steps"])
        ax.plot([p["mean_normalized_steps"] for p in pts], [p["success"] for p in pts], marker="o", label=label,
                color=COLORS.get(rule))
    ax.axhline(results["full_budget_success"], color="gray", ls="--", lw=1, label="run to step limit")
    ax.set(xlabel="mean normalised steps used", ylabel="success rate", xlim=(0, 1.05), ylim=(0, 1),
           title=f"Stopping: success vs steps ({results['strategy']}, {results['n_test']} test episodes)\n"
                 f"{results['scorer']}, {results['size']}")
    ax.title.set_fontsize(9)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    path = out / "stop_success_vs_steps.png"
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


FAILURE_COLORS = {"collision": "tab:red", "object not found: out of steps": "tab:blue",
                  "object not found: search ended": "lightsteelblue",
                  "object not found: pick limit used up": "tab:cyan", "pick failed": "tab:orange",
                  "receptacle not found: out of steps": "tab:purple", "receptacle not found: search ended": "plum",
                  "place failed": "tab:brown", "stopped away from the object": "tab:orange", "run failed": "black",
                  "success": "tab:green"}


def plot_failures(table: dict[str, dict[str, int]], causes: tuple[str, ...], variants: list[str], title: str,
                  path: Path) -> Path:
    """HELIOS Fig. 5 / 6: per agent variant, the share of runs by first failure (eqa.task_traces), one
    horizontal stacked bar each, the count written in every segment wide enough; legend in the causes' order."""
    from matplotlib.patches import Patch

    vs = [v for v in variants if v in table]
    shown = [c for c in causes if any(table[v][c] for v in vs)]
    fig, ax = plt.subplots(figsize=(8.5, 1.3 + 0.5 * len(vs)))
    for y, v in enumerate(vs):
        n = max(sum(table[v].values()), 1)
        left = 0.0
        for c in shown:
            w = 100 * table[v][c] / n
            if w <= 0:
                continue
            ax.barh(y, w, left=left, color=FAILURE_COLORS.get(c, "grey"), edgecolor="white")
            if w >= 4:
                light = FAILURE_COLORS.get(c) in ("lightsteelblue", "plum")
                ax.text(left + w / 2, y, str(table[v][c]), ha="center", va="center", fontsize=8,
                        color="black" if light else "white")
            left += w
    ax.set_yticks(range(len(vs)), [f"{v} (n={sum(table[v].values())})" for v in vs])
    ax.invert_yaxis()
    ax.set_xlim(0, 100)
    ax.set_xlabel("% of runs, by the first thing that failed")
    ax.set_title(title, fontsize=8.5)
    ax.legend([Patch(color=FAILURE_COLORS.get(c, "grey")) for c in shown], shown, fontsize=7, ncol=3,
              loc="upper center", bbox_to_anchor=(0.5, -0.15 - 0.4 / max(len(vs), 1)), frameon=False)
    fig.savefig(path, dpi=110, bbox_inches="tight")
    plt.close(fig)
    return path
