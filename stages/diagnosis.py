"""Why the plan graph has no path from the start to the goal: the cause, and counts (§5.3, issue 14).

"No path in the graph" hides causes that each ask the user for another change. :func:`diagnose` checks
them in this order; ``causes`` lists every one that holds and ``cause`` is the first:

1. ``start_not_sp``, ``goal_not_sp``: the pose is USP, so it has no free node (the object cannot be
   left standing there alone);
2. ``start_has_no_grasp``, ``goal_has_no_grasp``: every (pose, pair) candidate there was refused;
   ``rejected`` counts them by reason family (``ik_unreachable``, ``env_collision``, ...);
3. ``no_roll_to_goal_face``: the goal lies on another face and no sequence of tumbles leads from the
   start's face to it whatever the poses (``sample.json``'s ``face_route``, ``stages.poses.face_route``:
   every roll toward it falls back or rolls on); ``no_tumble_to_goal_face``: no tumble link of the
   lattice lands on it (or the ``no_tumble`` ablation); ``pusher_out_of_reach`` / ``tumble_rejected``: tumble edges
   land on it but every one is refused, mostly for the pusher (``ik_unreachable``, ``joint_limit``,
   ``no_pusher_contact``) or for something else (the catch, a collision);
4. ``goal_not_connected``: no lattice route leads from the start to the goal pose (pivot links both
   ways, tumble links from their pose onto their landing only, grasps ignored, the ablations
   applied): none of the pivots that join it to the lattice (``stages.poses._insert_goal``) starts
   from a pose the start's links lead to;
5. the grasp graph is cut: each lattice link from a pose the start reaches to one it does not is
   classed (:func:`link_classes`): ``next_pose_has_no_grasp``; ``no_shared_grasp``, no edge joins
   the two poses (a pivot keeps its grasp, §5.1, and the two have none in common); or by the
   primitive of most of the refused edges between them when all are refused, ``pivot_rejected``,
   ``tumble_rejected`` or ``pusher_out_of_reach`` (an edge removed by backtracking counts with its
   motion-level reason, one an ablation drops as ``ablation``), or ``grasp_not_reached`` when one of
   them passes but from a grasp of the reached pose that the start does not reach (nor a regrasp
   there leads to). The cause is the class of the first link that the nearest
   lattice route from the reached poses to the goal takes out of them (the first barrier on the way);
   all links are counted in ``links_leading_on``. With no such route, the primitive of most refused
   edges leading on from the reached nodes (USP regrasps, catches).

The plan's ``reason`` takes a fixed phrase per cause (:data:`REASONS`), since the benchmark turns it
into a reason code; the numbers stay in the diagnosis dict, and ``detail`` says the main ones in one
line.
"""

from __future__ import annotations

from dataclasses import dataclass

import networkx as nx
import numpy as np

from stages.artifacts import Table

REASONS = {
    "start_not_sp": "the start pose is not SP",
    "goal_not_sp": "the goal pose is not SP",
    "start_has_no_grasp": "the start pose has no grasp",
    "goal_has_no_grasp": "the goal pose has no grasp",
    "no_roll_to_goal_face": "no sequence of tumbles leads from the start's face to the goal's",
    "no_tumble_to_goal_face": "no tumble reaches the goal's face",
    "pusher_out_of_reach": "the pushing arm cannot reach the tumbles that lead on",
    "tumble_rejected": "the tumbles that lead on are rejected",
    "goal_not_connected": "the goal pose is not connected to the start's pose lattice",
    "pivot_rejected": "the pivots that lead on are rejected",
    "regrasp_rejected": "the regrasps that lead on are rejected",
    "no_shared_grasp": "no grasp is shared with the next poses",
    "next_pose_has_no_grasp": "the poses that lead on have no grasp",
    "grasp_not_reached": "the start reaches no grasp that leads on",
}
#: Reason families of a tumble whose pushing arm cannot reach or push.
PUSHER_REASONS = ("ik_unreachable", "joint_limit", "no_pusher_contact")


@dataclass(frozen=True)
class Tables:
    """The artifacts a diagnosis reads: ``nodes``, ``edges`` (graph), ``poses``, ``links``
    (``pose_links``), ``rejects`` (``grasp_rejects``) of the sample, the goal's pose id (-1 when
    the sampler has none) and ``face_route``, the sample's placements from the start's face to the
    goal's (``[]``: no sequence of tumbles leads there)."""

    nodes: Table
    edges: Table
    poses: Table
    links: Table
    rejects: Table
    goal_pose: int
    face_route: list


