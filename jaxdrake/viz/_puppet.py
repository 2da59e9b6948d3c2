"""Movies of URDF robots in 3-D, rendered offscreen by MuJoCo.

The robot's `<visual>` elements become a MuJoCo model with no dynamics of its own — a puppet:
each link is a mocap body (a body whose world pose is set directly) holding its visuals as
geoms (boxes, spheres and cylinders as MuJoCo primitives; meshes of any format trimesh reads,
`.dae` included, as MuJoCo meshes), over a checkered floor (at z = 0, or under the robot where
it hangs below its base). A frame places every link at its pose $T_\\ell(q)$ (computed by
jaxdrake, `MeshcatVisualizer.frame_transforms`) and renders (EGL without a display), through a
camera aimed so that what the frames draw fills the image (`aim`).
"""

from __future__ import annotations

import numpy as np

from ._urdf_visuals import SKELETON_COLOR, link_color, skeleton_radii

AZIMUTH, ELEVATION = 135.0, -20.0  # degrees: the camera looks from the front left, a little down
FILL = 0.9  # the drawn robot spans this much of the image's height or width


def _add_visual(mujoco, spec, body, visual, color, mesh_file, name):
    """One URDF <visual> as a geom of `body` (a MuJoCo mesh asset for a mesh, the file given by
    `mesh_file(filename)`), in `color` (RGBA)."""
    import trimesh

    origin = np.eye(4) if visual.origin is None else np.asarray(visual.origin, float)
    quat = np.zeros(4)
    mujoco.mju_mat2Quat(quat, np.ascontiguousarray(origin[:3, :3]).ravel())
    geom = body.add_geom(pos=origin[:3, 3], quat=quat, rgba=color, contype=0,
                         conaffinity=0)
    shape = visual.geometry
    if shape.box is not None:
        geom.type, geom.size = mujoco.mjtGeom.mjGEOM_BOX, np.asarray(shape.box.size, float) / 2
    elif shape.sphere is not None:
        geom.type, geom.size = mujoco.mjtGeom.mjGEOM_SPHERE, [float(shape.sphere.radius), 0, 0]
    elif shape.cylinder is not None:  # along z in both formats; MuJoCo takes the half-length
        geom.type = mujoco.mjtGeom.mjGEOM_CYLINDER
        geom.size = [float(shape.cylinder.radius), float(shape.cylinder.length) / 2, 0]
    elif shape.mesh is not None:
        path = mesh_file(shape.mesh.filename)
        mesh = trimesh.load(path, force="mesh")  # a scene (.dae, .glb) flattened into one mesh
        scale = np.ones(3) if shape.mesh.scale is None else np.broadcast_to(np.asarray(shape.mesh.scale, float), 3)
        spec.add_mesh(name=name, uservert=(np.asarray(mesh.vertices) * scale).ravel(),
                      userface=np.asarray(mesh.faces).ravel())
        geom.type, geom.meshname = mujoco.mjtGeom.mjGEOM_MESH, name
    else:
        raise ValueError(f"a <visual> without geometry ({visual.name})")


def puppet_model(links, visuals, materials, mesh_file, skeleton, neutral):
    """A MuJoCo model with one mocap body per link (in `links` order, the root first), and its
    camera (free, looking from `AZIMUTH`, `ELEVATION`; `render_frames` aims it).

    `visuals`: {link: [URDF <visual>]} (`mesh_file(link, filename)`: a mesh's file); when none has any, `skeleton` ({link: offsets in its
    frame}) gives a sphere per link and a capsule to each attached link (`skeleton_radii`).
    `neutral`: the links' 4x4 world poses at the neutral configuration (the floor goes under
    a robot that hangs below its base there)."""
    from ..mujoco import import_mujoco

    mujoco, _ = import_mujoco()
    spec = mujoco.MjSpec()
    spec.visual.global_.offwidth, spec.visual.global_.offheight = 1920, 1080
    spec.visual.headlight.ambient, spec.visual.headlight.diffuse = [0.4, 0.4, 0.4], [0.6, 0.6, 0.6]
    spec.add_texture(name="sky", type=mujoco.mjtTexture.mjTEXTURE_SKYBOX, builtin=mujoco.mjtBuiltin.mjBUILTIN_GRADIENT,
                     width=64, height=64, rgb1=[0.95, 0.95, 0.97], rgb2=[0.75, 0.78, 0.82])
    spec.add_texture(name="grid", type=mujoco.mjtTexture.mjTEXTURE_2D, builtin=mujoco.mjtBuiltin.mjBUILTIN_CHECKER,
                     width=256, height=256, rgb1=[0.93, 0.91, 0.86], rgb2=[0.84, 0.81, 0.74])
    spec.add_material(name="grid", texrepeat=[16, 16], textures=["", "grid"], emission=0.4)  # a light floor
    lowest = float(np.min(np.asarray(neutral)[:, 2, 3]))
    floor = 0.0 if lowest >= -1e-9 else lowest - 0.1  # under a robot that hangs below its base
    world = spec.worldbody
    world.add_light(pos=[0, -1, floor + 4], dir=[0, 0.25, -1], diffuse=[0.5, 0.5, 0.5], castshadow=True)
    world.add_geom(type=mujoco.mjtGeom.mjGEOM_PLANE, pos=[0, 0, floor], size=[5, 5, 0.1], material="grid",
                   contype=0, conaffinity=0)
    drawn = any(visuals.get(link) for link in links)
    joint_radius, rod_radius = skeleton_radii(skeleton)
    for i, link in enumerate(links):
        body = world.add_body(name=f"link{i}", mocap=True)
        if drawn:
            for k, visual in enumerate(visuals.get(link, [])):
                _add_visual(mujoco, spec, body, visual, link_color(visual, materials, i),
                            lambda filename: mesh_file(link, filename),
                            f"mesh{i}_{k}")
            continue
        body.add_geom(type=mujoco.mjtGeom.mjGEOM_SPHERE, size=[joint_radius, 0, 0], rgba=SKELETON_COLOR,
                      contype=0, conaffinity=0)
        for offset in skeleton.get(link, []):
            body.add_geom(type=mujoco.mjtGeom.mjGEOM_CAPSULE, fromto=[0, 0, 0, *offset], size=[rod_radius, 0, 0],
                          rgba=SKELETON_COLOR, contype=0, conaffinity=0)
    camera = mujoco.MjvCamera()
    camera.azimuth, camera.elevation = AZIMUTH, ELEVATION
    return spec.compile(), camera


