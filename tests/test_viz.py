"""Visualizers draw what the plants' kinematics say: artist coordinates against closed forms
and `frame_pose`; movies decode back to the right frames, with the drawn parts where the
axes' transform puts them; the HTML export needs no network."""

import pathlib
import re

import jax
import jax.numpy as jnp
import matplotlib
import numpy as np
import pytest

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

import jaxdrake as jd  # noqa: E402
from jaxdrake.viz import PlanarRigidBodyVisualizer, visualizer_for  # noqa: E402

STATES = np.random.default_rng(0).uniform(-3, 3, (5, 4))


def drawn(fig, name):
    """The (k, 2) points of the artist drawing shape `name`."""
    artist = next(a for a in fig.axes[0].get_children() if a.get_gid() == name)
    points = artist.get_xy() if hasattr(artist, "get_xy") else np.stack(artist.get_data(), 1)
    return np.asarray(points, float)


def test_pendulum_acrobot_and_cart_pole_are_drawn_where_their_kinematics_put_them():
    pendulum, acrobot, cart_pole = jd.models.Pendulum(l=0.7), jd.models.Acrobot(l1=1.2, l2=2.1), jd.models.CartPole(l=0.6)
    for x in STATES:
        fig = visualizer_for(pendulum).draw(x[:2])
        np.testing.assert_allclose(drawn(fig, "bob")[0], 0.7 * np.array([np.sin(x[0]), -np.cos(x[0])]), atol=1e-12)
        plt.close(fig)
        fig = visualizer_for(acrobot).draw(x)
        elbow = 1.2 * np.array([np.sin(x[0]), -np.cos(x[0])])
        tip = elbow + 2.1 * np.array([np.sin(x[0] + x[1]), -np.cos(x[0] + x[1])])
        points = drawn(fig, "links")
        points = points[~np.isnan(points[:, 0])]
        assert any(np.allclose(p, elbow, atol=1e-12) for p in points)
        assert any(np.allclose(p, tip, atol=1e-12) for p in points)
        np.testing.assert_allclose(drawn(fig, "joints")[1], elbow, atol=1e-12)
        plt.close(fig)
        fig = visualizer_for(cart_pole).draw(x)
        points = drawn(fig, "links")
        tip = np.array([x[0] + 0.6 * np.sin(x[1]), -0.6 * np.cos(x[1])])
        assert any(np.allclose(p, tip, atol=1e-12) for p in points[~np.isnan(points[:, 0])])
        np.testing.assert_allclose(drawn(fig, "cart")[:4].mean(0), [x[0], 0.0], atol=1e-12)  # a closed polygon
        plt.close(fig)


def test_a_urdf_robot_projection_puts_every_joint_at_its_frame_pose():
    panda = jd.models.Panda()
    vis = PlanarRigidBodyVisualizer(panda, plane="xz")
    q = jnp.array([0.3, -0.5, 0.2, -2.0, 0.4, 1.5, 0.1])
    fig = vis.draw(jnp.concatenate([q, jnp.zeros(7)]))
    joints = drawn(fig, "joints")
    for k, link in enumerate(panda.tree.body_names):
        np.testing.assert_allclose(joints[k], np.asarray(panda.frame_pose(q, link)[1])[[0, 2]], atol=1e-12)
    plt.close(fig)


