"""sample → graph → plan → mpc on a small scene: every kept grasp, edge and step satisfies what it claims."""

import numpy as np
import pytest

from stages import artifacts, graph, poses, sample, se3, stability
from stages.objectmodel import load_object_model
from stages.robot import load_robot
from stages.sample import make_scene_collision_fn, placement_pose
from stages.scene import load_scene


@pytest.fixture(scope="module")
def ctx(small_build):
    scene_path, b = small_build
    scene = load_scene(scene_path)
    model, tables = load_object_model(b / "analysis")
    robot = load_robot(scene.robot.urdf_path, scene.base_transform(), tuple(scene.robot.eef_links))
    return scene, b, model, tables, robot


def test_grasps_are_reached_collision_free_and_stable(ctx):
    scene, b, model, tables, robot = ctx
    ps = artifacts.read_table(b / "sample" / "poses.parquet", "poses")
    gr = artifacts.read_table(b / "sample" / "grasps.parquet", "grasps")
    assert len(gr) > 50
    X = se3.matrix_from_columns(ps.columns)[gr["pose_id"]]
    con = tables["contacts"]
    p = np.stack([con["px"], con["py"], con["pz"]], 1)
    n = np.stack([con["nx"], con["ny"], con["nz"]], 1)
    r = scene.robot.ball_radius
    ql, qr = np.stack(list(gr["q_left"])), np.stack(list(gr["q_right"]))
    for arm, q, c in (("left", ql, gr["contact_left"]), ("right", qr, gr["contact_right"])):
        target = se3.transform_points(X, p[c] + r * n[c])
        # IK tolerance 1 mm (sample.Params.ik_tol).
        assert np.linalg.norm(robot.eef_position(arm, q) - target, axis=1).max() <= 1e-3 + 1e-9
        a = robot.arm(arm)
        assert ((q >= a.lower - 1e-9) & (q <= a.upper + 1e-9)).all()
    ok, why = make_scene_collision_fn(scene, robot, tables["mesh"])(ql, qr, X, np.ones((len(gr), 2), bool))
    assert ok.all(), why[~ok][:3]
    # The left ball takes the contact with the larger world y.
    yl = se3.transform_points(X, p[gr["contact_left"]])[:, 1]
    yr = se3.transform_points(X, p[gr["contact_right"]])[:, 1]
    assert (yl >= yr - 1e-12).all()
    # SP grasps' pivot vertices are those of their pose's support corners on which the LP holds the
    # object with the graph's friction and force safety both at the start of the tilt (on the corner
    # alone, untilted) and tilted by the planner's tilt (mpc.pivot_reference's axis): recorded ones
    # hold, the other corners do not.
    sp = np.flatnonzero(ps["support"][gr["pose_id"]] == "SP")[:40]
    corners = poses.pivot_corners(model, sample.Params().corner_cluster)
    rows = [(i, v, v in set(gr["pivot_vertices"][i].tolist())) for i in sp
            for v in corners[ps["placement_id"][gr["pose_id"][i]]]]
    i, v, recorded = (np.array(x) for x in zip(*rows, strict=True))
    assert recorded.any() and not recorded.all()
    Xi = X[i]
    p0 = se3.transform_points(Xi, model.vertices[v])
    d = se3.transform_points(Xi, model.com) - p0
    d[:, 2] = 0.0
    T = se3.transform_about_line(p0, np.cross(d / np.linalg.norm(d, axis=1, keepdims=True), [0, 0, 1.0]),
                                 np.full(len(i), scene.planner.tilt))
    cl, cr = gr["contact_left"][i], gr["contact_right"][i]
    gp = graph.Params()
    # Each ball's whole force (normal and friction) within the force the plan's MPC check allows.
    mu = gp.friction_safety * scene.object.friction
    f_max = gp.force_safety * scene.robot.max_eef_force / np.sqrt(1.0 + mu**2)
    holds = np.ones(len(i), bool)
    for Xt in (Xi, T @ Xi):  # the start of the tilt, the full tilt
        pts = np.stack([se3.transform_points(Xt, p[cl]), se3.transform_points(Xt, p[cr])], 1)
        nrm = -np.stack([se3.rotate_vectors(Xt, n[cl]), se3.rotate_vectors(Xt, n[cr])], 1)
        res = stability.evaluate(scene.object.mass, se3.transform_points(Xt, model.com), p0[:, None], None, pts,
                                 nrm, None, float(np.linalg.norm(tables["summary"]["extents"]) / 2),
                                 stability.Params(mu_eef=mu, mu_table=gp.friction_safety * scene.table.friction,
                                                  f_max=f_max),
                                 compute_margin=False)
        holds &= res.stable
    on = np.all(np.abs(p0[:, :2]) <= np.asarray(scene.table.size) / 2, axis=1)
    np.testing.assert_array_equal(recorded, holds & on)


