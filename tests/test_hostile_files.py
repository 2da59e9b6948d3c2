"""Robot files as an attacker or a careless user writes them: each is refused with a named
error (the element, the file, the remedy), or its text reaches a saved page escaped; and no
file outside the model's folder is opened on the way (Python's "open" audit events).

The corpus: script-tag names, mesh and resource paths that leave the model's folder (absolute,
`../`, `file://`, `http://`, `package://` without or escaping its `package_map` folder,
symbolic links, MuJoCo's `meshdir` / `assetdir` / `texturedir` and `<include>`), XML
entities and DTDs, and physically impossible values.
"""

import contextlib
import html
import os
import pathlib
import sys
import types

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxdrake as jd
from jaxdrake.multibody import MJCFError, URDFError

# ----- what was opened ----------------------------------------------------------------------

_OPENED = None  # a list while recording


def _audit(event, args):
    if event == "open" and _OPENED is not None and isinstance(args[0], (str, bytes, os.PathLike)):
        _OPENED.append(os.path.abspath(os.fsdecode(args[0])))


sys.addaudithook(_audit)  # for the whole session (hooks cannot be removed); records only inside `opened_only`

# what a run opens besides the model: Python and its packages (its import path), the system, caches
_ALLOWED = tuple({pathlib.Path(p).resolve() for p in (sys.prefix, sys.base_prefix, sys.exec_prefix, *filter(None, sys.path),
                                                       "/usr", "/lib", "/proc", "/sys", "/dev", "/etc",
                                                       pathlib.Path.home() / ".cache", pathlib.Path.home() / ".config")})


@contextlib.contextmanager
def opened_only(*folders):
    """Fail if the block opens a file outside `folders` (beside Python, its packages and the
    system): the hostile files' targets lie in a sibling folder of the model's."""
    global _OPENED
    _OPENED = []
    try:
        yield
    finally:
        opened, _OPENED = _OPENED, None
    # and JAX's persistent compilation cache (tests/conftest.py sets one per run): a program that
    # compiles for 0.3 s or more in the block is written there (or read), on a slow machine too
    cache = jax.config.jax_compilation_cache_dir
    allowed = tuple(pathlib.Path(f).resolve() for f in folders) + _ALLOWED + ((pathlib.Path(cache).resolve(),) if cache else ())
    outside = [p for p in opened if not any(pathlib.Path(p).resolve().is_relative_to(a) for a in allowed)]
    assert not outside, f"opened outside the model's folder: {outside}"


# ----- the files ----------------------------------------------------------------------------

STL = """solid s
facet normal 0 0 -1
outer loop
vertex 0 0 0
vertex 0 0.1 0
vertex 0.1 0 0
endloop
endfacet
facet normal 0 -1 0
outer loop
vertex 0 0 0
vertex 0.1 0 0
vertex 0 0 0.1
endloop
endfacet
facet normal -1 0 0
outer loop
vertex 0 0 0
vertex 0 0 0.1
vertex 0 0.1 0
endloop
endfacet
facet normal 1 1 1
outer loop
vertex 0.1 0 0
vertex 0 0.1 0
vertex 0 0 0.1
endloop
endfacet
endsolid s
"""
OBJ = "v 0 0 0\nv 0.1 0 0\nv 0 0.1 0\nv 0 0 0.1\nf 1 3 2\nf 1 2 4\nf 1 4 3\nf 2 3 4\n"
INERTIAL = '<inertial><mass value="1"/><inertia ixx="0.01" iyy="0.01" izz="0.01" ixy="0" ixz="0" iyz="0"/></inertial>'