def test_a_gif_decodes_to_the_requested_frames_with_the_bob_where_the_axes_put_it(tmp_path):
    from PIL import Image, ImageSequence

    pendulum = jd.models.Pendulum()
    vis = visualizer_for(pendulum)
    traj = jd.simulate(pendulum, (0.0, 1.5), jnp.array([2.0, 0.0]))
    path = vis.save(traj, tmp_path / "pendulum.gif", fps=8)
    frames = [np.asarray(f.convert("RGB")) for f in ImageSequence.Iterator(Image.open(path))]
    assert len(frames) == round(1.5 * 8) and frames[0].shape == (480, 640, 3)
    # GIF delays are in 10-ms units: 125-ms frames alternate 130 / 120, and the movie lasts 1.5 s
    durations = [f.info["duration"] for f in ImageSequence.Iterator(Image.open(path))]
    assert sum(durations) == 1500 and set(durations) <= {120, 130}
    animation = vis.animate(traj, fps=8)  # the same figure, to read its transform
    fig = animation._fig
    fig.canvas.draw()
    k = 7
    x = np.asarray(traj.state(k / 8))
    bob = 0.5 * np.array([np.sin(x[0]), -np.cos(x[0])])
    px, py = fig.axes[0].transData.transform(bob)
    red = np.abs(frames[k].astype(int) - np.array([214, 39, 40])).sum(axis=2) < 60  # C3, the bob
    rows, cols = np.nonzero(red)
    assert len(rows) > 20
    assert abs(cols.mean() - px) < 2 and abs(rows.mean() - (480 - py)) < 2
    plt.close(fig)


def test_mp4_and_html_movies_of_a_hybrid_trajectory(tmp_path):
    import imageio.v3 as iio

    wheel = jd.models.RimlessWheel()
    vis = visualizer_for(wheel)
    traj = jd.simulate(wheel, (0.0, 2.0), jnp.array([0.0, 2.0]))
    assert len(traj.events["times"]) >= 2  # the movie plays through impacts
    mp4 = vis.save(traj, tmp_path / "wheel.mp4", fps=10)
    frames = np.stack(list(iio.imiter(mp4)))
    assert frames.shape[0] == 20 and frames.shape[1:3] == (480, 640)
    html = vis.save(traj, tmp_path / "wheel.html", fps=10).read_text()
    assert "<script" in html and not re.search(r"(https?:)?//[a-z0-9.-]+\.[a-z]{2,}", html, re.IGNORECASE)
    # the camera follows the wheel: after k impacts it has gone k steps down the ramp
    travel = vis.travel(traj, np.array([0.0, 1.99]))
    step = 2 * np.sin(np.pi / 8)
    k = np.searchsorted(traj.events["times"], 1.99)
    np.testing.assert_allclose(np.linalg.norm(travel[1]), k * step, rtol=1e-12)
    np.testing.assert_allclose(travel[1] / np.linalg.norm(travel[1]), [np.cos(0.08), -np.sin(0.08)], rtol=1e-12)


def test_a_visualizer_is_a_system_in_a_diagram_and_errors_name_the_remedy():
    pendulum = jd.models.Pendulum()
    vis = visualizer_for(pendulum)
    assert vis.input_frame == pendulum.state_frame and vis.num_states == 0 and vis.draw_period == 1 / 32
    diagram = jd.cascade(pendulum, vis)
    traj = jd.simulate(diagram, (0.0, 1.0), jnp.array([1.0, 0.0]))
    np.testing.assert_allclose(traj.final_state, jd.simulate(pendulum, (0.0, 1.0), jnp.array([1.0, 0.0])).final_state)
    animation = vis.animate(traj)
    assert animation._fig.axes[0].get_title().startswith("Pendulum: t = ")
    plt.close(animation._fig)
    with pytest.raises(TypeError, match="subclass jaxdrake.viz.Visualizer"):
        visualizer_for(jd.models.VanDerPol())
    with pytest.raises(ValueError, match="choose .gif, .mp4 or .html"):
        vis.save(traj, "movie.avi")


def test_visualizer_for_recognises_the_notes_rigid_body_plants_by_their_class():
    """Not by where their URDF file lives: an `Acrobot` (also one given ground contact) and a
    `DoublePendulum` are drawn in the x-z plane, a `CartPole` with its cart unless another plane
    is asked for; the acrobot's own URDF loaded as a plain `RigidBodySystem` is any URDF robot,
    a 3-D MeshCat scene."""
    pytest.importorskip("meshcat")
    acrobot = jd.models.Acrobot()
    touching = acrobot.with_collision_geometry("lower_link", jd.geometry.Sphere(0.1)).with_ground(-4.0)
    for plant in (acrobot, touching, jd.models.DoublePendulum()):
        vis = visualizer_for(plant)
        assert type(vis) is PlanarRigidBodyVisualizer and vis.plane == (0, 2)
    assert type(visualizer_for(jd.models.CartPole())) is jd.viz.CartPoleVisualizer
    assert type(visualizer_for(jd.models.CartPole(), plane="yz")) is PlanarRigidBodyVisualizer
    assert type(visualizer_for(jd.RigidBodySystem.from_urdf(acrobot.source))) is jd.viz.MeshcatVisualizer


