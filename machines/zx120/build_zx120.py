#!/usr/bin/env python3
"""Write zx120.urdf and meshes/*.obj for the Hitachi ZX120 from simple solids.

Run by hand after changing the geometry or machine.yaml; the outputs are committed:
    python machines/zx120/build_zx120.py

Kinematics (link/joint names, joint origins and limits) follow OPERA's ROS description v2
(pwri-opera/zx120_ros, see reference/zx120.yaml). The meshes are our own boxes and cylinders, drawn in
each link's frame: at all joints zero the boom, arm and bucket lie along +x of the machine, and in their
own frames along +z, with "up" being -x (the boom joint origin is pitched +90 deg). Masses, speed and
torque limits come from machine.yaml; inertia and centre of mass from each mesh scaled to its mass.
"""
from __future__ import annotations

import math
from pathlib import Path
from xml.sax.saxutils import quoteattr

import numpy as np
import trimesh
import yaml

HERE = Path(__file__).resolve().parent

# OPERA v2 joint origins and limits (zx120_description/urdf/zx120.urdf).
BOOM_PIN_XYZ = (0.14, -0.16443, 0.424)
BOOM_LENGTH = 4.6          # boom pin -> arm pin
ARM_LENGTH = 2.519         # arm pin -> bucket pin
BUCKET_LENGTH = 1.23       # bucket pin -> cutting edge, along bucket_link +z
LIMITS = {
    "boom_joint": (-1.2217304764, 0.767944870878),
    "arm_joint": (0.523598775598, 2.65290046303),
    "bucket_joint": (-0.575958653158, 2.49582083035),
}
BUCKET_OUTER_WIDTH = 0.70
PLATE = 0.035              # bucket plate thickness


# ----------------------------------------------------------------------------------------- solids
def box(lo, hi) -> trimesh.Trimesh:
    """Axis-aligned box between corners lo and hi."""
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    return trimesh.creation.box(extents=hi - lo, transform=trimesh.transformations.translation_matrix((lo + hi) / 2))


def beam_xz(p0, p1, depth, width, y=0.0, extend=(0.0, 0.0)) -> trimesh.Trimesh:
    """Box from p0 to p1 (points in the x-z plane at height y), `depth` across the line in that plane,
    `width` along y; `extend` lengthens the (start, end) so consecutive plates overlap instead of gapping."""
    p0, p1 = np.array([p0[0], y, p0[1]], float), np.array([p1[0], y, p1[1]], float)
    axis = p1 - p0
    direction = axis / np.linalg.norm(axis)
    p0, p1 = p0 - extend[0] * direction, p1 + extend[1] * direction
    mesh = trimesh.creation.box(extents=(depth, width, np.linalg.norm(p1 - p0)))
    # local z -> direction by a rotation about y (the segment lies in the x-z plane)
    pitch = math.atan2(direction[0], direction[2])
    transform = trimesh.transformations.rotation_matrix(pitch, (0, 1, 0))
    transform[:3, 3] = (p0 + p1) / 2
    mesh.apply_transform(transform)
    return mesh


def pin_boss(center, radius, width) -> trimesh.Trimesh:
    """Cylinder along y (a pin boss) centred at `center`."""
    transform = trimesh.transformations.rotation_matrix(math.pi / 2, (1, 0, 0))
    transform[:3, 3] = center
    return trimesh.creation.cylinder(radius=radius, height=width, sections=24, transform=transform)


def z_cylinder(radius, z0, z1) -> trimesh.Trimesh:
    return trimesh.creation.cylinder(radius=radius, segment=((0, 0, z0), (0, 0, z1)), sections=32)


def plate_from_profile(points_xz, y0, y1) -> trimesh.Trimesh:
    """A side plate: the convex region of the profile points, extruded from y0 to y1."""
    pts = np.array([[x, y, z] for x, z in points_xz for y in (y0, y1)])
    return trimesh.convex.convex_hull(pts)