@pytest.fixture
def place(tmp_path):
    """(model folder, outside folder): the outside one holds secret meshes and files."""
    model, outside = tmp_path / "model", tmp_path / "outside"
    model.mkdir()
    outside.mkdir()
    for name in ("secret.stl", "mesh.stl"):
        (outside / name).write_text(STL)
    (outside / "secret.obj").write_text(OBJ)
    (outside / "secret.txt").write_text("the password")
    (outside / "inc.xml").write_text('<mujoco><asset><mesh name="m" file="secret.obj"/></asset></mujoco>')
    (model / "mesh.stl").write_text(STL)
    (model / "mesh.obj").write_text(OBJ)
    os.symlink(outside / "secret.stl", model / "link.stl")
    os.symlink(outside / "secret.obj", model / "link.obj")
    return model, outside


def urdf(robot="r", link="arm", joint="j", inertial=INERTIAL, joint_body='<axis xyz="0 0 1"/>', geometry="",
         prolog=""):
    """A two-link URDF: `base` and `link` joined by revolute `joint`; `geometry`: elements of `link`."""
    return (f'{prolog}<robot name="{robot}"><link name="base"/><link name="{link}">{inertial}{geometry}</link>'
            f'<joint name="{joint}" type="revolute"><parent link="base"/><child link="{link}"/>{joint_body}</joint>'
            "</robot>")


def write(folder, text, name="robot.urdf"):
    path = pathlib.Path(folder) / name
    path.write_bytes(text.encode() if isinstance(text, str) else text)
    return path


def collision(filename):
    return f'<collision><geometry><mesh filename="{filename}"/></geometry></collision>'


def visual(filename):
    return f'<visual><geometry><mesh filename="{filename}"/></geometry></visual>'


def scene_html(path, package_map=None):
    """The saved MeshCat page of the robot at `path`, holding its neutral pose for 0.2 s."""
    plant = jd.RigidBodySystem.from_urdf(path)
    vis = jd.viz.MeshcatVisualizer(plant, package_map=package_map)
    held = types.SimpleNamespace(t0=0.0, t_final=0.2, system=plant,  # a trajectory's interface, no simulation
                                 state=lambda t: jnp.zeros((len(t), plant.num_continuous_states)))
    return vis.save(held, path.parent / "scene.html", fps=10).read_text()


# ----- names: escaped in a saved page --------------------------------------------------------

SCRIPT = "</title><script>alert(1)</script><title>"
NAMES = {  # case -> (the name's place, the name)
    "robot name": ("robot", SCRIPT),
    "link name": ("link", SCRIPT),
    "joint name": ("joint", SCRIPT),
    "material name": ("material", SCRIPT),
    "robot name, an attribute breaker": ("robot", 'x" onload="alert(1)'),
}


@pytest.mark.parametrize("case", list(NAMES))
def test_names_reach_a_saved_scene_only_as_text(case, place):
    pytest.importorskip("meshcat")
    model, _ = place
    where, name = NAMES[case]
    written = html.escape(name)  # in the URDF as XML text: the parsed name is the hostile one
    fields = {"geometry": '<visual><geometry><box size="0.1 0.1 0.1"/></geometry>'
                          f'<material name="{written}"><color rgba="1 0 0 1"/></material></visual>'}
    if where != "material":
        fields = {where: written}
    path = write(model, urdf(**fields))
    with opened_only(model):
        page = scene_html(path)
    assert "<script>alert" not in page and 'onload="alert' not in page
    assert page.count("<title>") == 1 and page.count("</title>") == 1
    if where == "robot":
        assert f"<title>{html.escape(name)}</title>" in page


# ----- paths: only inside the model's folder or a package_map folder --------------------------

PATHS = {  # filename (with {outside} for the outside folder) -> what the error says
    "absolute path": ("{outside}/secret.stl", "is not a path relative to the model's folder.*move the file into"),
    "../ path": ("../outside/secret.stl", "outside the model's folder.*move the file into the folder"),
    "file:// URI": ("file://{outside}/secret.stl", "is not a path relative.*URIs such as file://"),
    "http:// URI": ("http://127.0.0.1:9/secret.stl", "is not a path relative.*URIs such as file:// or http://"),
    "package:// without package_map": ("package://outside/secret.stl",
                                       "names package 'outside'; pass package_map=.*never searched for"),
    "package:// escaping its folder": ("package://pkg/../../outside/secret.stl",
                                       "outside the folder of package 'pkg'.*pass its package's folder"),
    "symbolic link out of the folder": ("link.stl", "resolves to .*outside.*a symbolic link out of it does not count"),
}