# ----- 3-D scenes (MeshCat) -------------------------------------------------------------------

def scene_transforms(commands, prefix):
    """{link: its last 4 x 4 transform} from the set_transform commands of a recorded scene."""
    out = {}
    for c in commands:
        parts = c["path"].split("/")
        if c["type"] == "set_transform" and len(parts) == 4 and parts[2] == prefix:
            out[parts[3]] = np.asarray(c["matrix"]).reshape(4, 4).T  # MeshCat sends column-major
    return out


def robot_packages():
    """The `package_map` of example-robot-data's URDFs (`package://example-robot-data/robots/...`)."""
    import importlib.metadata

    share = importlib.metadata.distribution("example-robot-data").locate_file("cmeel.prefix/share/example-robot-data")
    return {"example-robot-data": str(share)}


def test_meshcat_scene_places_every_link_at_its_frame_pose_with_its_meshes():
    meshcat = pytest.importorskip("meshcat")
    panda = jd.models.Panda()
    recorder = jd.viz.SceneRecorder()
    unmapped = jd.RigidBodySystem.from_urdf(panda.source, welded=("panda_finger_joint1", "panda_finger_joint2"))
    with pytest.raises(jd.multibody.URDFError, match="link 'panda_link0'.*names package 'example-robot-data'; "
                       "pass package_map="):  # package folders are never searched for
        jd.viz.MeshcatVisualizer(unmapped, scene=meshcat.Visualizer(window=jd.viz.SceneRecorder())).draw(
            jnp.zeros(14))
    assert dict(panda.package_map) == robot_packages()  # Panda() gives its own; the visualizer takes it
    vis = jd.viz.MeshcatVisualizer(panda, scene=meshcat.Visualizer(window=recorder))
    assert isinstance(visualizer_for(panda), jd.viz.MeshcatVisualizer)
    assert isinstance(visualizer_for(panda, plane="xz"), PlanarRigidBodyVisualizer)
    assert isinstance(visualizer_for(jd.models.Acrobot()), PlanarRigidBodyVisualizer)  # the notes' plants stay planar
    for q in np.random.default_rng(1).uniform(-1.5, 1.5, (3, 7)):
        vis.draw(jnp.concatenate([jnp.asarray(q), jnp.zeros(7)]))
        placed = scene_transforms(recorder.commands, "panda")
        assert set(placed) == set(panda.tree.frame_names)
        for link, T in placed.items():
            R, p = panda.frame_pose(jnp.asarray(q), link)
            np.testing.assert_allclose(T[:3, :3], R, atol=1e-12)
            np.testing.assert_allclose(T[:3, 3], p, atol=1e-12)
    meshes = [c for c in recorder.commands if c["type"] == "set_object" and "visual" in c["path"]]
    assert len(meshes) == 11 and all(c["object"]["geometries"][0]["format"] == "dae" for c in meshes)
    assert sum(c["type"] == "set_object" for c in recorder.commands) == 11  # the geometry is sent once


