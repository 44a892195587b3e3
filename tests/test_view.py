"""``pivot view``: the page's scene and animation follow the artifacts; a real browser draws and scrubs it."""

import json
import re
import shutil
import time
from pathlib import Path

import numpy as np
import pytest
import trimesh
from typer.testing import CliRunner

from pivotcli.app import app
from stages import artifacts, threejs, view
from stages.scene import load_scene
from tests.conftest import REPO

runner = CliRunner()


@pytest.fixture(scope="module")
def built(small_build, tmp_path_factory):
    """The small scene's build laid out as the Makefile does: analysis/, full/ with the plan, its
    trajectories and its physics execution."""
    from stages import execute, trajectory

    scene, small = small_build
    b = tmp_path_factory.mktemp("view") / "build"
    shutil.copytree(small / "analysis", b / "analysis")
    (b / "full").mkdir()
    shutil.copy(small / "plan.json", b / "full" / "plan.json")
    stats = trajectory.run(scene, b / "analysis", b / "full" / "plan.json", b / "full" / "trajectories.parquet",
                           trajectory.Params())
    assert stats["status"] == "ok"
    execute.run(scene, b / "analysis", b / "full" / "trajectories.parquet", b / "full", execute.Params())
    return scene, b


def scene_of(html: str) -> dict:
    return json.loads(re.search(r'<script type="application/json" id="pivot-scene">(.*?)</script>', html, re.S)[1])


def track(scene: dict, path: str, prop: str) -> tuple[np.ndarray, np.ndarray]:
    anim = next(a for a in scene["animations"] if a["path"] == path)
    tr = next(t for t in anim["clip"]["tracks"] if t["name"] == f".{prop}")
    return np.array(tr["times"]), np.array(tr["values"])


def test_view_is_one_offline_file_byte_identical_on_rerun(built, tmp_path):
    scene, b = built
    a, c = tmp_path / "a.html", tmp_path / "c.html"
    res = view.run(b, scene, a)
    view.run(b, scene, c)
    assert res.status == "ok" and a.read_bytes() == c.read_bytes()
    html = a.read_text()
    assert "MeshCat.Viewer" in html and threejs.viewer_script()[:200] in html  # the viewer is inlined
    assert not re.search(r"<(script|link|img)[^>]+(src|href)=", html)  # nothing loaded from elsewhere
    paths = {c["path"] for c in scene_of(html)["commands"]}
    for p in ("/meshcat/table", "/meshcat/goal", "/meshcat/plan/object", "/meshcat/execution/object",
              "/meshcat/plan/com_path", "/meshcat/plan/forces/left", "/meshcat/robot_trunk/base_link",
              "/meshcat/plan/robot/left_link_7_t", "/meshcat/execution/robot/right_link_7_t"):
        assert p in paths, p
    assert res.size < 4e6  # 60 s of plan and execution in a few MB
    from stages.objectmodel import load_object_model
    from stages.sample import placement_pose

    X_goal = placement_pose(load_scene(scene).goal, load_object_model(b / "analysis")[0], "goal")[0]
    goal = next(c for c in scene_of(html)["commands"] if c["type"] == "set_transform" and c["path"] == "/meshcat/goal")
    assert np.allclose(np.reshape(goal["matrix"], (4, 4)).T, X_goal, atol=1e-6)  # column-major in three.js


def test_object_track_follows_the_trajectories_and_the_execution(built, tmp_path):
    scene, b = built
    html = (view.run(b, scene, tmp_path / "v.html").path).read_text()
    s = scene_of(html)
    tr = artifacts.read_table(b / "full" / "trajectories.parquet", "trajectories")
    log = artifacts.read_table(b / "full" / "execution.parquet", "execution")
    for group, table in (("plan", tr), ("execution", log)):
        t, p = track(s, f"/meshcat/{group}/object", "position")
        rows = np.abs(table["t"][None, :] - t[:, None]).argmin(1)  # times are rounded to 1 ms
        want = np.stack([table["x"], table["y"], table["z"]], 1)[rows]
        assert np.abs(p.reshape(-1, 3) - want).max() <= 1e-4  # rounded to 0.1 mm in the page
    assert t[-1] == pytest.approx(tr["t"][-1], abs=1e-3) and 0.05 < np.diff(t).max() <= 1 / 12 + 0.05


