"""Stage ``plan``: search the grasp-augmented graph, check the motions lazily, backtrack (§5.3).

The graph (``stages.graph``) is searched with Dijkstra (networkx) from the start's free node to the
goal's free node. The cheapest path is then checked at the motion level, in order, carrying the
robot's actual joint configuration along (it starts at the home posture, all joints zero):

- **regrasp** (node → free → node in SP; node → node in USP): a collision-free transit of each
  moving arm from its current configuration to the new grasp's IK solution, with retreat and
  approach along the contact normals (``stages.transit``, OMPL's RRT-Connect). In SP the left arm
  moves, then the right; in USP the arms the edge names, one at a time, while the other holds.
- **pivot**: IK along the tilt → rotate → lower motion from the *actual* configuration (no branch
  flips), collisions along it, each ball's tool axis against its contact normal (§5.1's
  ``eef_normal_angle``), where its balls roll to on the object (``stages.rolling``: summed over the
  pivots of one grasp, each contact must stay on its surface, else ``ball_rolls_off``; §5.1 checks
  the ball's angle to the surface for the same reason), and the MPC of §5.2
  (``stages.mpc.run_pivot_mpc``) with the friction and force constraints; ``mpc_infeasible`` is a
  failure like any other, and so is ``mpc_marginal`` (feasible only near the force bound or with a
  large tracking error). A pivot that fails from where the walk left the robot (its balls rolled,
  its arms in another IK branch) is tried again after a retake of its grasp in SP, release and take
  the same contacts, the graph's two regrasp edges (:func:`_check_or_retake`, our addition: the
  graph's checks start from the grasp's own joints, so removing the edge for that state loses it).
- **tumble**: the pusher's transit to its contact, and the push along the rotation. Into SP, when the
  object would fall onto the other arm where the last grasp left it, that arm first goes to its rest
  posture (``{other}_before``), where the graph's pusher check has it; a tumble into SP that fails
  with the graph's pusher (the left arm's first, when it has one) is checked with the other arm's
  pushing and the first arm catching before its edge is removed (our addition). Into USP (a catch node,
  Fig. 18 b–d) the catcher first moves to its catching configuration while the object still stands
  (``{catcher}_before``), the tumbling MPC must lower the object onto it and hold it there
  (:func:`_usp_tumble_mpc`), and after the push the catcher holds the object alone; the hand-over
  that follows (a regrasp edge out of the catch node, Fig. 18 e–f) moves the pusher to its contact
  of the grasp, then the catcher to its own while the pusher's ball holds: a regrasp in USP; or,
  through a hold node, the pusher first to the hold's contact on top, then the catcher to its grasp
  contact and the pusher to its own.
- **squeeze tumble** (a tumble from a grasp node, ``stages.squeeze``): both balls stay on the
  grasp's contacts and roll the object onto its next face: IK from the actual configuration and
  collisions along the roll, the balls' rolling as for a pivot, and the tumbling MPC with both balls
  on throughout (:func:`_check_squeeze_step`).

Before a path is walked, its pivot edges that no path took before get the graph stage's arm checks,
which it defers (``stages.graph.Params.pivot_arms``; LazySP): IK from the grasp's own joints and
collisions along the edge, batched over the path (:func:`_graph_arm_checks`); an edge they refuse is
removed and logged with ``graph_check``, not counted as a backtrack, and the search runs again.
The first failing edge of the walk is removed (both directions for undirected ones), the removal and
its reason are logged, and the search runs again (backtracking, ``stages.stagelog.backtracks``), until a path
passes or none is left. With no path (before or after backtracking) the plan's ``reason`` names the
cause and ``diagnosis`` counts what failed (``stages.diagnosis``: no grasp at the start or goal, the
goal off the lattice, no tumble onto its face, the pivots, tumbles or regrasps that lead on
rejected, and why). A check's outcome is kept
by edge and exact robot state, so the next path re-walks the prefix it shares with the last one
without re-planning it (the result is the same, bit for bit). A pivot's MPC check depends on its edge
alone, not on the robot's state (nor does the state after the pivot depend on it), so its outcome is
kept by edge; with ``Params.mpc_helper`` a forked process runs the MPC checks of the pivots the walk
has passed while the walk goes on, and the outcomes are then taken in path order, so the first
failing edge is the same as when everything runs in turn. The pivot IK first tries all samples in
one vectorized solve (``Robot.ik_trajectory(batch=True)``) and falls back to step by step. Ablations (the paper's
comparisons): ``no_regrasp`` keeps only the first grasp and the final release (the graph MPC gait of
[3]); when the goal is then out of reach the plan goes to the reachable SP pose nearest the goal and
reports the remaining error, as Table 2 does; ``no_tumble`` and ``no_usp`` drop those edges or nodes.
"""

from __future__ import annotations

import multiprocessing
import os
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import networkx as nx
import numpy as np

from stages import artifacts, diagnosis, mpc, poses, provenance, se3, squeeze, stagelog, transit
from stages.graph import (
    PivotChecks,
    check_arm_motion,
    check_pivot_edges,
    eef_normal_angle_change,
    grasp_geometry,
    push_limits,
    pusher_motion,
    recorded_params,
    release_angle,
)
from stages.objectmodel import load_object_model
from stages.robot import load_robot
from stages.rolling import RollLimits, rolled_off, rolling_shift
from stages.sample import clearance_of, make_scene_collision_fn, placement_pose
from stages.scene import Scene, load_scene


@dataclass(frozen=True)
class Params:
    """Planner options (ablations, backtracking budget, motion-level settings)."""

    no_regrasp: bool = False
    no_tumble: bool = False
    no_usp: bool = False
    #: Edges removed at most before giving up.
    max_removals: int = 400
    #: Run the MPC on every pivot of a candidate path, and refuse pivots it can only just track: a
    #: tracking error above ``mpc_max_error`` (rad) or a ball force above ``mpc_max_force`` times the
    #: bound (in PyBullet such pivots slid their vertex by centimetres).
    check_mpc: bool = True
    mpc_max_error: float = 5e-3
    mpc_max_force: float = 0.9
    #: Run the pivots' MPC checks in a forked helper process while the walk goes on, when a core is
    #: idle (the MPC is most of a plan's time: on exp1_reach 2.5 s instead of 3.5 s on the idle
    #: 2-core VM). The plan is the same either way. Not in the artifact's parameters.
    mpc_helper: bool = True
    #: Durations (s) of tilt, rotate, lower of a pivot and of a tumble.
    pivot_durations: tuple[float, float, float] = (2.5, 3.0, 2.5)
    tumble_duration: float = 4.0
    transit: transit.Params = field(default_factory=transit.Params)
    #: MPC settings; dt = 1/24 s puts every row on the physics clock (10 steps of 1/240 s, stages.execute).
    mpc: mpc.Params = field(default_factory=lambda: mpc.Params(dt=1.0 / 24.0))
    #: The MPC plans with this fraction of the scene's friction coefficients, so that the forces it
    #: plans leave room for what the compliant arms add in execution (the squeeze).
    friction_safety: float = 0.8
    #: Check every tumble of a path as ``pivot mpc`` will do it (``stages.trajectory.check_tumble``:
    #: the pusher to its release, a catcher that lowers the object, the tumbling MPC, the catcher's
    #: transit), so that a plan the search returns is one the motion stage can execute.
    check_tumble: bool = True
    #: Where a pivot's balls roll to on the object (``stages.rolling``), accumulated over the pivots a
    #: grasp makes, must stay on the surfaces they were planned on (``ball_rolls_off``), their normals
    #: within the friction cone (``friction_safety`` of the object's friction) of the planned ones.
    roll: RollLimits = field(default_factory=RollLimits)


