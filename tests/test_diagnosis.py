"""Why a plan has no path (stages.diagnosis): each cause on a hand-made graph, then on small scenes."""

from types import SimpleNamespace

import numpy as np
import pytest

from stages import plan
from stages.artifacts import Table
from tests.conftest import PIANO, write_scene


def table(**cols) -> Table:
    return Table({k: np.asarray(v) for k, v in cols.items()}, {})


def toy(pivot12="ok", regrasp2="ok", pivot12_exists=True, support0="SP", goal_face=0, rolls=True):
    """Three poses in a row on placement 0 (the goal pose 2 on ``goal_face``), pivot links 0-1-2; a
    grasp node (0, 1, 2) and a free node (3, 4, 5) per pose (none for a USP pose); regrasp edges
    grasp-free, pivot edges 0-1 and 1-2 (statuses as given); ``rolls``: tumbles lead from face 0 to
    the goal's. A stand-in for ``plan._Context``."""
    sp = [support0 == "SP", True, True]
    free = [3 + k for k in range(sum(sp))]
    nodes = table(node_id=np.arange(3 + len(free)), kind=["grasp"] * 3 + ["free"] * len(free),
                  pose_id=[0, 1, 2, *[i for i in range(3) if sp[i]]], grasp_id=[0, 1, 2, *[-1] * len(free)],
                  support=[support0, "SP", "SP", *["SP"] * len(free)])
    rows = [(i, f, "regrasp", regrasp2 if i == 2 else "ok") for i, f in zip(np.flatnonzero(sp), free, strict=True)]
    rows += [(0, 1, "pivot", "ok")] + ([(1, 2, "pivot", pivot12)] if pivot12_exists else [])
    a, b, prim, status = map(list, zip(*rows, strict=True))
    edges = table(edge_id=np.arange(len(a)), node_a=a, node_b=b, primitive=prim, status=status,
                  directed=np.zeros(len(a), bool), weight=np.ones(len(a)))
    poses = table(placement_id=[0, 0, goal_face], support=[support0, "SP", "SP"], status=["ok"] * 3)
    links = table(pose_a=[0, 1], pose_b=[1, 2], primitive=["pivot", "pivot"])
    rejects = table(pose_id=[0, 2, 2], reason=["ik_unreachable", "normal_away", "env_collision:a/b"])
    return SimpleNamespace(nodes=nodes, edges=edges, poses=poses, links=links, rejects=rejects,
                           sample={"goal": {"pose_id": 2},
                                   "face_route": ([0] if goal_face == 0 else [0, goal_face]) if rolls else []})


def infeasible(ctx, params=plan.Params(), removed=()):  # noqa: B008 (frozen dataclass)
    G, start, goal = plan.build_search_graph(ctx, params)
    for a, b in removed:
        G.remove_edges_from([(a, b), (b, a)])
    log = [{"edge_id": int(np.flatnonzero((ctx.edges["node_a"] == a) & (ctx.edges["node_b"] == b))[0]),
            "reason": "mpc_infeasible"} for a, b in removed]
    return plan._infeasible(ctx, params, G, start, goal, log, "no path in the graph")


def test_a_cut_pivot_is_pivot_rejected_with_its_reason_counted():
    p = infeasible(toy(pivot12="unstable"))
    d = p["diagnosis"]
    assert p["reason"] == "no path in the graph: the pivots that lead on are rejected"
    assert d["causes"] == ["pivot_rejected"] and d["leads_on_rejected"] == {"pivot": {"unstable": 1}}
    assert d["reached"] == {"nodes": 4, "poses": 2, "placements": [0]} and d["goal_connected"]
    assert d["goal"]["grasps"] == 1 and d["goal"]["rejected"] == {"env_collision": 1, "normal_away": 1}
    assert "pivot 1 (unstable 1)" in d["detail"]


def test_a_pivot_removed_by_backtracking_counts_with_its_motion_reason():
    d = infeasible(toy(), removed=[(1, 2)])["diagnosis"]
    assert d["cause"] == "pivot_rejected" and d["leads_on_rejected"] == {"pivot": {"mpc_infeasible": 1}}