def test_the_drawn_balls_are_where_the_trajectories_put_them(built, tmp_path):
    """The ball rides with the last wrist link (its fixed frames merged into it): pose track x its offset."""
    from stages import se3

    scene, b = built
    s = scene_of(view.run(b, scene, tmp_path / "v.html").path.read_text())
    tr = artifacts.read_table(b / "full" / "trajectories.parquet", "trajectories")
    r = load_scene(scene).robot.ball_radius
    for arm, c in (("left", "l"), ("right", "r")):
        path = f"/meshcat/plan/robot/{arm}_link_7_t"
        obj = next(x["object"] for x in s["commands"] if x["type"] == "set_object" and x["path"] == path)
        geom = {g["uuid"]: g for g in obj["geometries"]}
        ball = [ch for ch in obj["object"]["children"]
                if geom.get(ch.get("geometry"), {}).get("radius") == pytest.approx(r)]
        assert len(ball) == 1
        offset = np.reshape(ball[0]["matrix"], (4, 4)).T[:3, 3]
        t, p = track(s, path, "position")
        _, q = track(s, path, "quaternion")
        drawn = se3.transform_points(se3.make_transform(se3.matrix_from_quat(q.reshape(-1, 4)), p.reshape(-1, 3)),
                                     offset)
        rows = np.abs(tr["t"][None, :] - t[:, None]).argmin(1)
        want = np.stack([tr[f"{c}x"], tr[f"{c}y"], tr[f"{c}z"]], 1)[rows]
        err = np.linalg.norm(drawn - want, axis=1)
        assert np.median(err) < 1e-3 and err.max() < 5e-3, (np.median(err), err.max())  # IK meets the ball to mm


def test_force_arrows_end_on_the_object_and_show_only_in_contact(built, tmp_path):
    scene, b = built
    s = scene_of(view.run(b, scene, tmp_path / "v.html").path.read_text())
    mesh = trimesh.load(b / "analysis" / "object.ply", force="mesh", process=False)
    _, X = track(s, "/meshcat/plan/object", "position")
    t, tip = track(s, "/meshcat/plan/forces/left", "position")
    _, shown = track(s, "/meshcat/plan/forces/left", "visible")
    _, q = track(s, "/meshcat/plan/object", "quaternion")
    tr = artifacts.read_table(b / "full" / "trajectories.parquet", "trajectories")
    rows = np.abs(tr["t"][None, :] - t[:, None]).argmin(1)
    assert shown.any() and not shown[~tr["left_contact"][rows]].any()
    from stages import se3

    X_WO = se3.make_transform(se3.matrix_from_quat(q.reshape(-1, 4)), X.reshape(-1, 3))
    tip_O = se3.transform_points(se3.invert(X_WO), tip.reshape(-1, 3))[shown]
    assert np.abs(trimesh.proximity.signed_distance(mesh, tip_O)).max() < 1e-3  # on the surface


def test_keyframes_keep_every_change_of_phase_and_contact():
    t = np.arange(100) / 24
    phase = np.array(["a"] * 37 + ["b"] * 63)
    rows = view.keyframe_rows(t, [phase], rate=12.0)
    assert 37 in rows and rows[0] == 0 and rows[-1] == 99 and len(rows) <= 52


def test_decimate_bounds_the_triangle_count_and_keeps_the_shape():
    m = trimesh.creation.icosphere(subdivisions=5, radius=0.2)  # 20,480 triangles
    v, f = view.decimate(m.vertices, m.faces, 2000)
    assert 200 < len(f) <= 2000 and f.max() < len(v)
    assert np.abs(np.linalg.norm(v, axis=1) - 0.2).max() < 0.01  # cluster means stay near the sphere
    small = trimesh.creation.box((0.1, 0.2, 0.3))
    assert view.decimate(small.vertices, small.faces, 2000)[1].shape == (12, 3)


def test_urdf_visuals_and_the_trunk_pose():
    visuals, joints = view.read_urdf(REPO / "data" / "robots" / "sda5f.urdf")
    assert len(visuals) == 21 and {v.kind for v in visuals} >= {"box", "capsule", "sphere"}
    X_WB = np.eye(4)
    X_WB[:3, 3] = [-0.7, 0.0, -0.75]
    poses = view.static_link_poses(joints, X_WB, moving=set())
    assert np.allclose(poses["base_link"], X_WB)
    assert np.allclose(poses["torso_link"][:3, 3], [-0.7 + 0.045, 0.0, -0.75 + 0.7296])  # the torso joint's origin