@dataclass
class _State:
    """Where the robot is while a path is walked."""

    q: dict  # arm -> (n,) joints
    normal: dict  # arm -> (3,) outward contact normal (W) when the ball touches, else None
    X_WO: np.ndarray
    #: arm -> (3,) how far (m, O) its ball has rolled on the object since it took its contact
    roll: dict = field(default_factory=lambda: {"left": np.zeros(3), "right": np.zeros(3)})

    def key(self) -> bytes:
        """The state's exact bytes: a step checked from an equal state gives an equal result."""
        parts = [self.X_WO.tobytes()]
        for arm in ("left", "right"):
            n = self.normal[arm]
            parts += [np.asarray(self.q[arm]).tobytes(), b"-" if n is None else np.asarray(n).tobytes(),
                      self.roll[arm].tobytes()]
        return b"|".join(parts)


class _Context:
    """Everything the motion checks need, loaded once."""

    def __init__(self, scene: Scene, analysis_dir, sample_dir, graph_dir):
        self.scene = scene
        self.model, self.tables = load_object_model(analysis_dir)
        sd, gd = Path(sample_dir), Path(graph_dir)
        self.poses = artifacts.read_table(sd / "poses.parquet", "poses")
        self.grasps = artifacts.read_table(sd / "grasps.parquet", "grasps")
        self.links = artifacts.read_table(sd / "pose_links.parquet", "pose_links")
        self.rejects = artifacts.read_table(sd / "grasp_rejects.parquet", "grasp_rejects")
        self.sample = artifacts.read_json(sd / "sample.json", "sample")
        self.nodes = artifacts.read_table(gd / "nodes.parquet", "nodes")
        self.edges = artifacts.read_table(gd / "edges.parquet", "edges")
        self.graph_params = self.edges.meta["params"]  # what the graph checked with, as recorded
        self.gp = recorded_params(self.graph_params)
        catches = artifacts.read_table(gd / "catches.parquet", "catches")
        self.catch = {int(n): (str(a), int(c), np.asarray(q, dtype=float)) for n, a, c, q in
                      zip(catches["node_id"], catches["arm"], catches["contact"], catches["q"], strict=True)}
        self.X_WO = se3.matrix_from_columns(self.poses.columns)
        self.robot = load_robot(scene.robot.urdf_path, scene.base_transform(), tuple(scene.robot.eef_links))
        self.collide = make_scene_collision_fn(scene, self.robot, self.tables["mesh"],
                                               clearance=clearance_of(self.grasps.meta["params"]))
        con = self.tables["contacts"]
        self.p_O = np.stack([con["px"], con["py"], con["pz"]], axis=1)
        self.n_O = np.stack([con["nx"], con["ny"], con["nz"]], axis=1)
        self.q_grasp = {
            "left": np.stack(list(self.grasps["q_left"])) if len(self.grasps) else np.zeros((0, 7)),
            "right": np.stack(list(self.grasps["q_right"])) if len(self.grasps) else np.zeros((0, 7)),
        }
        self.inputs = {"scene": scene.path, "nodes": gd / "nodes.parquet", "edges": gd / "edges.parquet",
                       "catches": gd / "catches.parquet",
                       "grasps": sd / "grasps.parquet", "poses": sd / "poses.parquet",
                       "pose_links": sd / "pose_links.parquet", "grasp_rejects": sd / "grasp_rejects.parquet",
                       **provenance.analysis_inputs(analysis_dir)}
        self.free_of_pose = free_nodes(self.nodes)
        self._tumble_env = None
        self._pivot_checks = None

    def pivot_checks(self):
        """The grasps' contact points and normals ``(G, 2, 3)`` (O), joints ``(G, 2, n)`` and
        ``pivot_vertices`` sets, for the graph's deferred checks (:func:`_graph_arm_checks`), made once."""
        if self._pivot_checks is None:
            p_g, n_g = grasp_geometry(self.tables, self.grasps, self.scene.robot.ball_radius)
            q_g = np.stack([self.q_grasp["left"], self.q_grasp["right"]], axis=1)
            self._pivot_checks = (p_g, n_g, q_g, [set(np.asarray(v).tolist()) for v in self.grasps["pivot_vertices"]])
        return self._pivot_checks

    def contact(self, grasp: int, arm: str) -> int:
        return int(self.grasps["contact_left" if arm == "left" else "contact_right"][grasp])

    def check_tumble(self, q: dict, step: dict, Xa: np.ndarray, Xb: np.ndarray) -> tuple[str, str]:
        """``stages.trajectory.check_tumble`` with its default parameters (those of ``pivot mpc``)."""
        from stages import trajectory  # it imports this module's neighbours, not this module

        if self._tumble_env is None:
            self._tumble_env = trajectory.make_env(self.scene, self.model, self.tables, self.robot,
                                                   trajectory.Params(), collide=self.collide, graph=self.gp)
        return trajectory.check_tumble(self._tumble_env, q, step, Xa, Xb)


def ablated_edges(nodes, edges, params: Params, start: int, goal: int) -> np.ndarray:
    """``(E,)`` bool: the edges the ablations drop (``no_tumble``: tumbles; ``no_usp``: edges at a USP
    node; ``no_regrasp``: regrasps other than the first grasp out of the ``start`` free node and the
    release into the ``goal``'s)."""
    usp = nodes["support"] == "USP"
    a, b, prim = edges["node_a"], edges["node_b"], edges["primitive"]
    out = np.zeros(len(prim), bool)
    if params.no_tumble:
        out |= prim == "tumble"
    if params.no_usp:
        out |= usp[a] | usp[b]
    if params.no_regrasp:
        out |= (prim == "regrasp") & ~np.isin(a, [start, goal]) & ~np.isin(b, [start, goal])
    return out


