"""Scene files: the default scene and its piano mesh, validation messages for bad input, round trips,
helpers."""

import copy
import json
import math
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import trimesh
from scipy.spatial import ConvexHull

from stages import se3
from stages.errors import InputError
from stages.scene import Scene, load_scene, scene_from_dict

REPO = Path(__file__).resolve().parents[1]
DEFAULT = REPO / "data" / "scenes" / "default.json"
URDF = REPO / "data" / "robots" / "sda5f.urdf"
PIANO = REPO / "data" / "objects" / "toy_piano.obj"


@pytest.fixture
def scene_dir(tmp_path) -> Path:
    """A folder with ``scenes/``, a box mesh and a placeholder URDF (the scene only checks it exists)."""
    (tmp_path / "scenes").mkdir()
    (tmp_path / "objects").mkdir()
    (tmp_path / "robots").mkdir()
    trimesh.creation.box((0.3, 0.2, 0.4)).export(tmp_path / "objects" / "box.stl")
    (tmp_path / "robots" / "r.urdf").write_text('<robot name="r"/>\n')
    return tmp_path


def minimal() -> dict:
    """Only the required keys."""
    return {
        "object": {"mesh": "../objects/box.stl", "mass": 2.0},
        "table": {"size": [0.9, 0.6], "height": 0.75},
        "robot": {"urdf": "../robots/r.urdf", "base_xyz": [-0.7, 0.0, -0.75]},
        "start": {"down": [0, 0, -1], "xy": [-0.2, 0.0]},
        "goal": {"placement": 3, "xy": [0.2, 0.1], "yaw_deg": 30},
    }


def rich() -> dict:
    """Every key, obstacles of every type."""
    d = minimal()
    d["name"] = "rich"
    d["object"].update(friction=0.4, scale=0.5)
    d["table"]["friction"] = 0.7
    d["robot"].update(base_yaw_deg=5, eef_links=["a", "b"], ball_radius=0.03, max_eef_force=40)
    d["obstacles"] = [
        {"type": "box", "size": [0.1, 0.2, 0.3], "xyz": [0.3, -0.2, 0.15], "yaw_deg": 10},
        {"type": "cylinder", "radius": 0.05, "height": 0.2, "xyz": [0.0, 0.25, 0.1]},
        {"type": "mesh", "mesh": "../objects/box.stl", "scale": 0.5, "xyz": [0.35, 0.25, 0.1], "yaw_deg": 0},
    ]
    d["planner"] = {"theta_t_deg": 10, "tilt_deg": 5, "usp": False,
                    "weights": {"pivot": 0.2, "regrasp": 1, "tumble": 2}, "seed": 7, "max_poses": 50,
                    "goal_reach": 0.5}
    return d


def write(scene_dir: Path, data: dict, name: str = "s.json") -> Path:
    p = scene_dir / "scenes" / name
    p.write_text(json.dumps(data, indent=1))
    return p


# ---- the reference scene ------------------------------------------------------------------------------

@pytest.mark.skipif(not URDF.exists(), reason="data/robots/sda5f.urdf not written yet")
def test_default_scene_loads_and_puts_the_piano_on_the_table_in_front_of_the_robot():
    s = load_scene(DEFAULT)
    assert s.name == "default"
    assert s.object.mass == 3.1 and s.table.size == (0.9, 0.6)
    X_WB = s.base_transform()
    # The base stands on the floor behind the near table edge.
    assert X_WB[2, 3] == pytest.approx(-s.table.height)
    assert X_WB[0, 3] < -s.table.size[0] / 2
    # The end-effector links named by the scene exist in the URDF.
    links = set(re.findall(r'<link\s+name="([^"]+)"', URDF.read_text()))
    assert set(s.robot.eef_links) <= links
    # Upright, keyboard (O -y) toward the robot (W -x), goal further away from the robot.
    for pl in (s.start, s.goal):
        assert pl.down == (0.0, 0.0, -1.0)
        R = se3.rot_z(pl.yaw)
        np.testing.assert_allclose(R @ [0.0, -1.0, 0.0], [-1.0, 0.0, 0.0], atol=1e-12)
    assert 0.15 <= s.goal.xy[0] - s.start.xy[0] <= 0.2
    # The whole piano footprint (not just its CoM) is on the table at start and goal.
    mesh = trimesh.load(s.object.mesh_path)
    for pl in (s.start, s.goal):
        R = se3.rot_z(pl.yaw)
        p_W = (mesh.vertices - [*mesh.center_mass[:2], 0.0]) @ R.T + [*pl.xy, 0.0]
        assert s.on_table(p_W).all()