def test_meshcat_html_export_is_offline_and_animates_the_skeleton_of_a_bare_urdf(tmp_path):
    import base64

    pytest.importorskip("meshcat")
    import umsgpack

    acrobot = jd.models.Acrobot(l1=1.2, l2=2.1)  # its URDF has no <visual>: spheres and rods
    vis = jd.viz.MeshcatVisualizer(acrobot)
    traj = jd.simulate(acrobot, (0.0, 1.0), jnp.array([1.0, 0.5, 0.0, 0.0]))
    html = vis.save(traj, tmp_path / "acrobot.html", fps=10).read_text()
    assert not re.findall(r"https?://(?!www\.w3\.org/\d{4}/)", html)  # only XML namespace names
    assert not re.search(r"""(src|href)\s*=\s*["']?//""", html)
    commands = [umsgpack.unpackb(base64.b64decode(c)) for c in re.findall(r'^"([A-Za-z0-9+/=]+)",?$', html, re.M)]
    rods = {c["path"]: c["object"]["geometries"][0]["height"] for c in commands
            if c["type"] == "set_object" and "rod" in c["path"]}
    assert sorted(rods.values()) == pytest.approx([1.2, 2.1], abs=1e-12)  # elbow and hand at the link lengths
    animation = commands[-1]
    assert animation["type"] == "set_animation"
    tracks = {a["path"].split("/")[-1]: a["clip"]["tracks"] for a in animation["animations"]}
    position = next(t for t in tracks["lower_link"] if t["name"] == ".position")
    assert len(position["keys"]) == 10  # round(T fps) frames
    k = 7
    q = traj.state(k / 10)[:2]
    np.testing.assert_allclose(position["keys"][k]["value"], acrobot.frame_pose(q, "lower_link")[1], atol=1e-12)


def test_urdf_robot_movies_rendered_by_mujoco_put_links_where_the_camera_sees_them(tmp_path):
    """A URDF robot's 3-D movie (MuJoCo renders its visuals, or here the skeleton of a bare
    URDF, each link placed by frame_pose): the elbow and the hand of the acrobot are drawn (blue)
    at their pinhole projections through the movie's camera (MuJoCo's free camera: lookat,
    distance, azimuth, elevation, fovy 45 degrees), a point beside the arm is not; the .gif
    decodes to round(T fps) frames that match direct renders; the Panda's meshes (.dae) render."""
    pytest.importorskip("meshcat")
    pytest.importorskip("mujoco")
    import imageio.v3 as iio

    acrobot = jd.models.Acrobot()
    vis = jd.viz.MeshcatVisualizer(acrobot, width=320, height=240)
    states = np.array([[0.4, 0.9, 0.0, 0.0], [2.5, -1.0, 0.0, 0.0]])
    images = vis.images(states)
    model, camera = vis._connection["puppet"]
    az, el = np.radians(camera.azimuth), np.radians(camera.elevation)
    forward = np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
    up = np.array([-np.sin(el) * np.cos(az), -np.sin(el) * np.sin(az), np.cos(el)])
    right = np.cross(forward, up)
    eye = np.asarray(camera.lookat) - camera.distance * forward
    focal = (vis.height / 2) / np.tan(np.radians(model.vis.global_.fovy) / 2)

    def pixel(point):
        d = point - eye
        return (vis.height / 2 - focal * (d @ up) / (d @ forward) - 0.5,
                vis.width / 2 + focal * (d @ right) / (d @ forward) - 0.5)

    def blue_near(image, point, radius=2):
        row, col = (int(round(c)) for c in pixel(point))
        patch = image[row - radius: row + radius + 1, col - radius: col + radius + 1].astype(int)
        return bool(np.any(patch[..., 2] - patch[..., 0] > 40))

    for x, image in zip(states, images):
        q = jnp.asarray(x[:2])
        elbow = np.asarray(acrobot.frame_pose(q, "lower_link")[1])
        for point in np.asarray(vis.link_transforms(jnp.asarray(x)))[:, :3, 3]:  # base, elbow, hand
            assert blue_near(image, point), point
        beside = elbow + 0.6 * np.cross(elbow / np.linalg.norm(elbow), [0.0, 1.0, 0.0])
        assert not blue_near(image, beside)
    traj = jd.simulate(acrobot, (0.0, 0.5), jnp.asarray(states[0]))
    frames = iio.imread(vis.save(traj, tmp_path / "acrobot.gif", fps=10), index=None)
    assert frames.shape[:3] == (5, 240, 320)
    direct = vis.images(np.asarray(traj.state(jnp.arange(5) / 10)))
    assert np.mean(np.abs(frames[3][..., :3].astype(float) - direct[3])) < 8  # the GIF's palette
    panda = jd.models.Panda()
    robot = jd.viz.MeshcatVisualizer(panda, width=160, height=120, package_map=robot_packages()).images(
        jnp.concatenate([panda.tree.neutral_configuration(), jnp.zeros(7)])[None])[0]
    assert robot.std() > 10  # meshes on the floor, not an empty frame