@pytest.mark.parametrize("case", list(PATHS))
def test_collision_meshes_outside_the_model_folder_are_refused(case, place):
    model, outside = place
    filename, message = PATHS[case]
    path = write(model, urdf(geometry=collision(filename.format(outside=outside))))
    (model / "pkg").mkdir()
    with opened_only(model), pytest.raises(URDFError, match=f"link 'arm'.*<mesh>.*{message}"):
        jd.RigidBodySystem.from_urdf(path, contact=True, package_map={"pkg": model / "pkg"})


@pytest.mark.parametrize("case", list(PATHS))
def test_visual_meshes_outside_the_model_folder_are_refused(case, place):
    pytest.importorskip("meshcat")
    model, outside = place
    filename, message = PATHS[case]
    path = write(model, urdf(geometry=visual(filename.format(outside=outside))))
    (model / "pkg").mkdir()
    plant = jd.RigidBodySystem.from_urdf(path)
    recorder = jd.viz.SceneRecorder()
    import meshcat

    vis = jd.viz.MeshcatVisualizer(plant, scene=meshcat.Visualizer(window=recorder), package_map={"pkg": model / "pkg"})
    with opened_only(model), pytest.raises(URDFError, match=f"link 'arm': <visual> <mesh>: .*{message}"):
        vis.draw(jnp.zeros(2))
    assert not recorder.commands  # nothing sent


def test_package_meshes_are_read_from_the_named_folder_only(place, tmp_path):
    """The positive control: `package://pkg/...` with package_map reads that folder's mesh."""
    pytest.importorskip("meshcat")
    model, outside = place
    package = tmp_path / "pkg"
    package.mkdir()
    (package / "part.stl").write_text(STL)
    path = write(model, urdf(geometry=visual("package://pkg/part.stl") + collision("package://pkg/part.stl")))
    with opened_only(model, package):
        plant = jd.RigidBodySystem.from_urdf(path, contact=True, package_map={"pkg": package})
        recorder = jd.viz.SceneRecorder()
        import meshcat

        jd.viz.MeshcatVisualizer(plant, scene=meshcat.Visualizer(window=recorder), package_map={"pkg": package}).draw(
            jnp.zeros(2))
    assert any(c["type"] == "set_object" and c["object"]["geometries"][0]["format"] == "stl" for c in recorder.commands)


def test_a_movie_reads_meshes_by_the_same_rule(place):
    pytest.importorskip("meshcat")
    pytest.importorskip("mujoco")
    model, outside = place
    path = write(model, urdf(geometry=visual("link.obj")))
    vis = jd.viz.MeshcatVisualizer(jd.RigidBodySystem.from_urdf(path), width=64, height=48)
    with opened_only(model), pytest.raises(URDFError, match="link 'arm': <visual> <mesh>: 'link.obj' resolves to"):
        vis.images(np.zeros((1, 2)))


# ----- MJCF: MuJoCo's file attributes, checked before MuJoCo reads them ------------------------