def free_nodes(nodes) -> dict[int, int]:
    """Pose id -> its free node (an SP pose with no ball on the object)."""
    free = np.flatnonzero(np.asarray(nodes["kind"]) == "free")
    return dict(zip(np.asarray(nodes["pose_id"])[free].tolist(), np.asarray(nodes["node_id"])[free].tolist(),
                    strict=True))


def build_search_graph(ctx: _Context, params: Params) -> tuple[nx.DiGraph, int, int]:
    """The DiGraph of ok edges after the ablations, with the start and goal free nodes."""
    nodes, edges = ctx.nodes, ctx.edges
    free = free_nodes(nodes)
    start = free.get(0, -1)
    goal = free.get(int(ctx.sample["goal"]["pose_id"]), -1)
    G = nx.DiGraph()
    G.add_nodes_from(nodes["node_id"].tolist())
    ok = np.flatnonzero((edges["status"] == "ok") & ~ablated_edges(nodes, edges, params, start, goal))
    arcs = []  # (a, b, data) in edge order, both ways for undirected edges
    for i, a, b, prim, weight, directed in zip(ok.tolist(), edges["node_a"][ok].tolist(), edges["node_b"][ok].tolist(),
                                               edges["primitive"][ok].tolist(), edges["weight"][ok].tolist(),
                                               edges["directed"][ok].tolist(), strict=True):
        data = {"weight": weight, "edge_id": i, "primitive": prim}
        if params.no_regrasp and prim == "regrasp":
            # Only the first grasp (out of the start's free node) and the final release (into the goal's).
            if a == start or b == goal:
                arcs.append((a, b, data))
            if b == start or a == goal:
                arcs.append((b, a, data))
            continue
        arcs.append((a, b, data))
        if not directed:
            arcs.append((b, a, data))
    G.add_edges_from(arcs)
    return G, start, goal


def movers(edges: dict, edge_id: int, u: int) -> list[str]:
    """The arms a USP regrasp edge moves, in turn, when it is walked from node ``u``: the order its
    ``arm`` column names from ``node_a`` (``"right,left"``), reversed from ``node_b``."""
    arms = str(edges["arm"][edge_id]).split(",")
    return arms if u == int(edges["node_a"][edge_id]) else arms[::-1]


def _transit(ctx: _Context, params: Params, state: _State, arm: str, q_goal, n_goal):
    other = "right" if arm == "left" else "left"
    return transit.plan_transit(ctx.robot, ctx.collide, arm, state.q[arm], q_goal, state.q[other], state.X_WO,
                                params.transit, n_start=state.normal[arm], n_goal=n_goal)


def _check_step(ctx: _Context, params: Params, state: _State, u: int, v: int, data: dict):
    """Check one edge of the path from ``state``; returns ``(ok, reason, step dict, new state)``.

    For a pivot that is the motion check (IK, collisions); its MPC check is :class:`_MPCChecks`'.
    """
    nodes = ctx.nodes
    prim = data["primitive"]
    pu, pv = int(nodes["pose_id"][u]), int(nodes["pose_id"][v])
    gv = int(nodes["grasp_id"][v])
    gu = int(nodes["grasp_id"][u])
    step = {"primitive": prim, "edge_id": data["edge_id"], "node_from": u, "node_to": v, "pose_from": pu,
            "pose_to": pv, "support": str(nodes["support"][v])}
    if prim == "regrasp":
        if nodes["kind"][v] == "free":  # release: the balls stay, backing off at the next transit
            step["arms"] = []
            return True, "ok", step, state
        arms = ["left", "right"] if nodes["kind"][u] == "free" else movers(ctx.edges, data["edge_id"], u)
        new = _State(dict(state.q), dict(state.normal), state.X_WO, dict(state.roll))
        paths = {}
        if nodes["kind"][v] == "hold":  # from a catch: the pusher alone, onto the hold's contact
            (arm_h, c_h, q_h), (arm_c, c_c, _) = ctx.catch[v], ctx.catch[u]
            target = {arm_h: (c_h, q_h)}
            contacts = {arm_h: c_h, arm_c: c_c}
        else:
            target = {a: (ctx.contact(gv, a), ctx.q_grasp[a][gv]) for a in ("left", "right")}
            contacts = {a: ctx.contact(gv, a) for a in ("left", "right")}
        for arm in arms:
            c, q_goal = target[arm]
            n_goal = se3.rotate_vectors(new.X_WO, ctx.n_O[c])
            res = _transit(ctx, params, new, arm, q_goal, n_goal)
            if res.status != "ok":
                return False, res.status, {**step, "detail": f"{arm} arm: {res.reason}"}, state
            paths[arm] = res.path
            new.q[arm] = res.path[-1]
            new.normal[arm] = n_goal
            new.roll[arm] = np.zeros(3)
        step.update(arms=arms, grasp_to=gv, transit={a: p.tolist() for a, p in paths.items()}, contacts=contacts)
        return True, "ok", step, new
    if prim == "pivot":
        vtx, Xa, Xb, p0, t, Xr = _pivot_motion(ctx, params, u, v, data["edge_id"])
        cl, cr = ctx.contact(gu, "left"), ctx.contact(gu, "right")
        p_c, n_c = ctx.p_O[[cl, cr]], ctx.n_O[[cl, cr]]
        q0 = np.stack([state.q["left"], state.q["right"]])[None]
        every = max(1, int(round(0.1 / params.mpc.dt)))  # IK and collisions every 0.1 s of the motion
        sub = np.unique(np.r_[np.arange(0, len(Xr), every), len(Xr) - 1])
        ok, why, q = check_arm_motion(ctx.robot, ctx.collide, Xr[sub][None], p_c[None], n_c[None], q0,
                                      ctx.scene.robot.ball_radius, ctx.gp, batch=True)
        if not ok[0]:
            return False, str(why[0]), step, state
        if eef_normal_angle_change(ctx.robot, q, Xr[sub][None], n_c[None])[0] > ctx.gp.max_eef_normal_change:
            return False, "eef_normal_angle", step, state
        roll, detail = _rolled(ctx, params, state, q[:, 0], Xr[sub], p_c, n_c)
        if roll is None:
            return False, "ball_rolls_off", {**step, "detail": detail}, state
        # The MPC check (``_MPCChecks``) depends on the arc alone; the walk asks for it.
        new = _State({"left": q[-1, 0, 0], "right": q[-1, 0, 1]},
                     {"left": se3.rotate_vectors(Xb, n_c[0]), "right": se3.rotate_vectors(Xb, n_c[1])}, Xb, roll)
        step.update(vertex=vtx, angle=float(_yaw_between(Xa, Xb)), grasp=gu,
                    contacts={"left": cl, "right": cr})
        return True, "ok", step, new
    if nodes["kind"][u] == "grasp":  # grasp -> grasp: the grasp itself rolls the object
        return _check_squeeze_step(ctx, params, state, data, step, gu)
    return _check_tumble_step(ctx, params, state, u, v, data, step)