def test_sample_predicts_the_graphs_pivot_test_with_the_same_safety_factors():
    s, g = sample.Params(), graph.Params()
    assert (s.pivot_friction_safety, s.pivot_force_safety) == (g.friction_safety, g.force_safety)


def test_rejects_carry_known_reason_codes(ctx):
    _, b, *_ = ctx
    rej = artifacts.read_table(b / "sample" / "grasp_rejects.parquet", "grasp_rejects")
    known = ("eef_under_object", "normal_away", "ik_unreachable", "joint_limit", "env_collision:", "self_collision:",
             "object_clearance:", "unstable")
    assert len(rej) > 0
    assert all(str(r).startswith(known) for r in rej["reason"])


def test_graph_edges_are_consistent_with_their_nodes(ctx):
    _, b, *_ = ctx
    nodes = artifacts.read_table(b / "graph" / "nodes.parquet", "nodes")
    edges = artifacts.read_table(b / "graph" / "edges.parquet", "edges")
    gr = artifacts.read_table(b / "sample" / "grasps.parquet", "grasps")
    ok = edges["status"] == "ok"
    piv = ok & (edges["primitive"] == "pivot")
    assert piv.sum() > 10
    a, c = edges["node_a"][piv], edges["node_b"][piv]
    # A pivot keeps the grasp: same contacts at both ends, different poses.
    assert (gr["contact_left"][a] == gr["contact_left"][c]).all()
    assert (gr["contact_right"][a] == gr["contact_right"][c]).all()
    assert (nodes["pose_id"][a] != nodes["pose_id"][c]).all()
    reg = ok & (edges["primitive"] == "regrasp")
    # A regrasp keeps the pose.
    assert (nodes["pose_id"][edges["node_a"][reg]] == nodes["pose_id"][edges["node_b"][reg]]).all()
    w = {"pivot": 0.1, "regrasp": 0.5, "tumble": 1.0}
    for prim, weight in w.items():
        sel = edges["primitive"] == prim
        expect = weight / 2 if prim == "regrasp" else weight
        kinds = nodes["kind"][edges["node_b"][sel]]
        if prim == "regrasp":  # grasp <-> free edges carry half the regrasp weight
            half = kinds == "free"
            assert np.allclose(edges["weight"][sel][half], expect)
        else:
            assert np.allclose(edges["weight"][sel], expect)


def test_plan_reaches_the_goal_with_exact_pivots(ctx):
    scene, b, model, tables, robot = ctx
    plan = artifacts.read_json(b / "plan.json", "plan")
    assert plan["status"] == "ok"
    steps = plan["steps"]
    assert steps[0]["primitive"] == "regrasp"  # the first grasp
    X_goal, _ = placement_pose(scene.goal, model, "goal")
    last = se3.matrix_from_columns({k: np.atleast_1d(v) for k, v in steps[-1]["X_WO_to"].items()})[0]
    np.testing.assert_allclose(last, X_goal, atol=1e-6)  # the goal is reached exactly, not approximately
    for s in steps:
        if s["primitive"] != "pivot":
            continue
        Xa = se3.matrix_from_columns({k: np.atleast_1d(v) for k, v in s["X_WO_from"].items()})[0]
        Xb = se3.matrix_from_columns({k: np.atleast_1d(v) for k, v in s["X_WO_to"].items()})[0]
        v = model.vertices[s["vertex"]]
        np.testing.assert_allclose(se3.transform_points(Xa, v), se3.transform_points(Xb, v), atol=1e-9)
    assert plan["counts"]["pivot"] == sum(s["primitive"] == "pivot" for s in steps)


