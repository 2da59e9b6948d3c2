"""3-D frames of URDF robots (MuJoCo renders the MeshCat visualizer's puppet) fill the image with
the robot: measured on the rendered pixels (the robot is the coloured part of the image; sky and
floor are near grey), a still of the acrobot spans most of the image's height or width without
touching its border, a movie of a full turn keeps one view that holds every frame's robot, and a
floating robot moved 5 m is followed at the same size."""

import numpy as np
import pytest

import jaxdrake as jd

pytest.importorskip("meshcat")
pytest.importorskip("mujoco")

HEIGHT, WIDTH = 120, 160


def robot_box(image):
    """(top, bottom, left, right) pixel rows / columns of the coloured pixels of an RGB image."""
    rgb = image[..., :3].astype(int)
    rows, cols = np.nonzero(rgb.max(axis=-1) - rgb.min(axis=-1) > 40)
    assert rows.size, "no robot in the image"
    return rows.min(), rows.max(), cols.min(), cols.max()


def fill(box):
    """The robot's span as a fraction of the image's height and of its width, the larger."""
    top, bottom, left, right = box
    return max((bottom - top + 1) / HEIGHT, (right - left + 1) / WIDTH)


def inside(box):
    top, bottom, left, right = box
    return top > 0 and left > 0 and bottom < HEIGHT - 1 and right < WIDTH - 1


def test_a_still_and_a_movie_of_the_acrobot_fill_the_frame():
    acrobot = jd.models.Acrobot()
    vis = jd.viz.MeshcatVisualizer(acrobot, width=WIDTH, height=HEIGHT)
    stills = {}
    for x in ([0.0, 0.0, 0.0, 0.0], [2.5, -1.0, 0.0, 0.0]):
        stills[x[0]] = box = robot_box(vis.images(np.array([x]))[0])
        assert inside(box) and fill(box) > 0.8, (x, box)
    turn = np.linspace(0.0, 2 * np.pi, 9)
    frames = vis.images(np.column_stack([turn, 0.5 * np.sin(turn), 0 * turn, 0 * turn]))
    boxes = np.array([robot_box(frame) for frame in frames])
    assert all(inside(box) for box in boxes), boxes
    union = (boxes[:, 0].min(), boxes[:, 1].max(), boxes[:, 2].min(), boxes[:, 3].max())
    assert fill(union) > 0.8, union
    assert fill(stills[0.0]) > fill(boxes[0]) + 0.3  # hanging, alone: framed closer than in the turn


def test_a_floating_robot_is_followed():
    plant = jd.RigidBodySystem.from_urdf(jd.models.Acrobot().source, floating_base=True)
    vis = jd.viz.MeshcatVisualizer(plant, width=WIDTH, height=HEIGHT)
    x = np.array(plant.initial_state(), float)
    x[7:9] = 0.4, 0.9
    moved = x.copy()
    moved[:3] = 5.0, -3.0, 1.0
    near, far = (robot_box(image) for image in vis.images(np.stack([x, moved])))
    assert inside(near) and inside(far) and fill(near) > 0.8
    np.testing.assert_allclose(far, near, atol=2)  # the same picture, 5.9 m away
