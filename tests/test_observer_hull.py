"""The mass in a tool's hull (soil_mass.csv's in_<tool>_kg, the bucket load of the Gym env and ROS) tests only the
grains inside a sphere around the hull: the same grains as testing every grain."""
from types import SimpleNamespace

import numpy as np
import trimesh

from opera_taichi.geometry import quat_to_matrix
from opera_taichi.observers import hull_halfspaces, inside_tools


def test_the_sphere_prefilter_keeps_every_grain_in_the_hull():
    rng = np.random.default_rng(0)
    mesh = trimesh.creation.cylinder(radius=0.6, height=1.5, sections=24)
    mesh.apply_translation([2.0, -0.5, 0.3])            # the hull off the link origin
    q = np.array([0.2, -0.4, 0.1, 0.9])
    q /= np.linalg.norm(q)
    p = np.array([5.0, 1.0, -0.4])
    sim = SimpleNamespace(model=SimpleNamespace(bindings=[SimpleNamespace(mesh=mesh)]),
                          tool_pose=lambda i: (p, q, None, None))
    planes = [hull_halfspaces(mesh)]
    rot = quat_to_matrix(q)
    centre = p + rot @ np.array([2.0, -0.5, 0.3])
    positions = centre + rng.uniform(-1.2, 1.2, (20000, 3))
    mask = inside_tools(sim, planes, positions)[0]
    local = (positions - p) @ rot
    brute = np.all(local @ planes[0][:, :3].T + planes[0][:, 3] <= 0.0, axis=1)
    assert 1000 < brute.sum() < 19000                   # both inside and outside grains
    assert np.array_equal(mask, brute)


def test_roll_pitch_yaw_round_trip_through_the_quaternion():
    from opera_taichi.geometry import quat_to_rpy, rpy_to_quat

    rng = np.random.default_rng(3)
    for rpy in np.column_stack([rng.uniform(-3.1, 3.1, 200), rng.uniform(-1.55, 1.55, 200),
                                rng.uniform(-3.1, 3.1, 200)]):
        q = rpy_to_quat(rpy)
        assert np.allclose(quat_to_rpy(q), rpy, atol=1e-9)
        assert np.allclose(quat_to_rpy(-q), rpy, atol=1e-9)   # q and -q are one rotation