def test_cli_view_of_a_build_without_a_plan_exits_1_and_the_page_says_why(small_build, tmp_path):
    scene, small = small_build
    b = tmp_path / "build"
    shutil.copytree(small / "analysis", b / "analysis")
    meta = artifacts.make_meta("plan", {}, {"scene": scene}, "test")
    artifacts.write_json(b / "full" / "plan.json", {"status": "infeasible", "reason": "no route past the wall",
                                                    "steps": []}, meta)
    r = runner.invoke(app, ["view", str(b), "--scene", str(scene)])
    assert r.exit_code == 1, r.output
    html = (b / "full" / "view.html").read_text()
    assert "no route past the wall" in html and "/meshcat/plan/object" in html


def test_cli_view_with_another_scene_is_one_line_exit_2_and_writes_nothing(built, tmp_path):
    _, b = built
    other = REPO / "data" / "scenes" / "exp1_reach.json"
    r = runner.invoke(app, ["view", str(b), "--scene", str(other), "--out", str(tmp_path / "v.html")])
    assert r.exit_code == 2 and "sha256" in r.output and len(r.output.strip().splitlines()) == 1
    assert not (tmp_path / "v.html").exists()
    assert load_scene(other).name == "exp1_reach"


# ------------------------------------------------------------------------------------ in a real browser

ARTIFACTS = REPO / "build" / "test-artifacts"


@pytest.fixture(scope="session")  # session-scoped as the build is, so that it is asked for first
def chromium() -> tuple[str, str]:
    """:func:`find_chromium`: a machine without chromium skips before the builds run."""
    return find_chromium()


def find_chromium() -> tuple[str, str]:
    """Paths of Debian's chromium and chromedriver; skips, saying why, where either is missing."""
    chromium, driver = shutil.which("chromium"), shutil.which("chromedriver")
    if not chromium or not driver:
        pytest.skip("browser test skipped: Debian's chromium and chromium-driver are not installed and could not "
                    "be (make test installs them with apt-get as root)")
    pytest.importorskip("selenium.webdriver", reason="browser test skipped: selenium is not installed")
    return chromium, driver


def chromium_driver():
    """Debian's chromium through its chromedriver (``make test`` installs both with apt), headless with
    software WebGL; skips, saying why, where either is missing."""
    chromium, driver = find_chromium()
    from selenium import webdriver

    opts = webdriver.ChromeOptions()
    opts.binary_location = chromium
    for arg in ("--headless=new", "--no-sandbox", "--disable-gpu", "--use-angle=swiftshader",
                "--enable-unsafe-swiftshader", "--window-size=1200,800", "--disable-dev-shm-usage"):
        opts.add_argument(arg)
    opts.set_capability("goog:loggingPrefs", {"browser": "ALL"})
    return webdriver.Chrome(options=opts, service=webdriver.ChromeService(executable_path=driver))


def canvas_pixels(drv) -> np.ndarray:
    """The WebGL canvas as an ``(h, w, 3)`` uint8 array (MeshCat's own capture)."""
    import base64
    import io

    from PIL import Image

    url = drv.execute_script("return viewer.capture_image();")
    return np.asarray(Image.open(io.BytesIO(base64.b64decode(url.split(",", 1)[1]))).convert("RGB"))