def family(reason: str) -> str:
    """A reason code's family: ``env_collision:left_link_6_b/table`` -> ``env_collision``."""
    return str(reason).split(":", 1)[0]


def count_reasons(reasons) -> dict[str, int]:
    """Counts of the reason families in ``reasons``, most frequent first (ties by name)."""
    fam, n = np.unique(np.array([family(r) for r in reasons], dtype=str), return_counts=True)
    order = np.lexsort((fam, -n))
    return {str(fam[i]): int(n[i]) for i in order}


def pose_facts(t: Tables, pose: int) -> dict:
    """Placement, support, grasps and refused candidates (by family) of one pose (-1: none)."""
    if pose < 0:
        return {"pose_id": -1, "grasps": 0, "candidates": 0, "rejected": {}}
    grasps = int(np.count_nonzero((t.nodes["pose_id"] == pose) & (t.nodes["kind"] == "grasp")))
    mine = t.rejects["pose_id"] == pose
    return {"pose_id": int(pose), "placement_id": int(t.poses["placement_id"][pose]),
            "support": str(t.poses["support"][pose]), "grasps": grasps,
            "candidates": grasps + int(np.count_nonzero(mine)), "rejected": count_reasons(t.rejects["reason"][mine])}


def lattice(t: Tables, no_tumble: bool, no_usp: bool) -> nx.DiGraph:
    """The kept poses joined by their pivot links both ways and their tumble links from the pose onto
    the landing only, as the search can take them (grasps ignored), with the ablations."""
    keep = np.ones(len(t.links), bool)
    if no_tumble:
        keep &= t.links["primitive"] != "tumble"
    if no_usp:
        usp = t.poses["support"] == "USP"
        keep &= ~(usp[t.links["pose_a"]] | usp[t.links["pose_b"]])
    L = nx.DiGraph()
    L.add_nodes_from(np.flatnonzero(t.poses["status"] == "ok").tolist())
    a, b = t.links["pose_a"], t.links["pose_b"]
    L.add_edges_from(zip(a[keep].tolist(), b[keep].tolist(), strict=True))
    back = keep & (t.links["primitive"] == "pivot")
    L.add_edges_from(zip(b[back].tolist(), a[back].tolist(), strict=True))
    return L


def edge_status(t: Tables, ablated: np.ndarray, removed: dict[int, str]) -> np.ndarray:
    """Each edge's status as the search saw it ``(E,)``: its graph status, ``ablation`` for an ok
    edge an ablation drops, the motion-level reason for one that backtracking removed."""
    status = np.asarray(t.edges["status"], dtype=object).copy()
    status[(status == "ok") & ablated] = "ablation"
    for e, why in removed.items():
        status[e] = why
    return status.astype(str)


def frontier(t: Tables, status: np.ndarray, reached: np.ndarray) -> dict[str, dict[str, int]]:
    """Refused edges that would lead from a reached node to one not reached, per primitive, counted
    by reason family. ``reached (n_nodes,)`` bool."""
    a, b = t.edges["node_a"], t.edges["node_b"]
    out_of = (reached[a] & ~reached[b]) | (~t.edges["directed"] & reached[b] & ~reached[a])
    sel = out_of & (status != "ok")
    return {p: count_reasons(status[sel & (t.edges["primitive"] == p)])
            for p in ("pivot", "regrasp", "tumble") if np.any(sel & (t.edges["primitive"] == p))}


def tumble_cause(rejected: dict[str, int]) -> str:
    """``pusher_out_of_reach`` when the pusher's reasons are at least half of the refused tumbles'."""
    pusher = sum(n for r, n in rejected.items() if r in PUSHER_REASONS)
    return "pusher_out_of_reach" if 2 * pusher >= sum(rejected.values()) else "tumble_rejected"


def _onto_goal_face(t: Tables, status: np.ndarray, face: int, no_tumble: bool) -> tuple[dict, str | None]:
    """Tumble links and edges landing on placement ``face`` from another, and the cause they give
    (None when an edge lands there, ``no_roll_to_goal_face`` when no tumbles lead from the start's
    face to it at all)."""
    g = t.poses["placement_id"]
    la, lb = t.links["pose_a"], t.links["pose_b"]
    links = int(np.count_nonzero((t.links["primitive"] == "tumble") & (g[lb] == face) & (g[la] != face)))
    pose = t.nodes["pose_id"]
    onto = (t.edges["primitive"] == "tumble") & (g[pose[t.edges["node_b"]]] == face)
    ok = int(np.count_nonzero(onto & (status == "ok")))
    rejected = count_reasons(status[onto & (status != "ok")])
    if not t.face_route:
        why = "no_roll_to_goal_face"
    elif no_tumble or links == 0:
        why = "no_tumble_to_goal_face"
    else:
        why = None if ok else tumble_cause(rejected) if rejected else "no_tumble_to_goal_face"
    return {"links": links, "edges_ok": ok, "edges_rejected": rejected, "no_tumble": bool(no_tumble),
            "face_route": [int(g) for g in t.face_route], "cause": why}, why


