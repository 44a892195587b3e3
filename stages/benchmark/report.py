"""``pivot benchmark report``: ``report.md`` and figures from a sweep's ``results.parquet`` (issue 13).

Rates, as the issue defines them:

- **plan found**: cases whose plan stage found a full plan (status ok), over the cases labelled
  reachable (the unreachable ones are counted apart, in their own table, never dropped);
- **physics success**: (case, seed) runs that succeed in PyBullet, over the runs of the reachable
  cases whose plan was found (and, in a second figure, over all runs of reachable cases: end to end).

Failure reasons are ranked by the number of cases (plan-level) or runs (physics) they end, each with
an example case to rerun alone (``pivot run OUT/scenes/<case>.json``).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from stages import artifacts
from stages.benchmark.sweep import STAGES


def _rate(num: int, den: int) -> str:
    return f"{num}/{den} ({100 * num / den:.0f} %)" if den else "–"


def case_table(res) -> dict:
    """Per case (its seed-0 row) and per run arrays of the results (struct of arrays)."""
    c = {k: np.asarray(v) for k, v in res.columns.items()}
    first = c["seed"] == 0
    return {"case": {k: v[first] for k, v in c.items()}, "run": c}


def rates(case: dict, run: dict, mask_case: np.ndarray, mask_run: np.ndarray) -> dict:
    """Counts of one group: cases, reachable, plans found, runs, physics successes."""
    reach_c = mask_case & case["reachable"].astype(bool)
    reach_r = mask_run & run["reachable"].astype(bool)
    planned_r = reach_r & run["plan_found"].astype(bool)
    return {"cases": int(mask_case.sum()), "reachable": int(reach_c.sum()),
            "found": int((reach_c & case["plan_found"].astype(bool)).sum()),
            "runs_planned": int(planned_r.sum()), "success_planned": int((planned_r & run["success"]).sum()),
            "runs": int(reach_r.sum()), "success": int((reach_r & run["success"]).sum())}


def rate_rows(title: str, groups: list[tuple[str, dict]]) -> list[str]:
    """A Markdown table of :func:`rates` per group."""
    lines = [f"| {title} | cases | reachable | plan found (of reachable) | physics success (of planned runs) "
             "| end to end (of reachable runs) |", "|---|---|---|---|---|---|"]
    for name, r in groups:
        lines.append(f"| {name} | {r['cases']} | {r['reachable']} | {_rate(r['found'], r['reachable'])} | "
                     f"{_rate(r['success_planned'], r['runs_planned'])} | {_rate(r['success'], r['runs'])} |")
    return lines


def failure_rows(case: dict, run: dict) -> list[str]:
    """Failure reasons ranked: plan-level reasons per case, physics reasons per run; an example each."""
    planned = case["plan_found"].astype(bool) & (case["stage_reached"] == "execute")
    reasons = [(r, n, "case") for r, n in zip(*np.unique(case["reason"][~planned], return_counts=True), strict=True)]
    phys = run["plan_found"].astype(bool) & (run["stage_reached"] == "execute") & ~run["success"]
    reasons += [(r, n, "run") for r, n in zip(*np.unique(run["reason"][phys], return_counts=True), strict=True)]
    reasons = [x for x in reasons if x[0] != "ok"]
    reasons.sort(key=lambda x: (-x[1], x[0]))
    lines = ["| reason | count | of | reachable among them | example case | its error |", "|---|---|---|---|---|---|"]
    for reason, n, unit in reasons:
        src = case if unit == "case" else run
        sel = (src["reason"] == reason) & (~planned if unit == "case" else phys)
        i = int(np.flatnonzero(sel)[0])
        err = str(src["error"][i]).replace("|", "/")[:140]
        lines.append(f"| `{reason}` | {n} | {unit}s | {int(src['reachable'][sel].astype(bool).sum())} | "
                     f"`{src['case'][i]}` | {err} |")
    return lines


def stage_samples(run: dict, column: str) -> dict[str, np.ndarray]:
    """Per stage, the finite values of ``<column>_<stage>`` over the processes that ran it: the chain's
    stages once per case (its seed-0 row), the execution once per seed."""
    first = run["seed"] == 0
    out = {}
    for s in STAGES:
        v = run[f"{column}_{s}"][first if s != "execute" else slice(None)].astype(float)
        out[s] = v[np.isfinite(v)]
    return out


def time_rows(run: dict) -> list[str]:
    """Time and peak memory per stage over the processes that ran it (median, 90th percentile, max)."""
    lines = ["| stage | processes | median (s) | p90 (s) | max (s) | peak memory max (MB) |",
             "|---|---|---|---|---|---|"]
    times, mems = stage_samples(run, "t"), stage_samples(run, "mem")
    for s in STAGES:
        t, m = times[s], mems[s]
        if len(t):
            lines.append(f"| {s} | {len(t)} | {np.median(t):.1f} | {np.percentile(t, 90):.1f} | {t.max():.1f} | "
                         f"{m.max():.0f} |")
    return lines


def unreachable_rows(case: dict) -> list[str]:
    """The cases the necessary test labelled unreachable, with what the chain did anyway."""
    sel = ~case["reachable"].astype(bool)
    lines = ["| case | label | grasps start / goal | chain ended with |", "|---|---|---|---|"]
    for i in np.flatnonzero(sel):
        lines.append(f"| `{case['case'][i]}` | {case['reach_reason'][i]} | {case['grasps'][i]} | "
                     f"`{case['reason'][i]}` |")
    return lines


def whole_chain(chain: np.ndarray) -> str:
    """The sentence on the whole chain's wall time per case (s)."""
    if not len(chain):
        return "No case ran."
    return (f"Whole chain per case (analyze to the seed-0 execution, the stages it reached): median "
            f"{np.median(chain):.1f} s, max {chain.max():.1f} s.")