def _check_or_retake(ctx: _Context, params: Params, G: nx.DiGraph, state: _State, u: int, v: int, data: dict):
    """:func:`_check_step`, returning the steps walked as a list. A pivot or squeeze tumble that fails
    from where the walk left the balls is tried once more after a retake of its grasp in SP (release
    to the pose's free node, the same contacts again: the graph's two regrasp edges). The motions
    before it left state the graph's checks do not see (balls rolled on the object,
    ``ball_rolls_off``; arms in another IK branch); a retake puts the balls back on the planned
    contacts with the grasp's own joints, at the cost of a regrasp. The failure stands, and the edge
    is removed, when the retake or the motion after it fails too."""
    ok, why, step, new = _check_step(ctx, params, state, u, v, data)
    if ok or data["primitive"] == "regrasp" or ctx.nodes["kind"][u] != "grasp" or params.no_regrasp:
        return ok, why, [step], new
    f = ctx.free_of_pose.get(int(ctx.nodes["pose_id"][u]), -1)
    g = int(ctx.nodes["grasp_id"][u])
    fresh = all(np.array_equal(state.q[a], ctx.q_grasp[a][g]) and not state.roll[a].any() for a in state.q)
    if fresh or not (G.has_edge(u, f) and G.has_edge(f, u)):
        return ok, why, [step], new
    walked, s = [], state
    for a, b in ((u, f), (f, u)):
        r_ok, _, r_step, s = _check_step(ctx, params, s, a, b, G.edges[a, b])
        if not r_ok:
            return ok, why, [step], new
        walked.append(r_step)
    ok2, _, step2, new2 = _check_step(ctx, params, s, u, v, data)
    if not ok2:
        return ok, why, [step], new
    walked[1]["retake"] = True
    return True, "ok", [*walked, step2], new2


def _graph_arm_checks(ctx: _Context, G: nx.DiGraph, path: list[int], done: set) -> list[tuple]:
    """The graph stage's arm checks of a pivot edge (``stages.graph.Params.pivot_arms``: IK from its
    grasp's joints and collisions along the edge's own direction, ``eef_normal_angle``), deferred to
    the first path that takes the edge (LazySP) and batched over the path's pivot edges not in
    ``done``: ``(u, v, data, reason)`` of those refused, in path order. The graph would have refused
    them, so their removal is not backtracking; every pivot the walk then meets is checked again from
    the robot's actual joints (:func:`_check_step`)."""
    arcs = [(u, v, G.edges[u, v]) for u, v in zip(path[:-1], path[1:], strict=True)]
    arcs = [a for a in arcs if a[2]["primitive"] == "pivot" and a[2]["edge_id"] not in done]
    if not arcs:
        return []
    e = np.array([a[2]["edge_id"] for a in arcs], dtype=np.int64)
    done.update(e.tolist())
    ga, gb = ctx.nodes["grasp_id"][ctx.edges["node_a"][e]], ctx.nodes["grasp_id"][ctx.edges["node_b"][e]]
    poses_ab = np.stack([ctx.grasps["pose_id"][ga], ctx.grasps["pose_id"][gb]], axis=1)
    p_g, n_g, q_g, pivot_sets = ctx.pivot_checks()
    pc = PivotChecks(ctx.scene, ctx.model, ctx.tables, ctx.robot, ctx.collide, ctx.X_WO, poses_ab,
                     ctx.edges["vertex"][e], np.full((len(e), 2), -1), pivot_sets, p_g, n_g, q_g)
    gp = replace(ctx.gp, pivot_arms=True)
    status = check_pivot_edges(pc, np.stack([ga, gb, np.arange(len(e))], axis=1), gp)
    return [(*a, str(st)) for a, st in zip(arcs, status, strict=True) if st != "ok"]


def _rolled(ctx: _Context, params: Params, state: _State, q: np.ndarray, X: np.ndarray, p_c: np.ndarray,
            n_c: np.ndarray) -> tuple[dict | None, str]:
    """Where both balls have rolled to on the object (``stages.rolling``) after a motion through poses
    ``X (T, 4, 4)`` with joints ``q (T, 2, n)`` on contacts ``p_c, n_c (2, 3)`` (O), summed with what
    they rolled before (``state.roll``): ``(arm -> shift (3,) (m, O), "")``, or ``(None, which ball
    rolls off its surface and how far)``."""
    roll = {}
    for k, arm in enumerate(("left", "right")):
        shift = state.roll[arm] + rolling_shift(ctx.robot, arm, q[:, k], X, n_c[k], ctx.scene.robot.ball_radius)
        off = rolled_off(ctx.tables["mesh"], p_c[k], n_c[k], ctx.scene.robot.ball_radius, shift,
                         params.friction_safety * ctx.scene.object.friction, params.roll)
        if off >= 0:
            return None, f"{arm} ball, {1000 * np.linalg.norm(shift[off]):.0f} mm from its contact"
        roll[arm] = shift[-1]
    return roll, ""