@pytest.mark.slow
def test_plan_runs_in_physics_end_to_end(ctx):
    """mpc + execute on the small scene's plan: the object reaches the goal through its contacts."""
    from stages import execute, trajectory

    scene, b, *_ = ctx
    stats = trajectory.run(scene.path, b / "analysis", b / "plan.json", b / "trajectories.parquet",
                           trajectory.Params())
    assert stats["status"] == "ok"
    tr = artifacts.read_table(b / "trajectories.parquet", "trajectories")
    # Every pivot row keeps each ball force within its bound (MPC constraint) and the table pushing up.
    piv = tr["kind"] == "pivot"
    for side in ("l", "r"):
        f = np.stack([tr[f"f{side}x"], tr[f"f{side}y"], tr[f"f{side}z"]], 1)[piv]
        bound = scene.robot.max_eef_force * np.sqrt(1 + scene.object.friction**2)  # normal <= f_max, in the cone
        assert np.linalg.norm(f, axis=1).max() <= bound + 1e-6
    assert (tr["f0z"][piv] > 0).all()
    ex = execute.run(scene.path, b / "analysis", b / "trajectories.parquet", b / "exec", execute.Params())
    m = ex.metrics
    assert m["success"], {k: m[k] for k in ("failures", "final_position_error", "final_yaw_error_deg")}
    assert m["final_position_error"] <= 0.01 and m["final_yaw_error_deg"] <= 2.0
    assert not m["fell"] and not m["collision"]


def test_mpc_stage_is_continuous_within_limits_and_deterministic(ctx, tmp_path):
    from stages import trajectory

    scene, b, model, tables, robot = ctx
    out1, out2 = tmp_path / "t1.parquet", tmp_path / "t2.parquet"
    for out in (out1, out2):
        assert trajectory.run(scene.path, b / "analysis", b / "plan.json", out, trajectory.Params())["status"] == "ok"
    assert out1.read_bytes() == out2.read_bytes()  # same plan and parameters: byte-identical
    tr = artifacts.read_table(out1, "trajectories")
    dt = float(np.median(np.diff(tr["t"])))
    for arm in ("left", "right"):
        q = np.stack(list(tr[f"q_{arm}"]))
        a = robot.arm(arm)
        assert ((q >= a.lower - 1e-9) & (q <= a.upper + 1e-9)).all()
        # No branch flips: joint speeds stay within the arm's velocity limits (plus 10 % for the
        # finite difference of the sampled IK path).
        assert (np.abs(np.diff(q, axis=0)) / dt <= 1.1 * a.velocity).all()
    # The balls follow the object: in contact rows the planned ball centre sits one radius off the surface
    # at the grasp's contact, i.e. FK of the joints matches the ball column within the IK tolerance.
    rows = np.flatnonzero(tr["left_contact"])
    p_fk = robot.eef_position("left", np.stack(list(tr["q_left"]))[rows])
    p_col = np.stack([tr["lx"], tr["ly"], tr["lz"]], 1)[rows]
    assert np.linalg.norm(p_fk - p_col, axis=1).max() <= 2e-3



def test_plan_and_mpc_check_with_the_parameters_the_graph_recorded(small_build, tmp_path):
    """A graph built with other parameters than the defaults (a smaller largest joint step, a finer push
    step, less squeeze friction) records them in its artifacts; ``pivot plan`` checks its walk with
    those (its context reads them from ``edges.parquet``) and passes them on in ``plan.json``, from
    which ``pivot mpc`` builds its tumbles' environment: neither falls back to ``graph.Params()``'s
    defaults, which would silently check other motions than the graph did."""
    from dataclasses import replace

    from stages import plan, squeeze, trajectory

    scene_path, b = small_build
    gp = replace(graph.Params(), max_joint_step=0.3, push_step=np.radians(6.0),
                 squeeze=replace(squeeze.SqueezeParams(), friction=0.5))
    graph.run(scene_path, b / "analysis", b / "sample", tmp_path / "graph", gp)
    ctx = plan._Context(load_scene(scene_path), b / "analysis", b / "sample", tmp_path / "graph")
    assert ctx.gp == gp and ctx.gp != graph.Params()
    assert ctx.gp.squeeze.friction == 0.5
    plan.run(scene_path, b / "analysis", b / "sample", tmp_path / "graph", tmp_path / "plan.json", plan.Params())
    recorded = artifacts.read_json(tmp_path / "plan.json", "plan")["meta"]["params"]["graph"]
    assert graph.recorded_params(recorded) == gp
    model, tables = load_object_model(b / "analysis")
    scene = load_scene(scene_path)
    robot = load_robot(scene.robot.urdf_path, scene.base_transform(), tuple(scene.robot.eef_links))
    env = trajectory.make_env(scene, model, tables, robot, trajectory.Params(),
                              graph=graph.recorded_params(recorded))
    assert env.graph.max_joint_step == 0.3 and env.graph.push_step == np.radians(6.0)
