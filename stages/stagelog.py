"""What each stage logs: counts and decisions at INFO, per-edge and per-step reasons at DEBUG.

Each stage's ``run`` calls its ``log_*`` function once, after it wrote its artifacts, with what it
wrote; the messages go to the stage's logger (``stages.<stage>``), which ``pivot -v`` (INFO) and
``pivot -vv`` (DEBUG) show on stderr. Only summaries are formatted unless DEBUG is on, so a quiet run
pays nothing for the per-edge lines.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping

import numpy as np


def _counts(d: Mapping) -> str:
    return ", ".join(f"{k} {v}" for k, v in sorted(d.items()))


def log_analysis(summary: Mapping) -> None:
    """Counts of the analysis (facets, pivot vertices, placements, contacts, pairs) and what was filtered."""
    log = logging.getLogger("stages.analyze")
    log.info("analysis: %s", _counts(summary["counts"]))
    log.debug("analysis: contact candidates filtered: %s", _counts(summary.get("filtered", {})))


def log_sample(summary: Mapping, rejects: Mapping[str, np.ndarray]) -> None:
    """Poses by status, grasps kept of the candidates, and each grasp rejection (pose, pair, reason)."""
    log = logging.getLogger("stages.sample")
    log.info("sample: poses %s; %d SP, %d USP; goal %s", _counts(summary["poses"]), summary["poses_sp"],
             summary["poses_usp"], summary["goal"]["status"])
    log.info("sample: %d grasps of %d candidates; rejected: %s", summary["grasps"], summary["candidates"],
             _counts(summary.get("rejected", {})))
    if log.isEnabledFor(logging.DEBUG):
        for pose, pair, reason in zip(rejects["pose_id"], rejects["pair_id"], rejects["reason"], strict=True):
            log.debug("sample: pose %d pair %d rejected: %s", pose, pair, reason)


def log_graph(summary: Mapping, edges: Mapping[str, np.ndarray]) -> None:
    """Nodes by kind, edges ok/rejected by primitive, rejection reasons, and each rejected edge."""
    log = logging.getLogger("stages.graph")
    log.info("graph: nodes %s", _counts(summary["nodes"]))
    log.info("graph: edges %s", ", ".join(f"{k} {v['ok']} ok / {v['rejected']} rejected"
                                          for k, v in sorted(summary["edges"].items())))
    log.info("graph: rejected because %s", _counts(summary.get("reasons", {})))
    if log.isEnabledFor(logging.DEBUG):
        bad = np.flatnonzero(np.asarray(edges["status"]) != "ok")
        for i in bad:
            log.debug("graph: edge %d %s %d -> %d rejected: %s", edges["edge_id"][i], edges["primitive"][i],
                      edges["node_a"][i], edges["node_b"][i], edges["status"][i])


def backtracks(plan: Mapping) -> int:
    """Edges the plan's walk removed (backtracking, §5.3): its log less the graph stage's deferred
    refusals (``graph_check``, ``stages.plan._graph_arm_checks``)."""
    return sum(not e.get("graph_check") for e in plan.get("log", []))


def log_plan(plan: Mapping) -> None:
    """The plan's status, cost and counts; each edge backtracking removed and each step, with reasons."""
    log = logging.getLogger("stages.plan")
    log.info("plan: %s, cost %s, %s; %d edges removed by backtracking", plan["status"], plan.get("cost"),
             _counts(plan.get("counts", {})), backtracks(plan))
    if plan["status"] == "infeasible":
        log.info("plan: infeasible: %s", plan.get("reason"))
    for e in plan.get("log", []):
        log.debug("plan: removed %s edge %s (%s -> %s): %s", e.get("primitive"), e.get("edge_id"), e.get("node_a"),
                  e.get("node_b"), e.get("reason"))
    for i, s in enumerate(plan.get("steps", [])):
        log.debug("plan: step %d: %s pose %s -> %s", i, s.get("primitive"), s.get("pose_from"), s.get("pose_to"))


def log_trajectories(stats: Mapping, primitive: np.ndarray | None = None) -> None:
    """The MPC's status, primitives, steps and error; the steps of each primitive."""
    log = logging.getLogger("stages.trajectory")
    log.info("mpc: %s, %s primitives, %s steps, %.1f s of motion, tracking error <= %.2e rad", stats["status"],
             stats.get("primitives"), stats.get("steps"), stats.get("duration", 0.0), stats.get("mpc_max_error", 0.0))
    if stats["status"] != "ok":
        log.info("mpc: failed on primitive %s: %s", stats.get("failed_primitive"), stats.get("reason"))
    if primitive is not None and log.isEnabledFor(logging.DEBUG):
        ids, n = np.unique(np.asarray(primitive), return_counts=True)
        for p, k in zip(ids, n, strict=True):
            log.debug("mpc: primitive %d: %d steps", p, k)


def log_execution(metrics: Mapping, log_cols: Mapping[str, np.ndarray]) -> None:
    """Success and the final errors; per primitive the worst CoM error and pivot slip along it."""
    log = logging.getLogger("stages.execute")
    log.info("execute: success %s, final error %.4f m / %.2f deg, max pivot slip %.4f m, fell %s, collision %s",
             metrics["success"], metrics["final_position_error"], metrics["final_yaw_error_deg"],
             metrics["max_pivot_slip"], metrics["fell"], metrics["collision"])
    if log.isEnabledFor(logging.DEBUG):
        prim = np.asarray(log_cols["primitive"])
        for p in np.unique(prim):
            m = prim == p
            log.debug("execute: primitive %d: %d steps, CoM error <= %.4f m, pivot slip <= %.4f m", p, m.sum(),
                      np.max(log_cols["com_error"][m]), np.max(log_cols["pivot_slip"][m]))