@pytest.mark.skipif(not URDF.exists(), reason="data/robots/sda5f.urdf not written yet")
def test_default_scene_round_trips_through_json():
    s = load_scene(DEFAULT)
    again = scene_from_dict(json.loads(json.dumps(s.to_dict())), DEFAULT)
    assert again == s
    assert again.to_dict() == s.to_dict()


def test_piano_mesh_is_one_closed_body_of_the_papers_size():
    mesh = trimesh.load(PIANO)
    assert mesh.is_watertight and mesh.is_winding_consistent and mesh.body_count == 1
    assert mesh.volume > 0  # outward normals
    assert len(mesh.faces) <= 4000
    # §6: 0.425 (width, x) x 0.205 (depth, y) x 0.45 m (height, z); vertices are rounded to 1e-6 m.
    np.testing.assert_allclose(mesh.bounds, [[-0.2125, -0.1025, 0.0], [0.2125, 0.1025, 0.45]], atol=1e-9)
    # Standing on its feet the CoM projects well inside them (the legs are inset 2 mm from the sides).
    feet = mesh.vertices[mesh.vertices[:, 2] == 0.0, :2]
    eq = ConvexHull(feet).equations
    assert -np.max(eq[:, :2] @ mesh.center_mass[:2] + eq[:, 2]) > 0.05
    # The keyboard ledge makes the outline non-convex, the legs add curved faces.
    assert mesh.convex_hull.volume > 1.05 * mesh.volume
    assert len(mesh.facets) > 100


def test_piano_script_reproduces_the_committed_mesh_byte_for_byte(tmp_path):
    out = tmp_path / "piano.obj"
    subprocess.run([sys.executable, str(PIANO.with_name("make_toy_piano.py")), str(out)], check=True,
                   capture_output=True)
    assert out.read_bytes() == PIANO.read_bytes()


# ---- loading and defaults ---------------------------------------------------------------------------

def test_minimal_scene_fills_defaults(scene_dir):
    path = write(scene_dir, minimal(), "mini.json")
    s = load_scene(path)
    assert s.name == "mini"  # the file stem
    assert (s.object.friction, s.object.scale, s.table.friction) == (0.5, 1.0, 0.5)
    assert s.robot.eef_links == ("left_ball", "right_ball")
    assert (s.robot.ball_radius, s.robot.max_eef_force, s.robot.base_yaw_deg) == (0.02, 50.0, 0.0)
    assert s.obstacles == ()
    assert (s.planner.theta_t_deg, s.planner.tilt_deg, s.planner.usp) == (15.0, 8.0, True)
    assert (s.planner.weights.pivot, s.planner.weights.regrasp, s.planner.weights.tumble) == (0.1, 0.5, 1.0)
    assert (s.planner.seed, s.planner.max_poses, s.planner.goal_reach) == (0, 400, 0.5)
    assert s.start.placement is None and s.goal.down is None and s.goal.placement == 3
    assert s.object.mesh_path == (scene_dir / "objects" / "box.stl").resolve()
    assert s.planner.theta_t == pytest.approx(math.pi / 12)


def test_round_trip_to_dict_json_load_gives_an_equal_scene(scene_dir):
    s = load_scene(write(scene_dir, rich()))
    again = load_scene(write(scene_dir, s.to_dict(), "again.json"))
    assert again == s
    assert json.dumps(again.to_dict(), sort_keys=True) == json.dumps(s.to_dict(), sort_keys=True)
    # Canonical: integers written for float keys come back as floats, so equal scenes hash equally.
    assert isinstance(s.to_dict()["planner"]["theta_t_deg"], float)