BODY = '<worldbody><body><joint name="j"/><geom type="mesh" mesh="m"/></body></worldbody>'
MJCF = {  # model text (with {outside}) -> what the error says
    "mesh file, absolute": (f'<mujoco><asset><mesh name="m" file="{{outside}}/secret.obj"/></asset>{BODY}</mujoco>',
                            r"<mesh name='m' file>: .*is not a path relative"),
    "mesh file, ../": (f'<mujoco><asset><mesh name="m" file="../outside/secret.obj"/></asset>{BODY}</mujoco>',
                       r"<mesh name='m' file>: .*outside the model's folder"),
    "mesh file, symbolic link": (f'<mujoco><asset><mesh name="m" file="link.obj"/></asset>{BODY}</mujoco>',
                                 r"<mesh name='m' file>: 'link.obj' resolves to .*outside"),
    "compiler meshdir, absolute": ('<mujoco><compiler meshdir="{outside}"/><asset><mesh name="m" file="secret.obj"/>'
                                   f'</asset>{BODY}</mujoco>', r"<compiler meshdir>: .*is not a path relative"),
    "compiler meshdir, ../": ('<mujoco><compiler meshdir="../outside"/><asset><mesh name="m" file="secret.obj"/>'
                              f'</asset>{BODY}</mujoco>', r"<compiler meshdir>: .*outside the model's folder"),
    "compiler assetdir, ../": ('<mujoco><compiler assetdir="../outside"/><asset><mesh name="m" file="secret.obj"/>'
                               f'</asset>{BODY}</mujoco>', r"<compiler assetdir>: .*outside the model's folder"),
    "texture file under texturedir": ('<mujoco><compiler texturedir="textures"/><asset>'
                                      '<texture name="t" type="2d" file="../../outside/secret.png"/></asset>'
                                      '<worldbody><body><joint/><geom size=".1"/></body></worldbody></mujoco>',
                                      r"<texture name='t' file>: .*outside the model's folder"),
    "cube texture face": ('<mujoco><asset><texture name="t" type="cube" fileright="/etc/hostname"/></asset>'
                          '<worldbody><body><joint/><geom size=".1"/></body></worldbody></mujoco>',
                          r"<texture name='t' fileright>: '/etc/hostname' is not a path relative"),
    "include, ../": (f'<mujoco><include file="../outside/inc.xml"/>{BODY}</mujoco>',
                     r"<include>: .*outside the model's folder"),
    "include of a file that escapes": (f'<mujoco><include file="inner.xml"/>{BODY}</mujoco>',
                                       r"inner.xml: <mesh name='m' file>: .*outside the model's folder"),
    "DOCTYPE with an entity": ('<?xml version="1.0"?><!DOCTYPE m [<!ENTITY e SYSTEM "file://{outside}/secret.txt">]>'
                               '<mujoco model="&e;"><worldbody><body><joint/><geom size=".1"/></body></worldbody>'
                               "</mujoco>", "DOCTYPE / ENTITY declarations are not accepted"),
}


@pytest.mark.parametrize("case", list(MJCF))
@pytest.mark.parametrize("reader", ["from_mjcf", "MujocoSystem.from_xml"])
def test_mjcf_files_outside_the_model_folder_are_refused_before_mujoco_reads_them(case, reader, place):
    pytest.importorskip("mujoco")
    model, outside = place
    text, message = MJCF[case]
    write(model, '<mujoco><asset><mesh name="m" file="../outside/secret.obj"/></asset></mujoco>', "inner.xml")
    path = write(model, text.format(outside=outside), "model.xml")
    load = jd.RigidBodySystem.from_mjcf if reader == "from_mjcf" else jd.MujocoSystem.from_xml
    with opened_only(model), pytest.raises(MJCFError, match=message):
        load(path)


def test_mjcf_text_reads_files_only_inside_the_working_directory_or_assets(place, monkeypatch):
    pytest.importorskip("mujoco")
    model, outside = place
    monkeypatch.chdir(model)
    text = f'<mujoco><asset><mesh name="m" file="{outside}/secret.obj"/></asset>{BODY}</mujoco>'
    with opened_only(model), pytest.raises(MJCFError, match=r"\(MJCF text\): <mesh name=.m. file>: .*not a path relative"):
        jd.MujocoSystem.from_xml(text)
    inside = f'<mujoco><asset><mesh name="m" file="mesh.obj"/></asset>{BODY}</mujoco>'
    assert jd.MujocoSystem.from_xml(inside).mj_model.nmesh == 1  # the working directory's own files are read
    assert jd.MujocoSystem.from_xml(text, assets={f"{outside}/secret.obj": OBJ.encode()}).mj_model.nmesh == 1