def _check_squeeze_step(ctx: _Context, params: Params, state: _State, data: dict, step: dict, g: int):
    """:func:`_check_step` of a squeeze tumble (``stages.squeeze``): both balls on grasp ``g``'s
    contacts roll the object over the edge. IK from the actual joints and collisions every 0.1 s of
    the motion (as a pivot's, so ``stages.trajectory.plan_squeeze`` ends in the same joints), the
    balls' rolling on the object, and the tumbling MPC with both balls on throughout
    (``stages.squeeze.mpc_params``: less friction than a pivot's), judged as a pivot's
    (``mpc_infeasible``, ``mpc_marginal``)."""
    from stages import trajectory  # it imports this module's neighbours, not this module

    e0, e1 = int(ctx.edges["edge_v0"][data["edge_id"]]), int(ctx.edges["edge_v1"][data["edge_id"]])
    Xa, Xb = ctx.X_WO[step["pose_from"]], ctx.X_WO[step["pose_to"]]
    cl, cr = ctx.contact(g, "left"), ctx.contact(g, "right")
    p_c, n_c = ctx.p_O[[cl, cr]], ctx.n_O[[cl, cr]]
    P = ctx.gp.squeeze
    m = squeeze.squeeze_motion(ctx.model, Xa, (e0, e1), P, params.mpc.dt)
    every = max(1, int(round(0.1 / params.mpc.dt)))
    sub = np.unique(np.r_[np.arange(0, len(m.t), every), len(m.t) - 1])
    q0 = np.stack([state.q["left"], state.q["right"]])[None]
    ok, why, q = check_arm_motion(ctx.robot, ctx.collide, m.X_ref[sub][None], p_c[None], n_c[None], q0,
                                  ctx.scene.robot.ball_radius, ctx.gp, batch=True)
    if not ok[0]:
        return False, str(why[0]), step, state
    roll, detail = _rolled(ctx, params, state, q[:, 0], m.X_ref[sub], p_c, n_c)
    if roll is None:
        return False, "ball_rolls_off", {**step, "detail": detail}, state
    if params.check_mpc:
        out = trajectory.tumble_mpc(ctx.scene.object.mass, np.asarray(ctx.tables["summary"]["inertia"]), ctx.model,
                                    m.roll, m.theta, m.t, m.X_ref, np.ones(len(m.t), bool), p_c, n_c,
                                    squeeze.mpc_params(params.mpc, P, ctx.scene.object.friction,
                                                       ctx.scene.table.friction, ctx.scene.robot.max_eef_force))
        if isinstance(out, str):
            return False, "mpc_infeasible", {**step, "detail": out}, state
        f_peak = float(np.max(np.linalg.norm(out[1], axis=2)))
        if max(out[3], default=0.0) > params.mpc_max_error or \
                f_peak > params.mpc_max_force * ctx.scene.robot.max_eef_force:
            return False, "mpc_marginal", {**step, "detail": f"peak ball force {f_peak:.1f} N"}, state
    new = _State({"left": q[-1, 0, 0], "right": q[-1, 0, 1]},
                 {"left": se3.rotate_vectors(Xb, n_c[0]), "right": se3.rotate_vectors(Xb, n_c[1])}, Xb, roll)
    step.update(mode="squeeze", pusher="both", edge=[e0, e1], grasp=g, contacts={"left": cl, "right": cr},
                squeeze=asdict(P))
    return True, "ok", step, new


def _check_tumble_step(ctx: _Context, params: Params, state: _State, u: int, v: int, data: dict, step: dict):
    """:func:`_check_step` of a tumble: with the graph's pusher (its first that works, the left arm's
    before the right's), then, into SP, with the other arm's first pusher, which swaps the catcher as
    well: where the object lands out of one arm's reach or across its links, the other may catch it.
    The first failure stands when neither works (:func:`_check_tumble_with`)."""
    pusher = str(ctx.edges["arm"][data["edge_id"]])
    first = _check_tumble_with(ctx, params, state, v, data, dict(step), pusher)
    if first[0] or ctx.nodes["kind"][v] == "catch":  # into USP the catch node names the catcher
        return first
    other = "right" if pusher == "left" else "left"
    swapped = _check_tumble_with(ctx, params, state, v, data, dict(step), other)
    return swapped if swapped[0] else first


def _check_tumble_with(ctx: _Context, params: Params, state: _State, v: int, data: dict, step: dict, pusher: str):
    """:func:`_check_tumble_step` with ``pusher``'s arm: its pusher (``stages.graph.pusher_motion``),
    the transits of both arms, and the whole tumble as the motion stage will do it
    (``Params.check_tumble``); into USP the catch's MPC as well."""
    nodes = ctx.nodes
    e0, e1 = int(ctx.edges["edge_v0"][data["edge_id"]]), int(ctx.edges["edge_v1"][data["edge_id"]])
    Xa, Xb = ctx.X_WO[step["pose_from"]], ctx.X_WO[step["pose_to"]]
    found = _push_plan(ctx, Xa, Xb, e0, e1, pusher)
    if found is None:
        return False, "no_pusher_contact", step, state
    c, q_push = found
    new = _State(dict(state.q), dict(state.normal), Xa)
    catcher = "right" if pusher == "left" else "left"
    into_usp = nodes["kind"][v] == "catch"
    if into_usp:
        _, c_catch, q_catch = ctx.catch[v]
    if into_usp and params.check_mpc:  # the catcher's contact must lower the object into USP and hold it
        why = _usp_tumble_mpc(ctx, params, Xa, e0, e1, c, c_catch)
        if why:
            return False, "mpc_infeasible", step, state
    transits = {}
    if not into_usp and _in_the_way(ctx, state, catcher, pusher, q_push[-1], Xa, e0, e1):
        # Into SP the other arm must be away, as the graph's pusher check has it (at rest): where the
        # last grasp left it, the object would fall onto it (then no transit could start there).
        res = _transit(ctx, params, new, catcher, ctx.robot.arm(catcher).q_rest, None)
        if res.status != "ok":
            return False, res.status, {**step, "detail": f"{catcher} arm: {res.reason}"}, state
        new.q[catcher], new.normal[catcher] = res.path[-1], None
        transits[f"{catcher}_before"] = res.path.tolist()
    if into_usp:  # the catcher first goes where the object will land on it (Fig. 18 b, c)
        res = _transit(ctx, params, new, catcher, q_catch, None)
        if res.status != "ok":
            return False, res.status, {**step, "detail": f"{catcher} arm: {res.reason}"}, state
        new.q[catcher], new.normal[catcher] = res.path[-1], None
        transits[f"{catcher}_before"] = res.path.tolist()
    res = _transit(ctx, params, new, pusher, q_push[0], se3.rotate_vectors(Xa, ctx.n_O[c]))
    if res.status != "ok":
        return False, res.status, {**step, "detail": f"{pusher} arm: {res.reason}"}, state
    transits[pusher] = res.path.tolist()
    step.update(edge=[e0, e1], pusher=pusher, pusher_contact=int(c), transit=transits)
    if into_usp:
        step.update(catcher=catcher, catch_contact=c_catch)
    if params.check_tumble:  # the whole tumble as the motion stage will do it: push, catch, MPC, transits
        code, why = ctx.check_tumble(state.q, step, Xa, Xb)
        if code != "ok":
            return False, code, {**step, "detail": why}, state
    new.q[pusher] = q_push[-1]
    new.normal[pusher] = None
    new.X_WO = Xb
    if into_usp:  # the catcher holds the object alone; the next step (a regrasp) hands it over
        new.normal[catcher] = se3.rotate_vectors(Xb, ctx.n_O[c_catch])
    return True, "ok", step, new