def test_to_dict_of_a_minimal_scene_lists_every_key(scene_dir):
    d = load_scene(write(scene_dir, minimal())).to_dict()
    assert set(d) == {"name", "object", "table", "robot", "obstacles", "start", "goal", "planner"}
    assert set(d["planner"]) == {"theta_t_deg", "tilt_deg", "usp", "weights", "seed", "max_poses", "goal_reach"}
    assert d["goal"] == {"placement": 3, "xy": [0.2, 0.1], "yaw_deg": 30.0}


# ---- bad input: one line naming the file and the key ------------------------------------------------

def _set(path: str, value):
    """A mutation setting the key at dotted ``path`` (``[i]`` for list items) to ``value``."""
    def mutate(d):
        keys = re.findall(r"[^.\[\]]+|\[\d+\]", path)
        for k in keys[:-1]:
            d = d[int(k[1:-1])] if k.startswith("[") else d[k]
        last = keys[-1]
        d[int(last[1:-1]) if last.startswith("[") else last] = value
    return mutate


def _drop(section: str, key: str):
    def mutate(d):
        del d[section][key]
    return mutate


BOX45 = [{"type": "box", "size": [0.4, 0.02, 0.1], "xyz": [0.0, 0.0, 0.05], "yaw_deg": 45}]


def _start_in_rotated_box(d):
    """A harmless first obstacle, then a 0.4 x 0.02 bar turned by 45° through the start (0.1, 0.1)."""
    d["obstacles"] = [{"type": "cylinder", "radius": 0.01, "height": 0.1, "xyz": [0.4, 0.25, 0.05]}, *BOX45]
    d["start"]["xy"] = [0.1, 0.1]