# ----------------------------------------------------------------------------------------- links
def track_mesh() -> trimesh.Trimesh:
    """Undercarriage in track_link (= base_link, on the ground): two track frames, centre frame,
    swing bearing up to the swing joint at z = 1.0."""
    parts = []
    for side in (1, -1):
        parts.append(box((-1.80, side * 1.0 - 0.25, 0.0), (1.80, side * 1.0 + 0.25, 0.78)))
    parts.append(box((-1.10, -0.75, 0.30), (1.10, 0.75, 0.78)))     # car body frame
    parts.append(z_cylinder(0.75, 0.78, 1.0))                        # swing bearing
    return trimesh.util.concatenate(parts)


def body_mesh() -> trimesh.Trimesh:
    """Upper structure in body_link (origin on the swing axis, 1.0 m above ground). Cab on the left
    (+y), boom foot just right of centre, engine and counterweight at the rear."""
    return trimesh.util.concatenate([
        box((-1.30, -1.25, 0.00), (1.25, 1.25, 0.22)),     # revolving frame deck
        box((-2.15, -1.20, 0.05), (-1.45, 1.20, 1.05)),    # counterweight (tail radius ~2.15 m)
        box((-1.45, -1.20, 0.22), (-0.35, 1.20, 1.05)),    # engine and pump housing
        box((-0.35, 0.30, 0.22), (1.10, 1.22, 1.75)),      # cab: top at 2.75 m above ground
        box((-0.35, -1.20, 0.22), (1.15, -0.55, 1.05)),    # tanks and tool box
        box((-0.05, -0.42, 0.15), (0.35, 0.10, 0.58)),     # boom foot bracket around the boom pin
    ])


def boom_mesh() -> trimesh.Trimesh:
    """Bent boom from the foot pin (origin) to the arm pin (0, 0, 4.6); the knee bulges up (-x)."""
    knee = (-1.0, 2.0)
    return trimesh.util.concatenate([
        beam_xz((0.0, 0.0), knee, depth=0.42, width=0.32, extend=(0.0, 0.2)),
        beam_xz(knee, (0.0, BOOM_LENGTH), depth=0.42, width=0.32, extend=(0.2, 0.0)),
        pin_boss((0, 0, 0), 0.15, 0.70),                   # foot boss
        pin_boss((0, 0, BOOM_LENGTH), 0.13, 0.42),         # arm pin boss
    ])


def arm_mesh() -> trimesh.Trimesh:
    """Arm from the arm pin (origin) to the bucket pin (0, 0, 2.519), with the cylinder bracket
    reaching back and up beyond the arm pin."""
    return trimesh.util.concatenate([
        beam_xz((-0.32, -0.60), (0.0, ARM_LENGTH), depth=0.36, width=0.25),
        beam_xz((-0.55, -0.55), (-0.15, 0.25), depth=0.20, width=0.20),   # arm cylinder bracket
        pin_boss((0, 0, 0), 0.13, 0.30),
        pin_boss((0, 0, ARM_LENGTH), 0.10, 0.30),
    ])


def bucket_profile():
    """Inner profile of the bucket shell in the bucket_link x-z plane: a circular back from the top lip
    near the pin round to the floor, then the floor to the cutting edge at (0, 1.23). The shell lies on
    the -x side of the pin-edge chord, so the mouth faces +x: curling (positive bucket_joint) moves the
    edge towards +x of this frame and soil enters through the mouth."""
    center, radius = np.array([-0.25, 0.45]), 0.55
    angles = np.linspace(0.0, 0.8 * math.pi, 6)          # 5 plates for the curved back
    arc = [center + radius * np.array([-math.sin(t), -math.cos(t)]) for t in angles]
    edge = np.array([0.0, BUCKET_LENGTH])
    lip = arc[-1] + 0.78 * (edge - arc[-1])              # where the floor plate meets the cutting edge
    return arc, lip, edge