def test_meshcat_draws_each_active_contact_as_an_arrow_of_its_force(tmp_path):
    """A ball resting on the ground: an arrow from the contact point straight up, |f| /
    newtons_per_meter long (f = m g at rest), in a drawn scene and in a saved animation, whose
    frames follow the contact results of a dropped ball (hidden in flight); a robot's name
    stays text in the page."""
    import base64

    meshcat = pytest.importorskip("meshcat")
    import umsgpack
    from jaxdrake.multibody import ContactMaterial

    urdf = (pathlib.Path(__file__).parent / "data/contact_ball.urdf").read_text()
    (tmp_path / "ball.urdf").write_text(urdf.replace('name="contact_ball"', 'name="&lt;/title&gt;&lt;script&gt;x"'))
    ball = jd.RigidBodySystem.from_urdf(tmp_path / "ball.urdf", floating_base=True, contact=True).with_ground(
        material=ContactMaterial(point_contact_stiffness=1e6, hunt_crossley_dissipation=50.0))
    recorder = jd.viz.SceneRecorder()
    vis = jd.viz.MeshcatVisualizer(ball, scene=meshcat.Visualizer(window=recorder), contact_forces=True,
                                   newtons_per_meter=50.0)
    m, g, k = 2.0, 9.81, 3e4 * 1e6 / (3e4 + 1e6)  # the ball's and the ground's stiffness in series
    resting = jnp.array([0.0, 0.0, 0.1 - m * g / k, 0, 0, 0, 1, 0, 0, 0, 0, 0, 0])
    vis.draw(resting)
    arrow = "/meshcat/contact_forces/</title><script>x/0"
    last = {}
    for c in recorder.commands:
        last[(c["type"], c["path"])] = c
    assert last[("set_property", arrow)]["value"] is True
    placed = np.asarray(last[("set_transform", arrow)]["matrix"]).reshape(4, 4).T
    np.testing.assert_allclose(placed[:3, 3], [0.0, 0.0, -m * g / k / 2], atol=1e-12)  # C, between the surfaces
    np.testing.assert_allclose(placed[:3, 1], [0.0, 0.0, 1.0], atol=1e-12)  # up: the ground's push on the ball
    shaft = np.asarray(last[("set_transform", arrow + "/shaft")]["matrix"]).reshape(4, 4).T
    np.testing.assert_allclose(shaft[1, 1], m * g / 50.0, rtol=1e-9)
    head = np.asarray(last[("set_transform", arrow + "/head")]["matrix"]).reshape(4, 4).T
    np.testing.assert_allclose(head[1, 3], m * g / 50.0, rtol=1e-9)
    vis.draw(resting.at[2].set(0.5))
    assert recorder.commands[-1] == {"type": "set_property", "path": arrow, "property": "visible", "value": False}

    traj = jd.simulate(ball, (0.0, 0.5), resting.at[2].set(0.15), solver="rk4", dt=1e-3)  # falls 5 cm, lands
    page = vis.save(traj, tmp_path / "ball.html", fps=20).read_text()
    assert "<script>x" not in page and "&lt;/title&gt;&lt;script&gt;x" in page
    commands = [umsgpack.unpackb(base64.b64decode(c)) for c in re.findall(r'^"([A-Za-z0-9+/=]+)",?$', page, re.M)]
    clips = {a["path"]: {t["name"]: t["keys"] for t in a["clip"]["tracks"]} for a in commands[-1]["animations"]}
    visible = [key["value"] for key in clips[arrow][".visible"]]
    lengths = [key["value"][1] for key in clips[arrow + "/shaft"][".scale"]]
    assert len(visible) == 10 and not visible[0] and any(visible)
    results = jax.jit(lambda ts: jax.vmap(ball.contact_results)(traj.state(ts)))(jnp.arange(10) / 20)
    forces = np.linalg.norm(np.asarray(results.force[:, 0]), axis=1)
    np.testing.assert_array_equal(visible, np.asarray(results.active[:, 0]) & (forces > 0.01))
    np.testing.assert_allclose(np.where(visible, lengths, 0.0), np.where(visible, forces / 50.0, 0.0), rtol=1e-9)