def _in_the_way(ctx: _Context, state: _State, idle: str, pusher: str, q_push_end, Xa, e0, e1,
                samples: int = 8) -> bool:
    """Whether the object, rolling over edge (e0, e1) from ``Xa`` past the pusher's release to its
    landing, hits the idle arm where it is (the pusher at the end of its push)."""
    from stages import trajectory  # it imports this module's neighbours, not this module

    roll = trajectory.roll_segments(ctx.model, Xa, e0, e1)
    X = roll.poses(np.linspace(min(ctx.gp.push_angle, roll.total), roll.total, samples))
    q = {idle: state.q[idle], pusher: q_push_end}
    k = ("left", "right").index(idle)
    touching = np.zeros((samples, 2), bool)
    touching[:, 1 - k] = True  # the pusher's ball has just let go
    ok, _, arms = ctx.collide(np.broadcast_to(q["left"], (samples, len(q["left"]))),
                              np.broadcast_to(q["right"], (samples, len(q["right"]))), X, touching, blame=True)
    return bool(np.any(~ok & arms[:, k]))


def _usp_tumble_mpc(ctx: _Context, params: Params, Xa, e0, e1, c_push: int, c_catch: int) -> str:
    """Why the tumbling MPC of ``stages.trajectory`` cannot roll the object from ``Xa`` over edge
    (e0, e1) into USP with these pusher and catcher contacts ("" when it can)."""
    from stages import trajectory  # it imports this module's neighbours, not this module

    tp = trajectory.TumbleParams()
    mp = _mpc_params(ctx, params)
    roll = trajectory.roll_segments(ctx.model, Xa, e0, e1)
    th_r = release_angle(ctx.model, roll, ctx.gp)
    if roll.total < th_r + np.radians(5.0):
        return "the landing comes before the release"
    t, theta, on_p = trajectory.tumble_profile(roll, th_r, roll.total, tp, mp.dt)
    out = trajectory.tumble_mpc(ctx.scene.object.mass, np.asarray(ctx.tables["summary"]["inertia"]), ctx.model,
                                roll, theta, t, roll.poses(theta), on_p, ctx.p_O[[c_push, c_catch]],
                                ctx.n_O[[c_push, c_catch]], mp)
    return out if isinstance(out, str) else ""


def _pivot_motion(ctx: _Context, params: Params, u: int, v: int, edge_id: int):
    """The pivot of arc ``u -> v``: vertex, start and goal poses, table vertex ``p0 (3,)`` (W) and the
    tilt -> rotate -> lower reference ``t (T,)``, ``X_ref (T, 4, 4)`` sampled at the MPC's step."""
    vtx = int(ctx.edges["vertex"][edge_id])
    Xa, Xb = ctx.X_WO[int(ctx.nodes["pose_id"][u])], ctx.X_WO[int(ctx.nodes["pose_id"][v])]
    p0 = se3.transform_points(Xa, ctx.model.vertices[vtx])
    d = poses.tilt_direction(ctx.model, Xa, vtx, ctx.scene.planner.tilt)
    t, Xr, _ = mpc.pivot_reference(Xa, Xb, p0, ctx.scene.planner.tilt, params.mpc.dt, params.pivot_durations,
                                   p_com_O=ctx.model.com, tilt_dir=d)
    return vtx, Xa, Xb, p0, t, Xr


def _pivot_mpc(mass, inertia, p_com_O, p_c, n_in, p0, t, X_ref, mpc_params, max_error, max_force):
    """The MPC of one pivot (``stages.mpc.run_pivot_mpc``) judged as the walk judges it: returns
    ``(reason, largest tracking error (rad), peak ball force (N))``, the reason ``ok``,
    ``mpc_infeasible`` (the last two None) or ``mpc_marginal``."""
    res = mpc.run_pivot_mpc(mass, inertia, p_com_O, p_c, n_in, p0, t, X_ref, mpc_params)
    if res.status != "ok":
        return "mpc_infeasible", None, None
    err = float(np.max(res.tracking_error))
    f_peak = float(np.max(np.linalg.norm(res.f_eef_W, axis=2)))
    if err > max_error or f_peak > max_force:
        return "mpc_marginal", err, f_peak  # feasible only at its limits: physics slips
    return "ok", err, f_peak


def _mpc_helper(conn) -> None:
    """The forked helper of :class:`_MPCChecks`: ``(arc, args)`` in, ``(arc, outcome or None)`` out.

    It leaves with ``os._exit``: no exit handlers, no flushing of stdio buffers that another thread
    of the parent (a progress bar) may have held at the fork.
    """
    try:
        while True:
            job = conn.recv()
            if job is None:
                break
            arc, args = job
            try:
                out = _pivot_mpc(*args)
            except Exception:  # noqa: BLE001 -- the walk runs it again itself and reports the error
                out = None
            conn.send((arc, out))
    except (EOFError, OSError, KeyboardInterrupt):
        pass
    finally:
        os._exit(0)


def _spare_core() -> bool:
    """Whether a core is idle besides the one this process uses: fewer tasks are runnable now than
    there are cores (Linux's /proc/loadavg, this process included), elsewhere a 1-minute load average
    at least a core and a half below the core count. (A helper that shares a busy machine's cores
    with someone else's work only adds its speculative checks to the walk's time.)"""
    cores = os.cpu_count() or 1
    try:
        with open("/proc/loadavg") as f:
            return int(f.read().split()[3].split("/")[0]) < cores
    except (OSError, ValueError, IndexError):
        pass
    try:
        return os.getloadavg()[0] <= cores - 1.5
    except (AttributeError, OSError):
        return False