def test_a_urdf_for_mujoco_cannot_move_its_meshdir_out(place):
    pytest.importorskip("mujoco")
    model, outside = place
    path = write(model, urdf(geometry=visual("secret.obj")).replace(
        "</robot>", '<mujoco><compiler meshdir="../outside"/></mujoco></robot>'))
    with opened_only(model), pytest.raises(MJCFError, match=r"robot.urdf: <compiler meshdir>: .*outside"):
        jd.MujocoSystem.from_xml(path)


# ----- XML: no DTD, no entity ----------------------------------------------------------------

LAUGHS = "".join(f'<!ENTITY l{i} "{f"&l{i - 1};" * 10 if i else "lol"}">' for i in range(10))
XML = {
    "billion laughs": f'<?xml version="1.0"?><!DOCTYPE robot [{LAUGHS}]>' + urdf(robot="&l9;"),
    "external entity, a file": '<!DOCTYPE robot [<!ENTITY s SYSTEM "file://{outside}/secret.txt">]>' + urdf(robot="&s;"),
    "external entity, the network": '<!DOCTYPE robot [<!ENTITY s SYSTEM "http://127.0.0.1:9/x">]>' + urdf(robot="&s;"),
    "external DTD": '<!DOCTYPE robot SYSTEM "file://{outside}/secret.txt">' + urdf(),
    "parameter entity": '<!DOCTYPE robot [<!ENTITY % p SYSTEM "file://{outside}/secret.txt"> %p;]>' + urdf(),
    "a DOCTYPE in UTF-16": ('<?xml version="1.0" encoding="UTF-16"?><!DOCTYPE robot [<!ENTITY s "x">]>'
                            + urdf(robot="&s;")),
}


@pytest.mark.parametrize("case", list(XML))
@pytest.mark.parametrize("reader", ["from_urdf", "contact", "mimic", "MeshcatVisualizer"])
def test_xml_declarations_are_refused_by_every_reader(case, reader, place):
    model, outside = place
    text = XML[case].replace("{outside}", str(outside))
    path = write(model, text.encode("utf-16") if "UTF-16" in case else text)
    with opened_only(model), pytest.raises(URDFError, match="DOCTYPE / ENTITY declarations are not accepted.*"
                                                            "remove the DOCTYPE"):
        if reader == "from_urdf":
            jd.multibody.tree_from_urdf(path)
        elif reader == "contact":
            from jaxdrake.multibody._urdf_collision import read_urdf_collisions

            read_urdf_collisions(path)
        elif reader == "mimic":
            jd.multibody.urdf_mimic_joints(path)
        else:
            pytest.importorskip("meshcat")
            plant = jd.RigidBodySystem.from_urdf(write(model, urdf(), "plain.urdf"))
            jd.viz.MeshcatVisualizer(plant, urdf=path, scene=_recording_scene()).draw(jnp.zeros(2))


def _recording_scene():
    import meshcat

    return meshcat.Visualizer(window=jd.viz.SceneRecorder())


def test_a_collada_mesh_with_an_external_entity_is_refused(place):
    pytest.importorskip("meshcat")
    model, outside = place
    write(model, f'<?xml version="1.0"?><!DOCTYPE c [<!ENTITY s SYSTEM "file://{outside}/secret.txt">]>'
                 '<COLLADA xmlns="http://www.collada.org/2005/11/COLLADASchema" version="1.4.1">&s;</COLLADA>', "part.dae")
    path = write(model, urdf(geometry=visual("part.dae")))
    vis = jd.viz.MeshcatVisualizer(jd.RigidBodySystem.from_urdf(path), scene=_recording_scene())
    with opened_only(model), pytest.raises(URDFError, match="part.dae: XML DOCTYPE / ENTITY declarations"):
        vis.draw(jnp.zeros(2))


# ----- physically impossible values ----------------------------------------------------------

def inertial(mass="1", ixx="0.01", iyy="0.01", izz="0.01", ixy="0"):
    return (f'<inertial><mass value="{mass}"/><inertia ixx="{ixx}" iyy="{iyy}" izz="{izz}" ixy="{ixy}" ixz="0" '
            'iyz="0"/></inertial>')