def link_classes(t: Tables, L: nx.DiGraph, reached_poses: set, status: np.ndarray) -> dict[str, int]:
    """The lattice links from a reached pose to one not reached, by why the search cannot take them:
    the primitive and reason family of most of the refused edges between the two poses
    (``pivot:unstable``, ``tumble:ik_unreachable``, ...) when none passes; ``<primitive>:grasp_not_reached``
    when one passes but starts from a grasp of ``p`` the start does not reach (nor any regrasp
    there), whatever the others were refused for; with no edge between them, ``next_pose_has_no_grasp`` or
    ``no_shared_grasp`` (a pivot keeps its grasp and they share none)."""
    pose_of = t.nodes["pose_id"]
    grasped = set(pose_of[t.nodes["kind"] == "grasp"].tolist())
    pa, pb = pose_of[t.edges["node_a"]], pose_of[t.edges["node_b"]]
    between: dict[tuple[int, int], list[int]] = {}
    for e in np.flatnonzero(pa != pb):  # edges that move the object: their pose pair
        between.setdefault((int(min(pa[e], pb[e])), int(max(pa[e], pb[e]))), []).append(int(e))
    out: dict[str, int] = {}
    for p in reached_poses:
        for q in (L.neighbors(p) if p in L else ()):
            if q in reached_poses:
                continue
            edges = between.get((min(p, q), max(p, q)), [])
            passed = [e for e in edges if status[e] == "ok"]
            if passed:  # one passes, but from a grasp (or free node) at p that the start does not reach
                why = f"{t.edges['primitive'][passed[0]]}:grasp_not_reached"
            elif edges:  # by what most of them are refused for
                fam, n = np.unique([f"{t.edges['primitive'][e]}:{family(status[e])}" for e in edges],
                                   return_counts=True)
                why = str(fam[np.argmax(n)])
            else:
                why = "no_shared_grasp" if q in grasped else "next_pose_has_no_grasp"
            out[why] = out.get(why, 0) + 1
    return dict(sorted(out.items(), key=lambda kv: (-kv[1], kv[0])))


def route_link(L: nx.DiGraph, reached_poses: set, goal_pose: int) -> tuple[int, int] | None:
    """The first link the nearest lattice route from the reached poses to the goal takes out of them
    (multi-source breadth first over the lattice), or None when no route leaves them."""
    src = [p for p in reached_poses if p in L]
    if goal_pose not in L or not src:
        return None
    try:
        path = nx.multi_source_dijkstra_path(L, src)[goal_pose]
    except KeyError:  # the goal is not in the reached poses' component
        return None
    return (path[0], path[1]) if len(path) > 1 else None


def _cut_cause(t: Tables, L: nx.DiGraph, reached_poses: set, leads_on: dict, status: np.ndarray) -> tuple[str, dict]:
    """The cause when the graph is cut past the poses the start reaches (module docstring, 5–6): the
    class (:func:`link_classes`) of the first link the nearest lattice route to the goal takes out of
    them; without one, the primitive of most refused edges leading on."""
    links = link_classes(t, L, reached_poses, status)
    facts = {"links_leading_on": links}
    first = route_link(L, reached_poses, t.goal_pose)
    if first is not None:
        cls = next(iter(link_classes(t, L.subgraph(first), {first[0]}, status)))
        facts["route_link"] = {"poses": [int(first[0]), int(first[1])], "class": cls}
        if ":" not in cls:
            return cls, facts
        prim, fam = cls.split(":")
        if fam == "grasp_not_reached":
            return "grasp_not_reached", facts
        return (tumble_cause({fam: 1}) if prim == "tumble" else f"{prim}_rejected"), facts
    if not leads_on:
        return "no_shared_grasp", facts
    prim = max(leads_on, key=lambda p: (sum(leads_on[p].values()), p))
    return (tumble_cause(leads_on[prim]) if prim == "tumble" else f"{prim}_rejected"), facts