def test_a_refused_release_at_the_goal_is_regrasp_rejected():
    d = infeasible(toy(regrasp2="env_collision:left_link_6_b/object"))["diagnosis"]
    assert d["cause"] == "regrasp_rejected" and d["leads_on_rejected"] == {"regrasp": {"env_collision": 1}}


def test_no_pivot_candidate_between_grasps_is_no_shared_grasp():
    d = infeasible(toy(pivot12_exists=False))["diagnosis"]
    assert d["cause"] == "no_shared_grasp" and d["leads_on_rejected"] == {}
    assert d["links_leading_on"] == {"no_shared_grasp": 1}


def test_a_tumble_link_off_the_goal_does_not_connect_the_goal():
    """The only link between poses 1 and 2 tumbles the object from the goal pose onto pose 1: the
    search cannot roll it back that way, so the goal is not connected to the start's lattice."""
    ctx = toy(pivot12_exists=False)
    ctx.links = table(pose_a=[0, 2], pose_b=[1, 1], primitive=["pivot", "tumble"])
    d = infeasible(ctx)["diagnosis"]
    assert not d["goal_connected"] and d["cause"] == "goal_not_connected"


def test_a_usp_start_is_start_not_sp():
    p = infeasible(toy(support0="USP"))
    assert p["reason"] == "no path in the graph: the start pose is not SP"
    assert p["diagnosis"]["causes"][0] == "start_not_sp" and "no free node" in p["diagnosis"]["detail"]


def test_a_goal_on_a_face_no_tumble_link_reaches_is_no_tumble_to_goal_face():
    d = infeasible(toy(goal_face=1))["diagnosis"]
    assert d["causes"] == ["no_tumble_to_goal_face"]
    assert d["tumbles_onto_goal_face"]["links"] == 0


def test_a_goal_face_no_sequence_of_tumbles_leads_to_is_no_roll_to_goal_face():
    p = infeasible(toy(goal_face=1, rolls=False))
    d = p["diagnosis"]
    assert p["reason"] == "no path in the graph: no sequence of tumbles leads from the start's face to the goal's"
    assert d["causes"][0] == "no_roll_to_goal_face" and d["tumbles_onto_goal_face"]["face_route"] == []
    assert "no roll" in d["detail"]


def test_an_ablation_counts_the_edges_it_drops():
    d = infeasible(toy(), plan.Params(no_regrasp=True, no_tumble=True))["diagnosis"]
    # no_regrasp keeps only the start's grasp and the goal's release: the middle pose's is ablated.
    assert d["edges_rejected"]["regrasp"] == {"ablation": 1}


# --- small scenes: the toy piano, 10-40 poses, one cause each ---------------------------------------

@pytest.fixture(scope="module")
def piano(tmp_path_factory):
    from stages import analyze

    tmp = tmp_path_factory.mktemp("diagnosis")
    analyze.run(PIANO, tmp / "analysis", 3.1, analyze.Params())
    return tmp


def plan_scene(tmp, name, params=plan.Params(), sample_params=None, **changes):  # noqa: B008 (frozen dataclass)
    from stages import graph, sample

    scene, b, a = write_scene(tmp, name, **changes), tmp / name, tmp / "analysis"
    sample.run(scene, a, b / "sample", sample_params or sample.Params())
    graph.run(scene, a, b / "sample", b / "graph", graph.Params())
    return plan.run(scene, a, b / "sample", b / "graph", b / "plan.json", params)


#: Grasps whose contact normals turn more than 120 deg from the shoulder refused: the piano turned -40 deg
#: near the right front then has none (with the default 150 deg, every heading there has some).
STRICT_AWAY = dict(away_angle=np.radians(120.0))


def test_scene_start_turned_away_from_the_arms_has_no_grasp(piano):
    from stages import sample

    p = plan_scene(piano, "start", sample_params=sample.Params(**STRICT_AWAY),
                   **{"start.xy": [0.05, 0.1], "start.yaw_deg": -40, "goal.xy": [0.0, 0.0],
                      "planner.max_poses": 20})
    d = p["diagnosis"]
    assert p["reason"] == "no path in the graph: the start pose has no grasp"
    assert d["start"]["grasps"] == 0 and sum(d["start"]["rejected"].values()) == d["start"]["candidates"] > 0