def bucket_mesh() -> trimesh.Trimesh:
    """Open bucket: curved back (5 plates), floor, cutting edge, two side plates, pin ears. Each plate
    a closed box; outer width 0.70 m; the edge's end face is centred on (0, y, 1.23)."""
    arc, lip, edge = bucket_profile()
    inner_half = BUCKET_OUTER_WIDTH / 2 - PLATE
    width = 2 * inner_half
    overlap = (PLATE / 2, PLATE / 2)
    parts = [beam_xz(a, b, depth=PLATE, width=width, extend=overlap) for a, b in zip(arc[:-1], arc[1:])]
    parts.append(beam_xz(arc[-1], lip, depth=PLATE, width=width, extend=overlap))            # floor
    parts.append(beam_xz(lip, edge, depth=1.4 * PLATE, width=BUCKET_OUTER_WIDTH))             # cutting edge
    profile = [tuple(p) for p in arc] + [tuple(lip), tuple(edge)]
    for side in (1, -1):
        y_in, y_out = side * inner_half, side * BUCKET_OUTER_WIDTH / 2
        parts.append(plate_from_profile(profile, min(y_in, y_out), max(y_in, y_out)))
        # pin ear: carries the bucket pin and the link pin, welded to the top of the back
        ear = [(0.10, -0.10), (0.10, 0.12), (-0.20, -0.18), (-0.40, 0.05), (-0.20, 0.25)]
        parts.append(plate_from_profile(ear, side * 0.20 - PLATE / 2, side * 0.20 + PLATE / 2))
    return trimesh.util.concatenate(parts)


LINK_MESHES = {
    "track_link": track_mesh,
    "body_link": body_mesh,
    "boom_link": boom_mesh,
    "arm_link": arm_mesh,
    "bucket_link": bucket_mesh,
}


# ----------------------------------------------------------------------------------------- URDF text
def fmt(values) -> str:
    # round off float noise (1e-17) so the file reads cleanly
    return " ".join(f"{(0.0 if abs(v) < 1e-9 else v):.12g}" for v in values)


def inertial_xml(mesh: trimesh.Trimesh, mass: float) -> str:
    """Inertial block: the mesh as a solid of uniform density scaled to `mass` (overlaps between the
    simple solids count twice, a small error for these shapes)."""
    solid = mesh.copy()
    solid.density = mass / solid.volume
    com = solid.center_mass
    # about the COM, link-frame axes; products below 1e-6 kg m^2 are float noise of symmetric shapes
    inertia = solid.moment_inertia
    i = np.vectorize(lambda v: f"{(0.0 if abs(v) < 1e-6 else v):.6g}")(inertia)
    return (f'    <inertial>\n      <origin xyz="{fmt(com)}" rpy="0 0 0"/>\n      <mass value="{mass:.10g}"/>\n'
            f'      <inertia ixx="{i[0, 0]}" ixy="{i[0, 1]}" ixz="{i[0, 2]}" '
            f'iyy="{i[1, 1]}" iyz="{i[1, 2]}" izz="{i[2, 2]}"/>\n    </inertial>\n')


def mesh_link_xml(name: str, mesh: trimesh.Trimesh, mass: float) -> str:
    uri = quoteattr(f"meshes/{name}.obj")
    geometry = f"      <geometry><mesh filename={uri}/></geometry>\n"
    return (f'  <link name="{name}">\n'
            f'    <visual>\n      <origin xyz="0 0 0" rpy="0 0 0"/>\n{geometry}'
            f'      <material name="zx120_orange"><color rgba="0.93 0.55 0.1 1"/></material>\n    </visual>\n'
            f'    <collision>\n      <origin xyz="0 0 0" rpy="0 0 0"/>\n{geometry}    </collision>\n'
            f'{inertial_xml(mesh, mass)}  </link>\n')


def joint_xml(name, jtype, parent, child, xyz=(0, 0, 0), rpy=(0, 0, 0), axis=None, limit=None) -> str:
    text = (f'  <joint name="{name}" type="{jtype}">\n    <parent link="{parent}"/>\n    <child link="{child}"/>\n'
            f'    <origin xyz="{fmt(xyz)}" rpy="{fmt(rpy)}"/>\n')
    if axis is not None:
        text += f'    <axis xyz="{fmt(axis)}"/>\n'
    if limit is not None:
        attrs = " ".join(f'{key}="{value:.12g}"' for key, value in limit.items())
        text += f"    <limit {attrs}/>\n"
    return text + "  </joint>\n"