BAD = [
    # (case id, mutation, key path named in the message, words in the message)
    ("unknown_top_key", _set("colour", "red"), "colour", "unknown key"),
    ("unknown_nested_key", _set("object.colour", "red"), "object.colour", "unknown key"),
    ("unknown_weight", _set("planner", {"weights": {"push": 1}}), "planner.weights.push", "unknown key"),
    ("missing_key", _drop("object", "mass"), "object.mass", "missing"),
    ("mass_is_string", _set("object.mass", "heavy"), "object.mass", "must be a number"),
    ("mass_is_bool", _set("object.mass", True), "object.mass", "must be a number"),
    ("size_not_list", _set("table.size", 0.9), "table.size", "list of 2 numbers"),
    ("object_not_dict", _set("table", [0.9, 0.6]), "table", "JSON object"),
    ("usp_not_bool", _set("planner", {"usp": "yes"}), "planner.usp", "true or false"),
    ("seed_not_int", _set("planner", {"seed": 1.5}), "planner.seed", "integer"),
    ("goal_reach_negative", _set("planner", {"goal_reach": -0.5}), "planner.goal_reach", "must be >= 0"),
    ("mass_nan", _set("object.mass", float("nan")), "object.mass", "finite"),
    ("height_inf", _set("table.height", float("inf")), "table.height", "finite"),
    ("base_nan", _set("robot.base_xyz", [0.0, float("nan"), 0.0]), "robot.base_xyz[1]", "finite"),
    ("mass_zero", _set("object.mass", 0), "object.mass", "must be > 0 (got 0)"),
    ("mass_negative", _set("object.mass", -1), "object.mass", "must be > 0 (got -1)"),
    ("object_friction_negative", _set("object.friction", -0.1), "object.friction", ">= 0"),
    ("table_friction_negative", _set("table.friction", -0.1), "table.friction", ">= 0"),
    ("table_size_zero", _set("table.size", [0.9, 0]), "table.size[1]", "> 0"),
    ("table_size_negative", _set("table.size", [-0.9, 0.6]), "table.size[0]", "> 0"),
    ("mesh_missing", _set("object.mesh", "../objects/nope.obj"), "object.mesh", "file not found"),
    ("urdf_missing", _set("robot.urdf", "../robots/nope.urdf"), "robot.urdf", "file not found"),
    ("same_eef_links", _set("robot.eef_links", ["a", "a"]), "robot.eef_links", "differ"),
    ("start_off_table", _set("start.xy", [0.46, 0.0]), "start.xy", "off the table"),
    ("goal_off_table", _set("goal.xy", [0.0, -0.31]), "goal.xy", "off the table"),
    ("down_zero", _set("start.down", [0, 0, 0]), "start.down", "nonzero"),
    ("down_and_placement", _set("start.placement", 1), "start", "exactly one"),
    ("placement_negative", _set("goal.placement", -1), "goal.placement", ">= 0"),
    ("obstacle_type", _set("obstacles", [{"type": "cone", "xyz": [0, 0, 0]}]), "obstacles[0].type", "box"),
    ("obstacle_box_size", _set("obstacles", [{"type": "box", "size": [0.1, 0, 0.1], "xyz": [0.3, 0, 0]}]),
     "obstacles[0].size[1]", "> 0"),
    ("cylinder_yaw_unknown",
     _set("obstacles", [{"type": "cylinder", "radius": 0.1, "height": 0.1, "xyz": [0.3, 0, 0],
                         "yaw_deg": 3}]),
     "obstacles[0].yaw_deg", "unknown key"),
    ("obstacle_mesh_missing", _set("obstacles", [{"type": "mesh", "mesh": "nope.stl", "xyz": [0, 0, 0]}]),
     "obstacles[0].mesh", "file not found"),
    ("start_in_box",
     _set("obstacles", [{"type": "box", "size": [0.1, 0.1, 0.1], "xyz": [-0.18, 0.04, 0.05]}]),
     "start.xy", "obstacles[0] (box)"),
    ("start_in_rotated_box", _start_in_rotated_box, "start.xy", "obstacles[1] (box)"),
    ("goal_in_cylinder",
     _set("obstacles", [{"type": "cylinder", "radius": 0.05, "height": 0.2, "xyz": [0.23, 0.14, 0.1]}]),
     "goal.xy", "obstacles[0] (cylinder)"),
    # The 0.3 x 0.2 box mesh at (0.3, 0.1) covers x in [0.15, 0.45], y in [0, 0.2].
    ("goal_in_mesh",
     _set("obstacles", [{"type": "mesh", "mesh": "../objects/box.stl", "xyz": [0.3, 0.1, 0]}]),
     "goal.xy", "obstacles[0] (mesh)"),
    ("bad_name", _set("name", "a/b"), "name", "letters"),
]


@pytest.mark.parametrize("mutate, key, words", [b[1:] for b in BAD], ids=[b[0] for b in BAD])
def test_bad_input_raises_one_line_naming_file_and_key(scene_dir, mutate, key, words):
    data = minimal()
    mutate(data)
    path = write(scene_dir, data)
    with pytest.raises(InputError) as err:
        load_scene(path)
    msg = str(err.value)
    assert "\n" not in msg
    assert msg.startswith(f"{path}: {key}: "), msg
    assert words in msg, msg


def test_rotated_box_footprint_follows_its_yaw(scene_dir):
    # (0.1, 0) is inside the unrotated 0.4 x 0.02 bar but 0.07 m from the bar turned by +45°: allowed.
    data = minimal()
    data["obstacles"] = BOX45
    data["start"]["xy"] = [0.1, 0.0]
    load_scene(write(scene_dir, data))
    # Turned by -45° instead, the bar misses (0.1, 0.1), which the +45° bar covers (test above).
    data["obstacles"] = [dict(BOX45[0], yaw_deg=-45)]
    data["start"]["xy"] = [0.1, 0.1]
    load_scene(write(scene_dir, data))


def test_invalid_json_names_file_line_and_column(scene_dir):
    text = '{\n  "name": "x",\n  "object": {"mass": 1,, }\n}\n'
    path = scene_dir / "scenes" / "broken.json"
    path.write_text(text)
    with pytest.raises(InputError) as err:
        load_scene(path)
    msg = str(err.value)
    # json reports the second comma on line 3: column of the character after "1,".
    col = text.splitlines()[2].index(",,") + 2
    assert msg.startswith(f"{path}:3:{col}: invalid JSON"), msg
    assert "\n" not in msg