def place(mujoco, model, data, poses):
    """Put the puppet's links at `poses` (links, 4, 4) and compute its geoms' world poses."""
    data.mocap_pos[:] = poses[:, :3, 3]
    for k, pose in enumerate(poses):
        mujoco.mju_mat2Quat(data.mocap_quat[k], np.ascontiguousarray(pose[:3, :3]).ravel())
    mujoco.mj_kinematics(model, data)


def drawn_points(mujoco, model, data, transforms) -> np.ndarray:
    """The corners of the bounding boxes of the robot's geoms (MuJoCo's `geom_aabb`, centre and
    half-sizes in each geom's frame) with its links at each of `transforms` (n, links, 4, 4):
    (n, 8 x robot geoms, 3) in the world frame. The floor is not the robot's."""
    robot = np.flatnonzero(model.body_mocapid[model.geom_bodyid] >= 0)
    signs = np.array([[i, j, k] for i in (-1, 1) for j in (-1, 1) for k in (-1, 1)], float)
    box = model.geom_aabb[robot]
    corners = box[:, None, :3] + signs * box[:, None, 3:]  # (g, 8, 3), geom frames
    points = []
    for poses in transforms:
        place(mujoco, model, data, poses)
        rotations = data.geom_xmat[robot].reshape(-1, 3, 3)
        points.append((np.einsum("gij,gcj->gci", rotations, corners) + data.geom_xpos[robot][:, None]).reshape(-1, 3))
    return np.stack(points)


def aim(camera, points, fovy: float, near: float, height: int, width: int) -> np.ndarray:
    """Aim MuJoCo's free `camera` (its azimuth and elevation kept) at `points` (m, 3): the least
    `distance` at which every point is in view (and at least `near` in front of the eye), the
    outermost spanning `FILL` of the image's height or width, with `lookat` placed so that they
    are centred in the image. Returns `lookat`.

    With the camera's forward, up and right unit vectors f, u, r (from azimuth a and elevation
    e: f = (cos e cos a, cos e sin a, sin e)), a point p at offset d = p - lookat is seen at
    depth D + d.f from an eye at distance D, at tangents (d.u, d.r) / (D + d.f) from the line of
    sight; it is in view where |d.u| <= (D + d.f) tan_y and |d.r| <= (D + d.f) tan_x, with
    tan_y = FILL tan(fovy/2) and tan_x = tan_y width/height, so
    D = max over the points of max(|d.u| / tan_y, |d.r| / tan_x) - d.f. Starting from the
    centre of their bounding box, `lookat` moves across the line of sight by D times the middle
    of their tangents' range, three times (perspective makes it a fixed point, not a formula)."""
    a, e = np.radians(camera.azimuth), np.radians(camera.elevation)
    forward = np.array([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)])
    up = np.array([-np.sin(e) * np.cos(a), -np.sin(e) * np.sin(a), np.cos(e)])
    right = np.cross(forward, up)
    tan_y = FILL * np.tan(np.radians(fovy) / 2)
    tan_x = tan_y * width / height
    lookat = (points.min(axis=0) + points.max(axis=0)) / 2
    for recentre in range(4):
        d = points - lookat
        vertical, across, depth = d @ up, d @ right, d @ forward
        distance = max(np.max(np.maximum(np.abs(vertical) / tan_y, np.abs(across) / tan_x) - depth),
                       np.max(near - depth))
        if recentre == 3:
            break
        seen_up, seen_right = vertical / (distance + depth), across / (distance + depth)
        lookat = lookat + distance * ((seen_up.max() + seen_up.min()) / 2 * up
                                      + (seen_right.max() + seen_right.min()) / 2 * right)
    camera.lookat[:], camera.distance = lookat, float(distance)
    return lookat


def render_frames(model, camera, transforms, height: int, width: int, follow: bool = False) -> np.ndarray:
    """RGB images (n, height, width, 3) of the puppet with its links at `transforms` (n, links, 4, 4),
    through `camera` aimed at everything the frames draw (`aim`): one view for the whole movie,
    or, where it must `follow` a floating robot, a view that moves with its root link."""
    from ..mujoco import import_mujoco, mujoco_renderer

    mujoco, _ = import_mujoco()
    transforms = np.asarray(transforms, float)
    data = mujoco.MjData(model)
    roots = transforms[:, 0, :3, 3] if follow else np.zeros((len(transforms), 3))
    points = drawn_points(mujoco, model, data, transforms) - roots[:, None]
    near = 2 * model.vis.map.znear * model.stat.extent  # MuJoCo clips what is nearer than half this
    lookat = aim(camera, points.reshape(-1, 3), model.vis.global_.fovy, near, height, width)
    frames = []
    with mujoco_renderer(model, height, width) as scene:
        for poses, root in zip(transforms, roots):
            place(mujoco, model, data, poses)
            camera.lookat[:] = lookat + root
            scene.update_scene(data, camera)
            frames.append(scene.render().copy())
    return np.stack(frames)