def every_case_rows(case: dict, run: dict, views: dict | None = None) -> list[str]:
    """Every case: kind, label, plan counts, the outcome of each seed's run and its 3D view (``views``:
    case -> page, relative to the report)."""
    views = views or {}
    lines = ["| case | kind | reachable | plan (pivots/tumbles/regrasps, backtracks) | outcome per seed | view |",
             "|---|---|---|---|---|---|"]
    for i, name in enumerate(case["case"]):
        sel = run["case"] == name
        plan = (f"{case['pivots'][i]}/{case['tumbles'][i]}/{case['regrasps'][i]}, {case['backtracks'][i]}"
                if case["plan_found"][i] else "–")
        outcome = ", ".join(f"{s}: `{r}`" for s, r in zip(run["seed"][sel], run["reason"][sel], strict=True))
        link = f"[3D]({views[name]})" if name in views else "–"
        lines.append(f"| `{name}` | {case['kind'][i]} | {'yes' if case['reachable'][i] else 'no'} | {plan} | "
                     f"{outcome} | {link} |")
    return lines


def write_report(out: str | Path) -> Path:
    """Write ``out/report.md`` and ``out/figures/*.png`` from ``out/results.parquet``; returns the path."""
    from stages import plots, view

    out = Path(out)
    res = artifacts.read_table(out / "results.parquet", "benchmark_results")
    suite = artifacts.read_json(out / "suite.json", "benchmark_suite")
    t = case_table(res)
    case, run = t["case"], t["run"]
    grasps = {c["case"]: f"{c['grasps_start']} / {c['grasps_goal']}" for c in suite["cases"]}
    case["grasps"] = np.array([grasps.get(c, "–") for c in case["case"]], dtype=object)
    everything = (np.ones(len(case["case"]), bool), np.ones(len(run["case"]), bool))
    by_object = [(o, rates(case, run, case["object"] == o, run["object"] == o)) for o in suite["objects"]]
    by_kind = [(k, rates(case, run, case["kind"] == k, run["kind"] == k)) for k in ("translate", "rotate", "face")]
    total = rates(case, run, *everything)
    figs = out / "figures"
    plots.show_benchmark_rates(by_object, figs / "rates_by_object.png")
    plots.show_benchmark_times(stage_samples(run, "t"), figs / "stage_times.png")
    views = view.write_case_views(out, suite["cases"])  # each case's 3D view, linked from its row
    first = run["seed"] == 0
    chain = np.nansum([run[f"t_{s}"][first].astype(float) for s in STAGES], axis=0)
    seeds = int(run["seed"].max()) + 1 if len(run["seed"]) else 0
    text = [f"# pivot benchmark: {total['cases']} cases, {seeds} seeds each",
            "", f"Suite `{out.name}`: {len(suite['objects'])} objects "
            f"({', '.join(suite['objects'])}), goal kinds translate / rotate / face; seed 0 runs the nominal "
            "physics, seeds > 0 perturb friction, CoM, inertia, mass and the initial position. "
            "Regenerate: `make benchmark`.", "",
            "## Overall", "", *rate_rows("suite", [("all", total)]), "",
            "## Per object", "", *rate_rows("object", by_object), "", "![rates](figures/rates_by_object.png)", "",
            "## Per goal kind", "", *rate_rows("goal kind", by_kind), "",
            "## Failure reasons, most common first", "", *failure_rows(case, run), "",
            "## Unreachable goals (the necessary test's label; counted apart, not dropped)", "",
            *unreachable_rows(case), "",
            "## Time per stage", "", *time_rows(run), "",
            whole_chain(chain), "",
            "![times](figures/stage_times.png)", "",
            "## Every case (rerun one: `pivot run OUT/scenes/<case>.json`)", "", *every_case_rows(case, run, views), ""]
    path = out / "report.md"
    with artifacts.atomic_path(path) as tmp:
        tmp.write_text("\n".join(text))
    return path