def build(out_dir: Path = HERE) -> dict[str, trimesh.Trimesh]:
    config = yaml.safe_load((out_dir / "machine.yaml").read_text())
    masses, actuators = config["masses"], config["joints"]

    def limit(joint):
        speed, torque = actuators[joint]["max_speed"], actuators[joint]["max_torque"]
        lo_hi = LIMITS.get(joint)
        base = {"lower": lo_hi[0], "upper": lo_hi[1]} if lo_hi else {}
        return {**base, "velocity": float(speed), "effort": float(torque)}

    meshes = {name: make() for name, make in LINK_MESHES.items()}
    mesh_dir = out_dir / "meshes"
    mesh_dir.mkdir(exist_ok=True)
    for name, mesh in meshes.items():
        assert all(part.is_watertight for part in mesh.split(only_watertight=False)), name
        (mesh_dir / f"{name}.obj").write_text(trimesh.exchange.obj.export_obj(
            mesh, include_normals=False, include_color=False, include_texture=False, header=None))

    parts = ['<?xml version="1.0" encoding="utf-8"?>\n',
             "<!-- Written by machines/zx120/build_zx120.py from machine.yaml: do not edit by hand. -->\n",
             "<!-- Kinematics: PWRI OPERA zx120_description v2. Meshes: simple solids, collision = visual. -->\n",
             '<robot name="zx120">\n', '  <link name="base_link"/>\n',
             joint_xml("base_joint", "fixed", "base_link", "track_link"),
             mesh_link_xml("track_link", meshes["track_link"], masses["track_link"]),
             joint_xml("swing_joint", "continuous", "track_link", "body_link", xyz=(0, 0, 1.0), axis=(0, 0, 1),
                       limit=limit("swing_joint")),
             mesh_link_xml("body_link", meshes["body_link"], masses["body_link"]),
             joint_xml("boom_joint", "revolute", "body_link", "boom_link", xyz=BOOM_PIN_XYZ,
                       rpy=(0, 1.5707963268, 0), axis=(0, 1, 0), limit=limit("boom_joint")),
             mesh_link_xml("boom_link", meshes["boom_link"], masses["boom_link"]),
             joint_xml("arm_joint", "revolute", "boom_link", "arm_link", xyz=(0, 0, BOOM_LENGTH), axis=(0, 1, 0),
                       limit=limit("arm_joint")),
             mesh_link_xml("arm_link", meshes["arm_link"], masses["arm_link"]),
             joint_xml("bucket_joint", "revolute", "arm_link", "bucket_link", xyz=(0, 0, ARM_LENGTH),
                       axis=(0, 1, 0), limit=limit("bucket_joint")),
             mesh_link_xml("bucket_link", meshes["bucket_link"], masses["bucket_link"]),
             # the cutting edge frame (dummy joint, as in OPERA; pitched 50 deg like OPERA's)
             joint_xml("bucket_end_joint", "revolute", "bucket_link", "bucket_end_link", xyz=(0, 0, BUCKET_LENGTH),
                       rpy=(0, 0.872664625997, 0), axis=(1, 0, 0),
                       limit={"lower": -3.14, "upper": 3.14, "velocity": 0.5, "effort": 1.0}),
             '  <link name="bucket_end_link">\n    <inertial>\n      <origin xyz="0 0 0" rpy="0 0 0"/>\n'
             '      <mass value="0.001"/>\n'
             '      <inertia ixx="1e-06" ixy="0" ixz="0" iyy="1e-06" iyz="0" izz="1e-06"/>\n    </inertial>\n  </link>\n',
             "</robot>\n"]
    (out_dir / "zx120.urdf").write_text("".join(parts))
    return meshes


if __name__ == "__main__":
    built = build()
    for link, mesh in built.items():
        size = (HERE / "meshes" / f"{link}.obj").stat().st_size
        print(f"{link:12s} {len(mesh.faces):5d} faces  {size / 1024:6.1f} kB  bounds {np.round(mesh.bounds, 3).tolist()}")
    print(f"wrote {HERE / 'zx120.urdf'}")