def _listening(pid):
    """The (ip, port) pairs process `pid` listens on (TCP)."""
    import psutil

    return {(c.laddr.ip, c.laddr.port) for c in psutil.Process(pid).net_connections(kind="inet")
            if c.status == psutil.CONN_LISTEN}


def test_the_live_meshcat_server_listens_on_127_0_0_1_only_and_stops_with_close():
    pytest.importorskip("meshcat")
    pytest.importorskip("psutil")
    vis = jd.viz.MeshcatVisualizer(jd.models.Acrobot())
    url = vis.url()
    server = vis._connection["server"]
    sockets = _listening(server.pid)
    assert len(sockets) == 2 and {ip for ip, _ in sockets} == {"127.0.0.1"}, sockets  # ZeroMQ and the web page
    assert url.startswith("http://127.0.0.1:") and int(url.split(":")[2].split("/")[0]) in {p for _, p in sockets}
    vis.close()
    assert server.poll() is not None and vis._connection["server"] is None


def test_the_meshcat_server_ends_when_its_parent_is_killed():
    import signal
    import subprocess
    import sys
    import time

    pytest.importorskip("meshcat")
    psutil = pytest.importorskip("psutil")
    server_file = pathlib.Path(jd.viz.__file__).parent / "_meshcat_server.py"
    parent = subprocess.Popen([sys.executable, "-c", f"""
import importlib.util, time
spec = importlib.util.spec_from_file_location("server", {str(server_file)!r})
server = importlib.util.module_from_spec(spec)
spec.loader.exec_module(server)
print(server.start()[0].pid, flush=True)
time.sleep(60)
"""], stdout=subprocess.PIPE)
    try:
        pid = int(parent.stdout.readline())
        assert {ip for ip, _ in _listening(pid)} == {"127.0.0.1"}
        parent.send_signal(signal.SIGKILL)  # no atexit, no cleanup: only the pipe's end-of-file
        parent.wait()
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline:
            if not psutil.pid_exists(pid) or psutil.Process(pid).status() == psutil.STATUS_ZOMBIE:
                break
            time.sleep(0.05)
        else:
            psutil.Process(pid).kill()
            pytest.fail("the MeshCat server outlived its killed parent")
    finally:
        parent.kill()
        parent.wait()


@pytest.mark.filterwarnings("ignore:Animation was deleted without rendering")
def test_a_movie_widens_its_view_to_hold_the_whole_trajectory():
    """A ball dropped from 12 m (the default view reaches 7 r = 7 m) stays inside every frame:
    the axes hold its apex, the ball's top at 13 m; a pendulum keeps its default view."""
    ball = jd.models.BouncingBall()
    traj = jd.simulate(ball, (0.0, 1.0), jnp.array([12.0, 0.0]))
    animation = visualizer_for(ball).animate(traj, fps=8)
    low, high = animation._fig.axes[0].get_ylim()
    assert high >= 13.0 and low <= -0.5 * ball.r
    pendulum = jd.models.Pendulum()
    vis = visualizer_for(pendulum)
    animation = vis.animate(jd.simulate(pendulum, (0.0, 1.0), jnp.array([1.0, 0.0])), fps=8)
    assert animation._fig.axes[0].get_xlim() == pytest.approx(vis.view()[0])