def test_scene_goal_turned_away_from_the_arms_has_no_grasp(piano):
    from stages import sample

    p = plan_scene(piano, "goal", sample_params=sample.Params(**STRICT_AWAY),
                   **{"goal.xy": [0.05, 0.1], "goal.yaw_deg": -40, "planner.max_poses": 10})
    d = p["diagnosis"]
    assert d["cause"] == "goal_has_no_grasp" and d["start"]["grasps"] > 0 and d["goal"]["grasps"] == 0


def test_scene_goal_beyond_a_small_lattice_is_not_connected(piano, monkeypatch):
    """Without the pivot walk's joins (``poses.Params.walk_strides``, which reach this goal)."""
    import functools

    from stages import poses

    monkeypatch.setattr(poses, "Params", functools.partial(poses.Params, walk_strides=0))
    p = plan_scene(piano, "far", **{"goal.xy": [0.40, 0.0], "planner.max_poses": 20, "planner.goal_reach": 0})
    d = p["diagnosis"]
    assert p["reason"] == "no path in the graph: the goal pose is not connected to the start's pose lattice"
    # 20 poses from the start, the goal, at most a quarter of 20 grown from the goal (poses.Params);
    # goal_reach 0: no A* toward the goal; the sampler's grasp-aware reach then grows at most three
    # rounds of a quarter of 20 (sample.Params.reach_rounds, reach_share) and does not get there either.
    assert d["causes"] == ["goal_not_connected"] and d["goal"]["grasps"] > 0 and 21 < d["lattice_poses"] <= 26 + 15


def test_scene_goal_reach_grows_the_lattice_on_toward_the_goal(piano, monkeypatch):
    """planner.goal_reach reaches the sampler: the same 20-pose scene grows up to 40 poses more toward the
    goal 0.4 m away, beyond the breadth-first and the goal's lattices and the sampler's grasp-aware reach
    (the same scene with goal_reach 0; both without the pivot walks of the reach's last resort)."""
    import functools

    from stages import poses

    monkeypatch.setattr(poses, "Params", functools.partial(poses.Params, walk_strides=0))
    far = plan_scene(piano, "far0", **{"goal.xy": [0.40, 0.0], "planner.max_poses": 20, "planner.goal_reach": 0})
    p = plan_scene(piano, "reach", **{"goal.xy": [0.40, 0.0], "planner.max_poses": 20, "planner.goal_reach": 2})
    assert p["diagnosis"]["lattice_poses"] > far["diagnosis"]["lattice_poses"] + 20


def test_scene_goal_on_its_back_without_tumbling_has_no_tumble_to_its_face(piano):
    p = plan_scene(piano, "back", plan.Params(no_tumble=True), **{"goal.down": [0, 1, 0], "planner.max_poses": 20})
    d = p["diagnosis"]
    assert d["cause"] == "no_tumble_to_goal_face" and d["tumbles_onto_goal_face"]["no_tumble"]
    assert d["goal"]["placement_id"] != d["start"]["placement_id"]


def test_scene_tilting_sixty_degrees_rejects_the_pivots_that_lead_on(piano):
    p = plan_scene(piano, "tilt", **{"planner.tilt_deg": 60, "goal.xy": [-0.1, 0.0], "planner.max_poses": 20})
    d = p["diagnosis"]
    assert d["cause"] == "pivot_rejected" and sum(d["leads_on_rejected"]["pivot"].values()) > 0
    assert d["start"]["grasps"] > 0 and d["goal"]["grasps"] > 0 and d["goal_connected"]


