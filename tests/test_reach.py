"""Grasp-aware reach (``stages.sample``): which poses the start reaches by links a grasp can make, and
LazySP over them with the graph stage's pivot checks."""

import numpy as np

from stages import poses, sample


def _poses(links, primitive, vertex) -> poses.PoseSet:
    n = 1 + int(np.max(links))
    return poses.PoseSet(
        X_WO=np.tile(np.eye(4), (n, 1, 1)), placement=np.zeros(n, np.int64), support=np.full(n, "SP"),
        status=np.full(n, "ok"), parent=-np.ones(n, np.int64), primitive=np.full(n, "pivot"),
        vertex=-np.ones(n, np.int64), edge=-np.ones((n, 2), np.int64), angle=np.zeros(n), margin=np.zeros(n),
        links=np.array(links, np.int64), link_primitive=np.array(primitive), link_vertex=np.array(vertex, np.int64),
        link_edge=-np.ones((len(links), 2), np.int64), link_angle=np.zeros(len(links)))


def _grasps(rows):  # (pose, left contact, right contact, pivot vertices)
    return {"pose_id": np.array([r[0] for r in rows], np.int64),
            "contact_left": np.array([r[1] for r in rows], np.int64),
            "contact_right": np.array([r[2] for r in rows], np.int64),
            "pivot_vertices": [np.array(r[3], np.int64) for r in rows]}


def test_a_pivot_link_needs_one_grasp_holding_its_vertex_at_both_ends():
    ps = _poses([(0, 1), (1, 2), (2, 3)], ["pivot"] * 3, [5, 6, 7])
    g = _grasps([(0, 1, 2, [5]), (1, 1, 2, [5, 6]), (2, 3, 4, [6, 7]),  # 1-2: vertex 6 by other contacts
                 (3, 3, 4, [])])                                         # 2-3: 7 listed at 2 only
    cands = sample.link_candidates(ps, g, tumbles=True)
    assert cands == {0: [(0, 1)]}
    G = sample.reach_graph(ps, cands)
    assert G.has_edge(0, 1) and not G.has_edge(1, 2) and not G.has_edge(2, 3)
    assert sample.held_corners(g)[1].tolist() == [5, 6] and sample.held_corners(g)[3].tolist() == []


def test_a_tumble_link_counts_out_of_sp_with_a_grasp_to_push_and_only_when_asked():
    ps = _poses([(0, 1), (2, 3), (4, 5)], ["tumble"] * 3, [-1] * 3)
    ps = poses.PoseSet(**{**ps.__dict__, "support": np.array(["SP", "SP", "SP", "SP", "USP", "SP"])})
    g = _grasps([(0, 1, 2, []), (3, 1, 2, []), (4, 1, 2, [])])
    assert sample.link_candidates(ps, g, tumbles=True) == {0: [(-1, -1)]}  # 2 has nothing to push with, 4 is USP
    assert sample.link_candidates(ps, g, tumbles=False) == {}


def test_lazy_reach_checks_the_shortest_path_first_and_goes_around_a_failed_pivot():
    """0-1-2 is short, 0-3-4-2 long; the pivot 1-2 fails its check: the goal is reached the long way,
    with only the checked candidates asked for, each once."""
    ps = _poses([(0, 1), (1, 2), (0, 3), (3, 4), (4, 2)], ["pivot"] * 5, [0] * 5)
    cands = {li: [(10 * li, 10 * li + 1)] for li in range(5)}
    asked = []

    def check(c):
        asked.extend(map(tuple, c.tolist()))
        return np.array(["env_collision" if li == 1 else "ok" for _, _, li in c.tolist()], dtype=object)

    G = sample.reach_graph(ps, cands)
    verified: dict = {}
    assert sample.lazy_reach(G, 2, cands, check, verified, walks=5)
    assert sorted(li for _, _, li in asked) == [0, 1, 2, 3, 4] and len(asked) == len(set(asked))
    assert not G.has_edge(1, 2)
    assert not sample.lazy_reach(G, 2, cands, lambda c: np.full(len(c), "unstable", dtype=object), {}, walks=5)


def test_lazy_reach_gives_up_undecided_after_its_walks():
    ps = _poses([(0, 1), (1, 2), (0, 3), (3, 2)], ["pivot"] * 4, [0] * 4)
    cands = {li: [(li, li)] for li in range(4)}
    G = sample.reach_graph(ps, cands)
    fail_all = lambda c: np.full(len(c), "env_collision", dtype=object)  # noqa: E731
    assert not sample.lazy_reach(G, 2, cands, fail_all, {}, walks=1)
    assert G.number_of_edges() >= 2  # the second path was never walked


def test_a_tumble_is_walked_only_the_way_its_pusher_rolls_the_object():
    """Pose 1 tumbles onto pose 0: 0 does not reach 1 through that link (rolling back over the edge is
    another link), while a pivot is walked both ways, and the sides follow the arcs."""
    ps = _poses([(1, 0), (1, 2)], ["tumble", "pivot"], [-1, 3])
    g = _grasps([(1, 1, 2, [3]), (2, 1, 2, [3])])
    cands = sample.link_candidates(ps, g, tumbles=True)
    assert cands == {0: [(-1, -1)], 1: [(0, 1)]}
    G = sample.reach_graph(ps, cands)
    assert G.has_edge(1, 0) and not G.has_edge(0, 1) and G.has_edge(1, 2) and G.has_edge(2, 1)
    ok = lambda c: np.full(len(c), "ok", dtype=object)  # noqa: E731
    assert not sample.lazy_reach(G, 2, cands, ok, {}, walks=5)
    assert sample._sides(G, 2) == ([0], [2, 1])