class _MPCChecks:
    """The MPC outcome of each pivot arc, computed once: it depends on the arc alone (poses, vertex,
    contacts), not on the robot's state, and the state after a pivot does not depend on it.

    Without a helper a pivot's MPC runs as soon as the walk requests it, right after its motion
    check. With ``Params.mpc_helper`` and an idle core a forked process runs the requested ones in
    path order while the walk goes on with the motion checks (which neither need nor change an MPC
    outcome), and stops walking once an outcome fails; the walk then takes the outcomes in path order
    and runs itself those the helper has not started (and, while waiting, later ones), so the two
    leapfrog. Where an outcome is computed changes nothing.
    """

    def __init__(self, ctx: _Context, params: Params):
        self.ctx, self.params = ctx, params
        self.done: dict = {}  # (u, v) -> outcome
        self.queue: list = []  # (u, v, edge_id) requested on the path being walked, in path order
        self.busy = None  # the arc the helper runs
        self.conn = self.proc = None
        if params.check_mpc and params.mpc_helper and _spare_core() and \
                "fork" in multiprocessing.get_all_start_methods():
            mp = multiprocessing.get_context("fork")
            self.conn, child = mp.Pipe()
            self.proc = mp.Process(target=_mpc_helper, args=(child,), daemon=True)
            self.proc.start()
            child.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        if self.proc is None:
            return
        if self.busy is None:
            try:
                self.conn.send(None)
            except OSError:
                pass
        else:  # it runs a speculative check nobody waits for any more
            self.proc.kill()
        self.proc.join(timeout=5.0)
        if self.proc.is_alive():
            self.proc.kill()
            self.proc.join()
        self.conn.close()

    def walk(self) -> None:
        """A new path is walked: what the last one requested is no longer wanted."""
        self.queue = []

    def request(self, u: int, v: int, edge_id: int) -> None:
        """The walk reached pivot arc ``u -> v`` (its motion check passed)."""
        self.queue.append((u, v, edge_id))
        if self.conn is None and (u, v) not in self.done:
            self.done[u, v] = _pivot_mpc(*self._args(u, v, edge_id))
        self.feed()

    def known_failure(self) -> bool:
        """Whether a pivot requested on this path already has a failing outcome (the rest is moot)."""
        return any(self.done.get(a[:2], ("ok",))[0] != "ok" for a in self.queue)

    def outcome(self, u: int, v: int, edge_id: int):
        """``(reason, max tracking error, peak force)`` of arc ``u -> v`` (see :func:`_pivot_mpc`)."""
        arc = (u, v)
        while arc not in self.done:
            if self.busy != arc:  # the helper has not started it: run it here
                self.feed(mine=arc)
                self.done[arc] = _pivot_mpc(*self._args(u, v, edge_id))
                continue
            # The helper runs it: run a later requested one meanwhile, or wait.
            later = [a for a in self.queue if a[:2] not in self.done and a[:2] != arc]
            if later:
                self.done[later[0][:2]] = _pivot_mpc(*self._args(*later[0]))
            self._collect(block=not later)
        self.feed()
        return self.done[arc]

    def feed(self, mine=None) -> None:
        """Hand the idle helper the first requested arc without an outcome (not ``mine``, which the
        walk is about to run)."""
        if self.conn is None:
            return
        self._collect(block=False)
        if self.busy is not None:
            return
        for u, v, edge_id in self.queue:
            if (u, v) not in self.done and (u, v) != mine:
                try:
                    self.conn.send(((u, v), self._args(u, v, edge_id)))
                    self.busy = (u, v)
                except OSError:
                    self.conn = None
                return

    def _args(self, u: int, v: int, edge_id: int) -> tuple:
        ctx, params = self.ctx, self.params
        _, _, _, p0, t, Xr = _pivot_motion(ctx, params, u, v, edge_id)
        gu = int(ctx.nodes["grasp_id"][u])
        c = [ctx.contact(gu, "left"), ctx.contact(gu, "right")]
        return (ctx.scene.object.mass, np.asarray(ctx.tables["summary"]["inertia"]), ctx.model.com, ctx.p_O[c],
                -ctx.n_O[c], p0, t, Xr, _mpc_params(ctx, params), params.mpc_max_error,
                params.mpc_max_force * ctx.scene.robot.max_eef_force)

    def _collect(self, block: bool) -> None:
        """Take the helper's outcome if it is there (or wait for it)."""
        if self.busy is None or not (block or self.conn.poll()):
            return
        try:
            arc, out = self.conn.recv()
        except (EOFError, OSError):  # the helper is gone: the walk runs everything itself
            self.conn = None
        else:
            if out is not None:
                self.done[arc] = out
        self.busy = None


def _push_plan(ctx: _Context, Xa, Xb, e0, e1, arm):
    """The pusher's contact and joint path for a tumble (``stages.graph.pusher_motion``), or None."""
    gp = ctx.gp
    found, c, q = pusher_motion(ctx.robot, ctx.collide, ctx.model, Xa, Xb, e0, e1, ctx.p_O, ctx.n_O,
                                ctx.scene.robot.ball_radius, gp, push_limits(ctx.scene, gp), arms=(arm,))
    return None if found is None else (c, q)


def _mpc_params(ctx: _Context, params: Params) -> mpc.Params:
    return replace(params.mpc, mu_eef=params.friction_safety * ctx.scene.object.friction,
                   mu_table=params.friction_safety * ctx.scene.table.friction,
                   f_max=ctx.scene.robot.max_eef_force)


def _yaw_between(Xa, Xb) -> float:
    return float(se3.yaw_of(Xb[:3, :3] @ Xa[:3, :3].T))


def search(ctx: _Context, params: Params) -> dict:
    """Search, check lazily, backtrack; returns the plan dict (status, steps, log, counts, cost)."""
    with _MPCChecks(ctx, params) as mpc_checks:
        return _search(ctx, params, mpc_checks)


def _search(ctx: _Context, params: Params, mpc_checks: _MPCChecks) -> dict:
    G, start, goal = build_search_graph(ctx, params)
    log: list[dict] = []
    partial = None
    target = goal
    if start < 0 or goal < 0 or not nx.has_path(G, start, goal):
        if not params.no_regrasp or start < 0 or goal < 0:
            return _infeasible(ctx, params, G, start, goal, log, "no path in the graph")
        target, partial = _nearest_reachable(ctx, G, start)
    home = np.zeros(ctx.robot.arm("left").dof)
    removals = 0
    checked: dict = {}  # (u, v, state) -> the check's outcome: a new path re-walks its prefix for free
    armed: set = set()  # pivot edges through the graph's deferred arm checks
    while True:
        try:
            path = nx.shortest_path(G, start, target, weight="weight")
        except nx.NetworkXNoPath:
            if params.no_regrasp and target != start:  # backtracking cut the way: the nearest reachable again
                target, partial = _nearest_reachable(ctx, G, start)
                continue
            return _infeasible(ctx, params, G, start, goal, log, "no path left after backtracking")
        if refused := _graph_arm_checks(ctx, G, path, armed):
            for u, v, data, why in refused:
                _remove(ctx, G, log, u, v, data, why, None, graph_check=True)
            continue
        state = _State({"left": home.copy(), "right": home.copy()}, {"left": None, "right": None},
                       ctx.X_WO[int(ctx.nodes["pose_id"][start])])
        steps = []
        failed = None
        pivots = []  # (index in steps, u, v, data) of the pivots walked, whose MPC outcome is asked for
        mpc_checks.walk()
        for u, v in zip(path[:-1], path[1:], strict=True):  # the path's few dozen edges
            data = G.edges[u, v]
            key = (u, v, state.key())
            if key not in checked:
                mpc_checks.feed()
                checked[key] = _check_or_retake(ctx, params, G, state, u, v, data)
            ok, why, walked, state = checked[key]
            if not ok:
                failed = (u, v, data, why, walked[-1].get("detail"))
                break
            if data["primitive"] == "pivot" and params.check_mpc:
                pivots.append((len(steps) + len(walked) - 1, u, v, data))
                mpc_checks.request(u, v, data["edge_id"])
            steps.extend(walked)
            if mpc_checks.known_failure():
                break
        # The pivots' MPC checks, in path order: a failing one comes before any later failure.
        for i, u, v, data in pivots:
            why, err, f_peak = mpc_checks.outcome(u, v, data["edge_id"])
            if why != "ok":
                failed, steps = (u, v, data, why, None), steps[:i]
                break
            steps[i].update(mpc_max_error=err, mpc_peak_force=f_peak)
        if failed is None:
            cost = float(sum(ctx.edges["weight"][s["edge_id"]] for s in steps))
            counts = {p: sum(s["primitive"] == p for s in steps) for p in ("pivot", "tumble")}
            # A regrasp changes a grasp: the first grasp out of the start's free node is not one, nor
            # is a retake of the same grasp (counted apart).
            counts["regrasp"] = sum(1 for s in steps if s["primitive"] == "regrasp" and s.get("arms")
                                    and s["node_from"] != start and not s.get("retake"))
            counts["retake"] = sum(1 for s in steps if s.get("retake"))
            # Regrasps while one ball holds the object in USP (after a catch too: the hand-over).
            counts["usp_regrasp"] = sum(1 for s in steps if s["support"] == "USP" and s["primitive"] == "regrasp"
                                        and s.get("arms"))
            out = {"status": "partial" if partial else "ok", "steps": steps, "log": log, "cost": cost,
                   "counts": counts, "nodes": [int(n) for n in path]}
            if partial:
                out["remaining_error"] = partial
            return out
        _remove(ctx, G, log, *failed)
        removals += 1
        if removals >= params.max_removals:
            return {"status": "infeasible", "reason": f"gave up after {removals} removed edges", "steps": [],
                    "log": log}