PHYSICS = {  # urdf() fields -> what the error says
    "negative mass": (dict(inertial=inertial(mass="-1")), r"link 'arm' has mass -1.0; a mass is a finite number >= 0.*"
                                                          r"fix its <inertial>"),
    "NaN mass": (dict(inertial=inertial(mass="nan")), r"link 'arm' has mass nan"),
    "negative moment": (dict(inertial=inertial(iyy="-0.01")), r"link 'arm' has an inertia that is not positive "
                                                              r"semi-definite.*fix its <inertial>"),
    "NaN moment": (dict(inertial=inertial(izz="nan")), r"link 'arm' has an inertia with non-finite entries"),
    "indefinite products": (dict(inertial=inertial(ixy="0.02")), r"link 'arm' has an inertia that is not positive"),
    "triangle inequality": (dict(inertial=inertial(ixx="0.01", iyy="0.01", izz="0.03")),
                            r"rigid body of link 'arm'.*break the triangle inequality.*I3 = 0.03.*fix the inertias"),
    "negative damping": (dict(joint_body='<axis xyz="0 0 1"/><dynamics damping="-0.5"/>'),
                         r"joint 'j' has damping -0.5; it must be a finite number >= 0.*a URDF.s <dynamics>"),
    "negative friction": (dict(joint_body='<axis xyz="0 0 1"/><dynamics friction="-1"/>'),
                          r"joint 'j' has friction -1.0"),
    "NaN damping": (dict(joint_body='<axis xyz="0 0 1"/><dynamics damping="nan"/>'), r"joint 'j' has damping nan"),
    "lower above upper": (dict(joint_body='<axis xyz="0 0 1"/><limit lower="1" upper="-1" effort="1" velocity="1"/>'),
                          r"joint 'j' has lower limit 1.0 above upper limit -1.0.*swap them"),
    "NaN limit": (dict(joint_body='<axis xyz="0 0 1"/><limit lower="nan" upper="1" effort="1" velocity="1"/>'),
                  r"joint 'j' has lower limit nan"),
    "negative effort": (dict(joint_body='<axis xyz="0 0 1"/><limit lower="-1" upper="1" effort="-2" velocity="1"/>'),
                        r"joint 'j' has effort limit -2.0; it must be >= 0"),
    "NaN origin": (dict(joint_body='<origin xyz="nan 0 0"/><axis xyz="0 0 1"/>'),
                   r"joint 'j': <origin xyz='nan 0 0'> is not 3 numbers"),
    "infinite axis": (dict(joint_body='<axis xyz="inf 0 0"/>'), r"joint 'j': <axis xyz='inf 0 0'> is not 3 numbers"),
}


@pytest.mark.parametrize("case", list(PHYSICS))
def test_physically_impossible_urdfs_are_refused_at_construction(case, place):
    model, _ = place
    fields, message = PHYSICS[case]
    path = write(model, urdf(**fields))
    with opened_only(model), pytest.raises(URDFError, match=message):
        jd.RigidBodySystem.from_urdf(path)


MJCF_PHYSICS = {
    "negative damping": ('<joint name="j" damping="-1"/>', r"joint 'j' has damping -1.0"),
    "negative frictionloss": ('<joint name="j" frictionloss="-1"/>', r"joint 'j' has friction -1.0"),
}


@pytest.mark.parametrize("case", list(MJCF_PHYSICS))
def test_physically_impossible_mjcf_joints_are_refused_though_mujoco_accepts_them(case, place):
    pytest.importorskip("mujoco")
    model, _ = place
    joint, message = MJCF_PHYSICS[case]
    path = write(model, f'<mujoco><worldbody><body>{joint}<geom size=".1"/></body></worldbody></mujoco>', "m.xml")
    with pytest.raises(MJCFError, match=message):
        jd.RigidBodySystem.from_mjcf(path)
