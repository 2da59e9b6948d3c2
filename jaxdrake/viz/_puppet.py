"""Movies of URDF robots in 3-D, rendered offscreen by MuJoCo.

The robot's `<visual>` elements become a MuJoCo model with no dynamics of its own — a puppet:
each link is a mocap body (a body whose world pose is set directly) holding its visuals as
geoms (boxes, spheres and cylinders as MuJoCo primitives; meshes of any format trimesh reads,
`.dae` included, as MuJoCo meshes), over a checkered floor (at z = 0, or under the robot where
it hangs below its base), with a camera that looks at the robot's neutral pose. A frame places
every link at its pose $T_\\ell(q)$ (computed by jaxdrake, `MeshcatVisualizer.frame_transforms`)
and renders (EGL without a display).
"""

from __future__ import annotations

import numpy as np

from ._urdf_visuals import link_color


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


def puppet_model(links, visuals, materials, mesh_file, skeleton, neutral, floating: bool):
    """A MuJoCo model with one mocap body per link (in `links` order, the root first), and its
    camera.

    `visuals`: {link: [URDF <visual>]} (`mesh_file(link, filename)`: a mesh's file); when none has any, `skeleton` ({link: offsets in its
    frame}) gives a sphere per link and a capsule to each attached link. `neutral`: the links'
    4x4 world poses at the neutral configuration. The camera frames the reach of a fixed-base
    robot (the sphere about its root through its farthest link at the neutral pose, above
    the floor), or follows the root of a `floating` one at the distance that frames its pose."""
    from ..multibody import import_mujoco

    mujoco, _ = import_mujoco()
    spec = mujoco.MjSpec()
    spec.visual.global_.offwidth, spec.visual.global_.offheight = 1920, 1080
    spec.visual.headlight.ambient, spec.visual.headlight.diffuse = [0.4, 0.4, 0.4], [0.6, 0.6, 0.6]
    spec.add_texture(name="sky", type=mujoco.mjtTexture.mjTEXTURE_SKYBOX, builtin=mujoco.mjtBuiltin.mjBUILTIN_GRADIENT,
                     width=64, height=64, rgb1=[0.95, 0.95, 0.97], rgb2=[0.75, 0.78, 0.82])
    spec.add_texture(name="grid", type=mujoco.mjtTexture.mjTEXTURE_2D, builtin=mujoco.mjtBuiltin.mjBUILTIN_CHECKER,
                     width=256, height=256, rgb1=[0.85, 0.85, 0.87], rgb2=[0.72, 0.72, 0.75])
    spec.add_material(name="grid", texrepeat=[16, 16], textures=["", "grid"])
    origins = np.asarray(neutral)[:, :3, 3]
    low, high = origins.min(axis=0), origins.max(axis=0)
    floor = 0.0 if low[2] >= -1e-9 else low[2] - 0.1  # under a robot that hangs below its base
    world = spec.worldbody
    world.add_light(pos=[0, -1, floor + 4], dir=[0, 0.25, -1], diffuse=[0.5, 0.5, 0.5], castshadow=True)
    world.add_geom(type=mujoco.mjtGeom.mjGEOM_PLANE, pos=[0, 0, floor], size=[5, 5, 0.1], material="grid",
                   contype=0, conaffinity=0)
    drawn = any(visuals.get(link) for link in links)
    for i, link in enumerate(links):
        body = world.add_body(name=f"link{i}", mocap=True)
        if drawn:
            for k, visual in enumerate(visuals.get(link, [])):
                _add_visual(mujoco, spec, body, visual, link_color(visual, materials, i),
                            lambda filename: mesh_file(link, filename),
                            f"mesh{i}_{k}")
            continue
        body.add_geom(type=mujoco.mjtGeom.mjGEOM_SPHERE, size=[0.03, 0, 0], rgba=[0.3, 0.45, 0.69, 1],
                      contype=0, conaffinity=0)
        for offset in skeleton.get(link, []):
            body.add_geom(type=mujoco.mjtGeom.mjGEOM_CAPSULE, fromto=[0, 0, 0, *offset], size=[0.015, 0, 0],
                          rgba=[0.3, 0.45, 0.69, 1], contype=0, conaffinity=0)
    model = spec.compile()
    camera = mujoco.MjvCamera()
    camera.azimuth, camera.elevation = 135.0, -20.0
    half_view = np.tan(np.radians(model.vis.global_.fovy) / 2)
    if floating:
        camera.type, camera.trackbodyid = mujoco.mjtCamera.mjCAMERA_TRACKING, model.body("link0").id
        camera.lookat[:] = (low + high) / 2
        camera.distance = max(0.6 * float(np.linalg.norm(high - low)) / half_view, 0.5)
        return model, camera
    root = origins[0]
    reach = 1.1 * max(float(np.max(np.linalg.norm(origins - root, axis=1))), 0.1)  # 10% for the geometry
    bottom, top = max(root[2] - reach, floor), root[2] + reach
    camera.lookat[:] = [root[0], root[1], (bottom + top) / 2]
    camera.distance = 0.8 * max(reach, (top - bottom) / 2) / half_view  # arms seldom fill the whole sphere
    return model, camera


def render_frames(model, camera, transforms, height: int, width: int) -> np.ndarray:
    """RGB images (n, height, width, 3) of the puppet with its links at `transforms` (n, links, 4, 4)."""
    from ..multibody import import_mujoco, mujoco_renderer

    mujoco, _ = import_mujoco()
    data = mujoco.MjData(model)
    frames = []
    with mujoco_renderer(model, height, width) as scene:
        for poses in np.asarray(transforms, float):
            data.mocap_pos[:] = poses[:, :3, 3]
            for k, pose in enumerate(poses):
                mujoco.mju_mat2Quat(data.mocap_quat[k], np.ascontiguousarray(pose[:3, :3]).ravel())
            mujoco.mj_kinematics(model, data)
            scene.update_scene(data, camera)
            frames.append(scene.render().copy())
    return np.stack(frames)