def test_browser_loads_the_page_from_disk_draws_it_and_the_slider_moves_the_object(chromium, built, tmp_path):
    from selenium.webdriver.common.action_chains import ActionChains
    from selenium.webdriver.common.by import By
    from selenium.webdriver.support.ui import WebDriverWait

    scene, b = built
    page = view.run(b, scene, tmp_path / "view.html").path
    tr = artifacts.read_table(b / "full" / "trajectories.parquet", "trajectories")
    ARTIFACTS.mkdir(parents=True, exist_ok=True)
    drv = chromium_driver()
    try:
        drv.get(page.resolve().as_uri())
        WebDriverWait(drv, 60).until(lambda d: d.execute_script(
            "return window.viewer !== undefined && viewer.animator.actions.length > 0"))
        errors = [e for e in drv.get_log("browser") if e["level"] == "SEVERE"]
        assert not errors, errors
        first = canvas_pixels(drv)
        assert len(np.unique(first.reshape(-1, 3), axis=0)) > 100  # a drawn scene, not a blank canvas
        slider = drv.find_element(By.ID, "pv-slider")
        shots, positions, times = [], [], []
        for fraction in (0.05, 0.6):
            x = int((fraction - 0.5) * slider.size["width"])
            ActionChains(drv).move_to_element_with_offset(slider, x, 0).click().perform()
            drv.execute_script("viewer.render();")
            times.append(float(slider.get_attribute("value")))
            positions.append(drv.execute_script(
                "var p = viewer.scene_tree.find(['meshcat', 'plan', 'object']).object.position;"
                "return [p.x, p.y, p.z];"))
            shots.append(canvas_pixels(drv))
            drv.save_screenshot(str(ARTIFACTS / f"view-t{times[-1]:.1f}.png"))
        drv.find_element(By.ID, "pv-play").click()  # play runs the clock on from the slider's time ...
        time.sleep(1.0)
        drv.find_element(By.ID, "pv-play").click()  # ... and pause stops it
        played = drv.execute_script("return viewer.animator.time;")
        time.sleep(0.5)
        assert times[1] < played == drv.execute_script("return viewer.animator.time;")
        drv.find_element(By.CSS_SELECTOR, ".pv-layer[data-layer=execution]").click()
        assert not drv.execute_script("return viewer.scene_tree.find(['meshcat', 'execution']).object.visible;")
        errors = [e for e in drv.get_log("browser") if e["level"] == "SEVERE"]
        assert not errors, errors
    finally:
        drv.quit()
    assert times[1] > times[0] + 0.3 * tr["t"][-1]  # the click moved the slider
    for t, p in zip(times, positions, strict=True):  # the drawn object is where the plan has it then
        want = [np.interp(t, tr["t"], tr[c]) for c in "xyz"]
        assert np.abs(np.array(p) - want).max() < 2e-3, (t, p, want)
    assert np.linalg.norm(np.subtract(*positions)) > 0.01
    changed = np.any(shots[0] != shots[1], axis=2)
    assert changed.mean() > 0.002  # the picture changed where the object moved
    shutil.copy(page, ARTIFACTS / "view.html")
    assert Path(ARTIFACTS / "view.html").stat().st_size > 0


def test_timeline_names_the_step_and_phase_and_marks_regrasps_and_catches():
    steps = [{"primitive": "regrasp", "support": "USP"}, {"primitive": "tumble", "support": "SP",
                                                          "pusher": "left", "catcher": "right"}]
    rows = [(0, "transit", "left")] * 3 + [(0, "hold", "hold")] * 2 + [(1, "tumble", p) for p in
                                                                         ("push", "push", "release", "catch")]
    tr = {"t": np.arange(len(rows)) * 0.5, "primitive": np.array([r[0] for r in rows]),
          "kind": np.array([r[1] for r in rows]), "phase": np.array([r[2] for r in rows])}
    out = view.timeline(tr, steps)
    assert out["segments"] == [[0.0, 0, "transit", "left"], [1.5, 0, "hold", "hold"], [2.5, 1, "tumble", "push"],
                               [3.5, 1, "tumble", "release"], [4.0, 1, "tumble", "catch"]]
    assert [t for t, _ in out["events"]] == [0.0, 3.5, 4.0]
    assert "left ball moves" in out["events"][0][1] and "USP" in out["events"][0][1]
    assert "right ball lowers" in out["events"][2][1]


def test_an_execution_log_that_stops_early_is_drawn_as_far_as_it_goes(built, tmp_path):
    from stages import execute

    scene, b = built
    c = tmp_path / "build"
    shutil.copytree(b, c)
    log = artifacts.read_table(c / "full" / "execution.parquet", "execution")
    half = len(log) // 2
    artifacts.write_table(c / "full" / "execution.parquet", {k: v[:half] for k, v in log.columns.items()},
                          execute.LOG_FIELDS, log.meta)
    s = scene_of(view.run(c, scene, tmp_path / "v.html").path.read_text())
    t, p = track(s, "/meshcat/execution/object", "position")
    assert t[-1] == pytest.approx(log["t"][half - 1], abs=1e-3)
    assert np.allclose(p[-3:], [log["x"][half - 1], log["y"][half - 1], log["z"][half - 1]], atol=1e-4)
    log2 = {k: v[:half] for k, v in log.columns.items()}
    log2["t"] = log2["t"] + 0.01  # another run's time steps: refused, one line naming the file
    artifacts.write_table(c / "full" / "execution.parquet", log2, execute.LOG_FIELDS, log.meta)
    with pytest.raises(view.ArtifactError, match="execution.parquet: its rows are not the trajectories"):
        view.run(c, scene, tmp_path / "w.html")
