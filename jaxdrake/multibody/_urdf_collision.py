r"""A URDF's collision geometry, read as Drake's parser reads it.

- `<collision>` elements of every link: `<origin>`, and a `<geometry>` of `<sphere radius>`,
  `<box size>`, `<cylinder radius length>`, `<capsule radius length>` /
  `<drake:capsule radius length>`, or `<mesh filename [scale]>` (a `.obj` / `.stl` reduced
  to its convex hull, as Drake's point contact uses a mesh);
- `<drake:proximity_properties>` inside a `<collision>`: `drake:point_contact_stiffness`,
  `drake:hunt_crossley_dissipation`, `drake:mu_static`, `drake:mu_dynamic` (their `value`);
- `<drake:collision_filter_group name>` with `<drake:member link>` and
  `<drake:ignored_collision_filter_group name>` (no contact between the members of the two
  groups, or within a group that ignores itself);
- joints (not fixed, not floating, parent not the world): their two links do not collide.

Mesh files are read only from inside the URDF's folder, or from the folders given as
`package_map` for `package://NAME/...` names: nothing outside a model's folder is opened
(`_files.resolve_model_file`, the one owner of that rule).
"""

from __future__ import annotations

import dataclasses
import functools
import pathlib

import numpy as np

from ..geometry import Box, Capsule, Convex, Cylinder, GeometryError, Sphere
from ._contact import URDF_DEFAULT_FRICTION, CollisionGeometry, ContactMaterial
from ._files import children_named, local_tag, resolve_model_file
from ._joints import JointType
from ._tree import URDF_JOINT_TYPES, URDFError, _numbers, _origin, read_urdf


@dataclasses.dataclass(frozen=True)
class URDFCollisions:
    """What a URDF says about contact: the geometries and the link pairs that never collide
    (joints and filter groups)."""

    geometries: tuple
    excluded_link_pairs: tuple


def read_urdf_collisions(path, *, package_map=None, mesh_hulls: bool = False,
                         max_hull_vertices: int | None = None) -> URDFCollisions:
    """The URDF's collision geometry (module docstring); `mesh_hulls`: collide a non-convex mesh
    through its convex hull (Drake's point contact does) instead of refusing it;
    `max_hull_vertices`: a mesh's hull simplified to at most this many vertices
    (`Convex.from_points`)."""
    path = pathlib.Path(path)
    root = read_urdf(path)
    read_mesh = functools.partial(Convex.from_mesh_file, require_convex=not mesh_hulls, max_vertices=max_hull_vertices)
    geometries = []
    for link in root.findall("link"):
        name = link.get("name")
        for k, element in enumerate(link.findall("collision")):
            geometries.append(_collision(element, name, k, path, package_map or {}, read_mesh))
    names = [g.name for g in geometries]
    seen = set()
    for i, n in enumerate(names):  # Drake makes repeated names unique per link the same way
        if n in seen:
            geometries[i] = dataclasses.replace(geometries[i], name=f"{n}_{i}")
        seen.add(geometries[i].name)
    excluded = []
    for joint in root.findall("joint"):
        parent, child = joint.find("parent"), joint.find("child")
        kind = URDF_JOINT_TYPES.get(joint.get("type"))
        if kind in (JointType.FIXED, JointType.FLOATING) or parent is None or child is None:
            continue
        if parent.get("link") != "world":
            excluded.append((parent.get("link"), child.get("link")))
    excluded += _filter_group_exclusions(root, path)
    return URDFCollisions(tuple(geometries), tuple(excluded))


def _collision(element, link, index, path, package_map, read_mesh) -> CollisionGeometry:
    name = element.get("name") or f"{link}_collision_{index}"
    where = f"link {link!r}, <collision name={name!r}>"
    R, p = _origin(element.find("origin"), path, where)
    geometry = element.find("geometry")
    shapes = [] if geometry is None else list(geometry)
    if len(shapes) != 1:
        raise URDFError(f"{path}: {where}: a <geometry> needs exactly one shape element, found "
                        f"{[local_tag(s.tag) for s in shapes] or 'none'}")
    shape = _shape(shapes[0], path, where, package_map, read_mesh)
    material = ContactMaterial()
    for properties in children_named(element, "drake:proximity_properties"):
        values = {}
        for item in properties:
            key = local_tag(item.tag).removeprefix("drake:")
            if key in ("point_contact_stiffness", "hunt_crossley_dissipation", "mu_static", "mu_dynamic"):
                values[key] = float(_numbers(item, "value", 1, np.nan, path, where))
        material = ContactMaterial(**values)
    if material.mu_static is None and material.mu_dynamic is None:  # Drake's URDF parser's default
        material = dataclasses.replace(material, mu_static=URDF_DEFAULT_FRICTION[0], mu_dynamic=URDF_DEFAULT_FRICTION[1])
    try:
        material.check(f"{path}: {where}")
    except GeometryError as error:
        raise URDFError(str(error)) from None
    return CollisionGeometry(name=name, link=link, shape=shape, rotation=np.asarray(R), translation=np.asarray(p),
                             material=material)


_REQUIRED = {"sphere": ("radius",), "box": ("size",), "cylinder": ("radius", "length"),
             "capsule": ("radius", "length"), "drake:capsule": ("radius", "length")}


def _shape(element, path, where, package_map, read_mesh):
    kind = local_tag(element.tag)

    def required(attribute, count=1):
        if element.get(attribute) is None and kind in _REQUIRED and attribute in _REQUIRED[kind]:
            raise URDFError(f"{path}: {where}: <{kind}> has no {attribute} attribute (it needs "
                            f"{' and '.join(_REQUIRED[kind])})")
        return _numbers(element, attribute, count, np.nan if count == 1 else [np.nan] * count, path, where)

    number = lambda attribute: float(required(attribute))  # noqa: E731
    try:
        if kind == "sphere":
            return Sphere(number("radius"))
        if kind == "box":
            return Box(*required("size", 3))
        if kind == "cylinder":
            return Cylinder(number("radius"), number("length"))
        if kind in ("capsule", "drake:capsule"):
            return Capsule(number("radius"), number("length"))
        if kind == "mesh":
            scale = element.get("scale")
            scale = (1.0, 1.0, 1.0) if scale is None else tuple(
                np.broadcast_to(_numbers(element, "scale", len(scale.split()), None, path, where), 3))
            mesh = resolve_model_file(element.get("filename"), path, f"{where}: <mesh>", URDFError,
                                      package_map=package_map)
            return read_mesh(mesh, scale)
    except GeometryError as error:
        raise URDFError(f"{path}: {where}: {error}") from None
    raise URDFError(f"{path}: {where}: unsupported collision shape <{kind}>; use a sphere, box, cylinder, "
                    "capsule (<drake:capsule>) or a convex mesh")


def _filter_group_exclusions(root, path):
    groups, ignores = {}, {}
    for group in children_named(root, "drake:collision_filter_group"):
        name = group.get("name")
        if not name:
            raise URDFError(f"{path}: a <drake:collision_filter_group> has no name")
        if group.get("ignore", "false").lower() in ("true", "1"):
            continue
        groups[name] = [m.get("link") for m in children_named(group, "drake:member")]
        ignores[name] = [g.get("name") for g in children_named(group, "drake:ignored_collision_filter_group")]
    pairs = []
    for name, ignored in ignores.items():
        for other in ignored:
            if other not in groups:
                raise URDFError(f"{path}: collision filter group {name!r} ignores group {other!r}, which "
                                "is not defined")
            pairs += [(a, b) for a in groups[name] for b in groups[other] if a != b]
    return pairs