def test_duplicate_key_is_an_error(scene_dir):
    path = scene_dir / "scenes" / "dup.json"
    path.write_text(json.dumps(minimal())[:-1] + ', "start": {"down": [0, 0, -1], "xy": [0, 0]}}')
    with pytest.raises(InputError, match=r'dup\.json: duplicate key "start"'):
        load_scene(path)


def test_missing_scene_file_is_an_input_error(tmp_path):
    with pytest.raises(InputError, match="nope.json: cannot read scene file"):
        load_scene(tmp_path / "nope.json")


# ---- helpers later stages use ------------------------------------------------------------------------

def test_base_transform_places_and_turns_the_base(scene_dir):
    data = minimal()
    data["robot"]["base_yaw_deg"] = 90
    X_WB = load_scene(write(scene_dir, data)).base_transform()
    assert X_WB.shape == (4, 4)
    np.testing.assert_allclose(X_WB[:3, 3], [-0.7, 0.0, -0.75])
    # Yaw +90°: the base x axis points along W +y (1e-15: cos(pi/2) in floating point).
    np.testing.assert_allclose(X_WB[:3, 0], [0.0, 1.0, 0.0], atol=1e-15)


def test_obstacle_geometries_are_centred_shapes_with_world_poses(scene_dir):
    s = load_scene(write(scene_dir, rich()))
    box, cyl, mesh = s.obstacle_geometries()
    assert [g.name for g in (box, cyl, mesh)] == ["obstacles[0]", "obstacles[1]", "obstacles[2]"]
    assert box.kind == "box" and box.size == (0.1, 0.2, 0.3)
    np.testing.assert_allclose(box.X_WOb[:3, 3], [0.3, -0.2, 0.15])
    assert se3.yaw_of(box.X_WOb[:3, :3]) == pytest.approx(math.radians(10))
    assert (cyl.kind, cyl.radius, cyl.height) == ("cylinder", 0.05, 0.2)
    # Mesh vertices are scaled (scale 0.5 of a 0.3 x 0.2 x 0.4 box) and read-only.
    assert mesh.kind == "mesh"
    np.testing.assert_allclose(np.ptp(mesh.vertices, axis=0), [0.15, 0.1, 0.2])
    assert mesh.faces.shape == (12, 3) and not mesh.vertices.flags.writeable
    poses = s.obstacle_poses()
    assert poses.shape == (3, 4, 4)
    np.testing.assert_allclose(poses[2], mesh.X_WOb)


def test_no_obstacles_gives_empty_pose_batch(scene_dir):
    s = load_scene(write(scene_dir, minimal()))
    assert s.obstacle_poses().shape == (0, 4, 4)
    assert s.obstacle_geometries() == ()


def test_table_geometry_has_its_top_at_world_z_zero(scene_dir):
    t = load_scene(write(scene_dir, minimal())).table_geometry()
    assert t.kind == "box" and t.size == (0.9, 0.6, 0.75)
    assert t.X_WOb[2, 3] + t.size[2] / 2 == pytest.approx(0.0)


@pytest.mark.parametrize("shape", [(0, 2), (1, 3), (4, 2), (2, 3, 3)])
def test_on_table_batches_over_leading_dimensions(scene_dir, shape, rng):
    s: Scene = load_scene(write(scene_dir, minimal()))
    p = rng.uniform(-0.6, 0.6, size=shape)
    got = s.on_table(p, margin=0.05)
    assert got.shape == shape[:-1]
    loop = [abs(q[0]) <= 0.4 and abs(q[1]) <= 0.25 for q in p.reshape(-1, shape[-1])]
    assert got.reshape(-1).tolist() == loop


def test_scenes_compare_by_content_not_location(scene_dir):
    a = load_scene(write(scene_dir, minimal(), "a.json"))
    data = copy.deepcopy(minimal())
    data["name"] = "a"
    b = load_scene(write(scene_dir, data, "b.json"))
    assert a == b and a.path != b.path
    data["object"]["mass"] = 2.5
    assert load_scene(write(scene_dir, data, "c.json")) != a