def test_scene_on_its_back_has_no_pusher_for_the_tumbles_onto_that_face(piano):
    """The piano to be laid on its back 0.1 m further: the tumbles onto its back land on it only by
    pushes that no arm reaches (the pushers that could start them on the table's friction, ``graph.
    tip_holds``, are out of reach), which is the cause; most refused tumbles leading on are the pusher's."""
    p = plan_scene(piano, "push", **{"goal.down": [0, 1, 0], "start.xy": [0.1, 0.0], "goal.xy": [0.2, 0.0],
                                     "planner.max_poses": 30})
    d = p["diagnosis"]
    assert p["reason"] == "no path in the graph: the pushing arm cannot reach the tumbles that lead on"
    onto = d["tumbles_onto_goal_face"]
    assert onto["links"] > 0 and onto["edges_ok"] == 0 and onto["cause"] == "pusher_out_of_reach"
    tumbles = d["leads_on_rejected"]["tumble"]
    assert tumbles.get("ik_unreachable", 0) + tumbles.get("joint_limit", 0) >= sum(tumbles.values()) / 2


def test_a_route_onto_a_pose_without_grasps_names_it_as_the_barrier():
    """Poses 0-1-2-3 pivoted in a row, the goal 3: pose 2 has no grasp, so the nearest route leaves the
    reached poses (0, 1) onto a pose with no grasp, which is the cause."""
    nodes = table(node_id=np.arange(7), kind=["grasp"] * 3 + ["free"] * 4, pose_id=[0, 1, 3, 0, 1, 2, 3],
                  grasp_id=[0, 1, 2, -1, -1, -1, -1], support=["SP"] * 7)
    a, b = [0, 1, 2, 0], [3, 4, 6, 1]
    edges = table(edge_id=np.arange(4), node_a=a, node_b=b, primitive=["regrasp"] * 3 + ["pivot"],
                  status=["ok"] * 4, directed=np.zeros(4, bool), weight=np.ones(4))
    ctx = SimpleNamespace(nodes=nodes, edges=edges, poses=table(placement_id=[0] * 4, support=["SP"] * 4,
                                                                status=["ok"] * 4),
                          links=table(pose_a=[0, 1, 2], pose_b=[1, 2, 3], primitive=["pivot"] * 3),
                          rejects=table(pose_id=[2], reason=["ik_unreachable"]),
                          sample={"goal": {"pose_id": 3}, "face_route": [0]})
    p = infeasible(ctx)
    d = p["diagnosis"]
    assert p["reason"] == "no path in the graph: the poses that lead on have no grasp"
    assert d["route_link"] == {"poses": [1, 2], "class": "next_pose_has_no_grasp"}
    assert d["links_leading_on"] == {"next_pose_has_no_grasp": 1}


def test_a_route_whose_links_pass_from_grasps_the_start_does_not_reach_says_so():
    """Pose 1 has a second grasp (node 6) whose pivot onto pose 2 passes, but its regrasp from pose 1's
    free node is refused, and the reached grasp's pivot is unstable: the nearest route leaves the
    reached poses by a link whose passing edge starts from a grasp the start does not reach, which is
    the cause; no refusal is named as that link's barrier."""
    ctx = toy(pivot12="unstable")
    n, e = ctx.nodes.columns, ctx.edges.columns
    ctx.nodes = table(**{k: np.append(v, x) for (k, v), x in
                         zip(n.items(), (6, "grasp", 1, 3, "SP"), strict=True)})
    m = len(e["edge_id"]) + 2
    ctx.edges = table(edge_id=np.arange(m), node_a=np.append(e["node_a"], [6, 6]),
                      node_b=np.append(e["node_b"], [4, 2]),
                      primitive=np.append(e["primitive"], ["regrasp", "pivot"]),
                      status=np.append(e["status"], ["env_collision:left_link_6_b/object", "ok"]),
                      directed=np.zeros(m, bool), weight=np.ones(m))
    p = infeasible(ctx)
    d = p["diagnosis"]
    assert d["route_link"] == {"poses": [1, 2], "class": "pivot:grasp_not_reached"}
    assert d["cause"] == "grasp_not_reached"
    assert p["reason"] == "no path in the graph: the start reaches no grasp that leads on"
    assert not any(k.endswith(":ok") for k in d["links_leading_on"])