def diagnose(t: Tables, G: nx.DiGraph, start: int, goal: int, ablated: np.ndarray, removed: dict[int, str],
             no_tumble: bool = False, no_usp: bool = False) -> dict:
    """Why ``G`` (the search graph, after any backtracking) has no path from node ``start`` to node
    ``goal`` (free nodes, -1 when the pose has none): the module docstring's causes and counts.

    ``ablated (E,)`` bool marks the ok edges the ablations drop, ``removed`` maps the edges that
    backtracking removed to their reason. Returns the ``diagnosis`` dict of ``plan.json``.
    """
    facts = {"start": pose_facts(t, 0), "goal": pose_facts(t, t.goal_pose)}
    causes = [f"{w}_not_sp" for w in ("start", "goal") if facts[w]["pose_id"] >= 0 and facts[w]["support"] != "SP"]
    causes += [f"{w}_has_no_grasp" for w in ("start", "goal") if facts[w]["grasps"] == 0]
    status = edge_status(t, ablated, removed)
    if t.goal_pose >= 0 and facts["goal"]["placement_id"] != facts["start"]["placement_id"]:
        facts["tumbles_onto_goal_face"], why = _onto_goal_face(t, status, facts["goal"]["placement_id"], no_tumble)
        causes += [why] if why else []
    L = lattice(t, no_tumble, no_usp)
    facts["lattice_poses"] = L.number_of_nodes()
    facts["goal_connected"] = bool(0 in L and t.goal_pose in L and nx.has_path(L, 0, t.goal_pose))
    causes += [] if facts["goal_connected"] else ["goal_not_connected"]
    reached = np.zeros(len(t.nodes), bool)
    if start >= 0:
        reached[[start, *nx.descendants(G, start)]] = True
    reached_poses = set(t.nodes["pose_id"][reached].tolist())
    facts["reached"] = {"nodes": int(reached.sum()), "poses": len(reached_poses),
                        "placements": sorted({int(t.poses["placement_id"][p]) for p in reached_poses})}
    facts["edges_rejected"] = {p: count_reasons(status[(t.edges["primitive"] == p) & (status != "ok")])
                               for p in ("pivot", "regrasp", "tumble")}
    facts["leads_on_rejected"] = frontier(t, status, reached)
    if not causes:
        cut, more = _cut_cause(t, L, reached_poses, facts["leads_on_rejected"], status)
        causes, facts = [cut], {**facts, **more}
    return {"cause": causes[0], "causes": causes, **facts, "detail": detail(causes[0], facts)}


def _top(counts: dict[str, int], k: int = 3) -> str:
    return ", ".join(f"{r} {n}" for r, n in list(counts.items())[:k]) or "none"


def detail(cause: str, d: dict) -> str:
    """One line with the counts that say what to change for ``cause`` (``d`` the diagnosis' facts)."""
    if cause.endswith("_not_sp"):
        w = cause.split("_")[0]
        return f"{w} pose {d[w]['pose_id']} is {d[w]['support']} on placement {d[w]['placement_id']}: no free node"
    if cause in ("start_has_no_grasp", "goal_has_no_grasp"):
        w = cause.split("_")[0]
        return f"{w} pose: 0 grasps of {d[w]['candidates']} candidates ({_top(d[w]['rejected'])})"
    f = d.get("tumbles_onto_goal_face", {})
    if cause == "no_roll_to_goal_face":
        return (f"goal on placement {d['goal']['placement_id']}, start on {d['start']['placement_id']}: no roll "
                "over a support edge of the faces tumbles reach from the start's lands on the goal's")
    if f.get("cause") == cause:
        off = ", tumbling switched off" if f["no_tumble"] else ""
        return (f"goal on placement {d['goal']['placement_id']}, start on {d['start']['placement_id']}: "
                f"{f['links']} tumble links onto it, {f['edges_ok']} tumble edges ok ({_top(f['edges_rejected'])} "
                f"rejected){off}")
    if cause == "goal_not_connected":
        return (f"no pivot sequence joins the goal pose ({d['goal']['grasps']} grasps) to the start's lattice of "
                f"{d['lattice_poses']} poses")
    reached = f"the start reaches {d['reached']['poses']} poses ({d['reached']['nodes']} nodes)"
    links = d.get("links_leading_on", {})
    leads = "; ".join(f"{p} {sum(c.values())} ({_top(c)})" for p, c in d["leads_on_rejected"].items())
    route = d.get("route_link")
    reached += f"; the nearest route to the goal leaves them by {route['class']}" if route else ""
    return (f"{reached}; lattice links leading on: {_top(links, 4)}"
            + (f"; rejected edges leading on: {leads}" if leads else ""))