def _remove(ctx: _Context, G: nx.DiGraph, log: list[dict], u: int, v: int, data: dict, why: str, detail,
            graph_check: bool = False) -> None:
    """Remove the failed arc ``u -> v`` (both ways when undirected) and log it; ``graph_check``: it
    failed the graph stage's deferred checks (:func:`_graph_arm_checks`), not a backtrack."""
    log.append({"edge_id": data["edge_id"], "primitive": data["primitive"], "node_a": int(u), "node_b": int(v),
                "reason": why, **({"detail": detail} if detail else {}),
                **({"graph_check": True} if graph_check else {})})
    G.remove_edge(u, v)
    if not ctx.edges["directed"][data["edge_id"]] and G.has_edge(v, u):
        G.remove_edge(v, u)


def _infeasible(ctx: _Context, params: Params, G: nx.DiGraph, start: int, goal: int, log: list[dict],
                prefix: str) -> dict:
    """The infeasible plan: ``reason`` is ``prefix`` and the diagnosed cause's fixed phrase (a stable
    reason code), ``diagnosis`` the cause with its counts (``stages.diagnosis``)."""
    t = diagnosis.Tables(ctx.nodes, ctx.edges, ctx.poses, ctx.links, ctx.rejects, int(ctx.sample["goal"]["pose_id"]),
                         ctx.sample["face_route"])
    removed = {int(r["edge_id"]): str(r["reason"]) for r in log}
    d = diagnosis.diagnose(t, G, start, goal, ablated_edges(ctx.nodes, ctx.edges, params, start, goal), removed,
                           no_tumble=params.no_tumble, no_usp=params.no_usp)
    return {"status": "infeasible", "reason": f"{prefix}: {diagnosis.REASONS[d['cause']]}", "diagnosis": d,
            "steps": [], "log": log}


def _nearest_reachable(ctx: _Context, G: nx.DiGraph, start: int) -> tuple[int, dict]:
    """The reachable node whose object pose is nearest the goal, and the remaining error to it.

    Nearest by ``|Δxy| + r |Δyaw|`` of the CoM (``r`` the object's bounding radius turns the yaw
    into an arc length) among poses on the goal's placement; other faces only when none is reached.
    Only SP poses count: the plan ends there holding the object, and a USP pose (over the table's
    edge) is not one it can be left in, so its distance to the goal would mean nothing.
    """
    reach = nx.single_source_dijkstra_path_length(G, start, weight="weight")
    goal_X = _goal_pose(ctx)
    com_goal = se3.transform_points(goal_X, ctx.model.com)
    r = float(np.linalg.norm(ctx.tables["summary"]["extents"]) / 2)
    goal_face = int(np.argmax(ctx.model.normals @ (goal_X[:3, :3].T @ np.array([0.0, 0.0, -1.0]))))
    best, best_d = start, np.inf
    for n in sorted(reach):  # every reachable node once
        if ctx.nodes["support"][n] != "SP":
            continue
        pose = int(ctx.nodes["pose_id"][n])
        X = ctx.X_WO[pose]
        d = float(np.linalg.norm(se3.transform_points(X, ctx.model.com)[:2] - com_goal[:2]))
        d += r * abs(_yaw_between(goal_X, X)) + (0.0 if int(ctx.poses["placement_id"][pose]) == goal_face else 1e3)
        if d < best_d - 1e-12:
            best, best_d = n, d
    X = ctx.X_WO[int(ctx.nodes["pose_id"][best])]
    err = se3.transform_points(X, ctx.model.com) - com_goal
    return best, {"x": float(err[0]), "y": float(err[1]), "distance": float(np.linalg.norm(err[:2])),
                  "yaw": float(_yaw_between(goal_X, X))}


def _goal_pose(ctx: _Context) -> np.ndarray:
    X, _ = placement_pose(ctx.scene.goal, ctx.model, "goal")
    return X


def run(scene_path, analysis_dir, sample_dir, graph_dir, out_path, params: Params, producer: str = "plan") -> dict:
    """Plan and write ``plan.json`` (status ok, partial or infeasible); returns the plan dict."""
    t0 = time.perf_counter()
    scene = load_scene(scene_path)
    provenance.check_graph(graph_dir, scene, analysis_dir, sample_dir)
    ctx = _Context(scene, analysis_dir, sample_dir, graph_dir)
    plan = search(ctx, params)
    elapsed = time.perf_counter() - t0
    meta_params = {**{k: v for k, v in asdict(params).items() if k != "mpc_helper"},
                   "weights": asdict(scene.planner.weights), "arm_clearance": ctx.collide.link_clearance,
                   "stick_clearance": ctx.collide.tool_clearance, "graph": ctx.graph_params}
    meta = artifacts.make_meta("plan", meta_params, ctx.inputs, producer)
    for s in plan["steps"]:
        for key in ("pose_from", "pose_to"):
            s[key.replace("pose", "X_WO")] = se3.columns_from_matrix(ctx.X_WO[s[key]])
    artifacts.write_json(out_path, plan, meta)
    artifacts.write_timings(out_path, {"plan": elapsed})
    stagelog.log_plan(plan)
    plan["time"] = elapsed
    return plan
