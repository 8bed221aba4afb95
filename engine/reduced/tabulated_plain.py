"""The tabulated layout of one spec, item by item (engine.reduced.tabulated_layout's reference).

Every check of engine.reduced.tabulated_layout in order, each raising a ValueError that names the
joint, body or sub-chain it refuses: the path for a spec whose structure the array path does not
take, and the reference the array path is tested against (tests/engine/test_tabulated_paths.py).
"""

from __future__ import annotations

import math

import numpy as np

from engine.pack import collision_pairs
from engine.reduced.tabulated_layout import (BASE_SLOTS, MAX_GROUPS, MAX_LINKS, PLANE_TOLERANCE, SubChain,
                                             TabulatedLayout, _assemble, _base_slots, _choose_base, _components,
                                             _frame_to, _planar_angle, _rounded, _turn_angle, matrix_quat,
                                             rot_minus_y)
from engine.reduced.tabulated_tables import START_TOLERANCE, TABLE_SAMPLES, _Planar, cached_table, wrap
from engine.spatial import cross, quat_matrix
from engine.spec import JointType, MechanismSpec, ShapeType


def _plain_layout(spec: MechanismSpec, *, samples: int = TABLE_SAMPLES) -> TabulatedLayout:
    """tabulated_layout item by item: every check in order, each raising its ValueError (the
    reference the array path equals, and its way out)."""
    bodies, joints = spec.bodies, spec.joints
    index = spec.body_index
    for joint in joints:
        if joint.parent is None:
            raise ValueError(f"joint '{joint.name}' holds body '{joint.child}' to the world: the tabulated path "
                             f"needs a floating base (no joint to the world)")
    base = _choose_base(spec)
    base_body = bodies[base]
    R_base = quat_matrix(base_body.orientation)
    base_com = base_body.position + R_base @ base_body.com
    components = _components(spec, base)
    if len(components) > MAX_GROUPS:
        raise ValueError(f"base '{base_body.name}' carries {len(components)} sub-chains: the kernel takes at most "
                         f"{MAX_GROUPS}")
    member = {b: g for g, comp in enumerate(components) for b in comp}
    of_group = [[] for _ in components]
    for j, joint in enumerate(joints):
        a, b = index[joint.parent], index[joint.child]
        of_group[member[b] if a == base else member[a]].append(j)
        where = f"joint '{joint.name}'"
        if joint.type not in (JointType.REVOLUTE, JointType.INLINE):
            raise ValueError(f"{where} is {joint.type.name.lower()}: a tabulated sub-chain has revolute and inline "
                             f"joints only")
        if joint.has_limits:
            raise ValueError(f"{where} has limits: the tabulated path has no limit rows")
        if joint.armature > 0.0 or joint.damping > 0.0:
            raise ValueError(f"{where} has armature or joint damping: the tabulated path has neither")
        if joint.drive is not None:
            if base not in (a, b):
                raise ValueError(f"{where} is driven inside a sub-chain: only the joint that turns a sub-chain on "
                                 f"base '{base_body.name}' may be driven")
            if joint.drive.stiffness > 0.0:
                raise ValueError(f"{where}: its drive has stiffness (a position target): the tabulated path has "
                                 f"velocity drives only")
    world_R = [quat_matrix(b.orientation) for b in bodies]
    # one plane normal: every joint's axis, in the base frame
    normal = None
    for j, joint in enumerate(joints):
        a, b = index[joint.parent], index[joint.child]
        axis_p = R_base.T @ world_R[a] @ quat_matrix(joint.parent_orientation) @ joint.axis
        if normal is None:
            normal, first = axis_p, joint
        elif np.linalg.norm(cross(normal, axis_p)) > PLANE_TOLERANCE:
            raise ValueError(f"joint '{joint.name}' turns about {np.round(axis_p, 6).tolist()} in the frame of base "
                             f"'{base_body.name}', joint '{first.name}' about {np.round(normal, 6).tolist()}: the "
                             f"kernel takes one plane normal per world")
        if joint.type == JointType.REVOLUTE:
            axis_c = R_base.T @ world_R[b] @ quat_matrix(joint.child_orientation) @ joint.axis
            if np.linalg.norm(cross(axis_c, axis_p)) > PLANE_TOLERANCE:
                raise ValueError(f"joint '{joint.name}': its parent and child axes differ at the start")
    Q = np.eye(3) if normal is None else _frame_to(normal)
    R_state = R_base @ Q
    state_R = [R_state.T @ m for m in world_R]  # every body's orientation in the state frame

    def com_world(i):
        return bodies[i].position + world_R[i] @ bodies[i].com

    def anchor_world(joint, side):
        i = index[joint.parent if side == "parent" else joint.child]
        local = joint.parent_position if side == "parent" else joint.child_position
        return bodies[i].position + world_R[i] @ local

    ground = None
    if spec.ground is not None:
        g = spec.ground
        if np.abs(g.normal - np.array([0.0, 0.0, 1.0])).max() > 1e-9:
            raise ValueError(f"ground plane: normal {np.round(g.normal, 6).tolist()}: the tabulated path takes a "
                             f"ground of normal +z")
        if g.restitution > 0.0:
            raise ValueError(f"ground plane: restitution {g.restitution:g}: the tabulated path has inelastic contacts")
        ground = (float(g.offset), float(g.friction))
    shapes_of = {}
    if ground is not None:
        for s, shape in enumerate(spec.shapes):
            shapes_of.setdefault(index[shape.body], []).append(s)
            if shape.restitution > 0.0:
                raise ValueError(f"shape '{shape.name}': restitution {shape.restitution:g}: the tabulated path has "
                                 f"inelastic contacts")
    for a, b in collision_pairs(spec):
        if b >= 0:
            raise ValueError(f"shapes '{spec.shapes[a].name}' and '{spec.shapes[b].name}' may touch each other: the "
                             f"tabulated path has ground contacts only (give them a common collision group)")
    groups = []
    for g, comp in enumerate(components):
        groups.append(_sub_chain(spec, comp, of_group[g], base, R_state, state_R, com_world, anchor_world, base_com,
                                 shapes_of, ground, samples))
    base_slots = _base_slots(spec, shapes_of.get(base, []), base_body.com, Q, ground)
    if len(base_slots) > BASE_SLOTS:
        raise ValueError(f"base '{base_body.name}': its shapes have {len(base_slots)} contact points, the kernel has "
                         f"{BASE_SLOTS} base slots (one box, or capsules and spheres)")
    where_is = {base: (-1, 0)}
    for g, chain in enumerate(groups):
        for k, i in enumerate(chain.bodies):
            where_is[i] = (g, k)
    return _assemble(spec, base, Q, R_state, base_com, groups, base_slots, ground, where_is,
                     [index[p.body] for p in spec.points])


def _sub_chain(spec, comp, joint_list, base, R_state, state_R, com_world, anchor_world, base_com, shapes_of, ground,
               samples) -> SubChain:
    """One component of the bodies off the base as a tabulated SubChain (see tabulated_layout)."""
    bodies, joints, index = spec.bodies, spec.joints, spec.body_index
    what = f"sub-chain of body '{bodies[comp[0]].name}'"
    K, count = len(comp), len(joint_list)
    if K > MAX_LINKS:
        raise ValueError(f"{what}: {K} bodies, the kernel takes at most {MAX_LINKS} per sub-chain")
    mobility = 3 * K - 2 * count
    if mobility != 1:
        raise ValueError(f"{what}: mobility 3 n - 2 j = 3 * {K} - 2 * {count} = {mobility} (a revolute or inline "
                         f"joint is 2 rows in the plane); the tabulated path needs 1, one driving coordinate")
    driven = [j for j in joint_list if joints[j].drive is not None]
    if len(driven) != 1:
        names = ", ".join(f"'{joints[j].name}'" for j in driven)
        raise ValueError(f"{what}: {len(driven)} driven joints to the base{' (' + names + ')' if driven else ''}; "
                         f"the tabulated path needs exactly one (its driving coordinate)")
    jd = driven[0]
    driver = joints[jd]
    what = f"sub-chain turned by joint '{driver.name}'"
    link_of = {i: k for k, i in enumerate(comp)}
    phi0 = np.array([_planar_angle(state_R[i]) for i in comp])
    C = [rot_minus_y(-phi0[k]) @ state_R[i] for k, i in enumerate(comp)]
    com = np.array([R_state.T @ (com_world(i) - base_com) for i in comp])
    base_side = "parent" if index[driver.parent] == base else "child"
    pivot = R_state.T @ (anchor_world(driver, base_side) - base_com)
    sides, fixed = [], []
    for j in joint_list:
        joint = joints[j]
        ends = []
        for side in ("parent", "child"):
            i = index[joint.parent if side == "parent" else joint.child]
            if i == base:
                point = R_state.T @ (anchor_world(joint, side) - base_com)
                ends.append((K, np.array([point[0] - pivot[0], point[2] - pivot[2]]), point[1]))
                fixed.append(np.hypot(*ends[-1][1]))
            else:
                k = link_of[i]
                local = C[k] @ ((joint.parent_position if side == "parent" else joint.child_position) - bodies[i].com)
                ends.append((k, local[[0, 2]], com[k][1] + local[1]))
        if joint.type == JointType.REVOLUTE and abs(ends[0][2] - ends[1][2]) > 1e-6 * max(1.0, np.abs(com).max()):
            raise ValueError(f"joint '{joint.name}': its anchors are {abs(ends[0][2] - ends[1][2]):.3g} m apart along "
                             f"its axis at the start")
        sides.append(ends)
    reach = [np.hypot(*end[1]) for ends in sides for end in ends if end[0] < K] + fixed
    scale = max(reach)
    if not scale > 0.0:
        raise ValueError(f"{what}: every joint sits at its links' centres of mass: no length sets its scale")
    plane_y = float(com[:, 1].mean())
    for k, i in enumerate(comp):
        if abs(com[k, 1] - plane_y) > PLANE_TOLERANCE * scale:
            raise ValueError(f"body '{bodies[i].name}': its centre of mass is {abs(com[k, 1] - plane_y):.3g} m off the "
                             f"plane of the {what} (the kernel keeps a sub-chain's centres of mass in one plane)")
    origin = np.array([pivot[0], plane_y, pivot[2]])
    ja = np.array([ends[0][0] for ends in sides])
    jb = np.array([ends[1][0] for ends in sides])
    ra = np.array([ends[0][1] for ends in sides]) / scale
    rb = np.array([ends[1][1] for ends in sides]) / scale
    # the driving coordinate q, as engine.joints measures it, against the driving link's angle
    k_d = link_of[index[driver.child if base_side == "parent" else driver.parent]]
    base_orientation = R_state.T @ quat_matrix(bodies[base].orientation)

    def q_of(phi):
        link = rot_minus_y(phi) @ C[k_d]
        parent, child = (base_orientation, link) if base_side == "parent" else (link, base_orientation)
        rel = (parent @ quat_matrix(driver.parent_orientation)).T @ (child @ quat_matrix(driver.child_orientation))
        return _turn_angle(rel, driver.axis)

    q0 = q_of(phi0[k_d])
    sign = float(np.round(wrap(q_of(phi0[k_d] + 0.25) - q0) / 0.25))
    if abs(sign) != 1.0:
        raise ValueError(f"joint '{driver.name}' does not turn its link about the plane normal")
    offset = float(phi0[k_d] - sign * q0)
    parent_i, child_i = index[driver.parent], index[driver.child]
    axis_w = quat_matrix(bodies[parent_i].orientation) @ quat_matrix(driver.parent_orientation) @ driver.axis
    rate = float((bodies[child_i].angular_velocity - bodies[parent_i].angular_velocity) @ axis_w)
    planar = _Planar(K, ja, jb, ra, rb, k_d, sign, offset)
    x0 = np.column_stack([(com[:, 0] - origin[0]) / scale, (com[:, 2] - origin[2]) / scale, phi0]).reshape(-1)
    closed, ok = planar.newton(x0, q0)
    moved = closed - x0
    moved[2::3] = wrap(moved[2::3])
    if not ok or np.abs(moved).max() > START_TOLERANCE:
        gap = np.abs(planar.residual(x0, q0)).max() * scale
        raise ValueError(f"{what}: its loops are open by {gap:.3g} m at the start (no closed pose near the spec's)")
    # the contact shape
    shape, contact = None, None
    on = [s for i in comp for s in shapes_of.get(i, [])]
    if len(on) > 1:
        names = ", ".join(f"'{spec.shapes[s].name}'" for s in on)
        raise ValueError(f"{what} carries {len(on)} shapes ({names}): the kernel has two contact slots per "
                         f"sub-chain, one capsule or one sphere")
    if on:
        s = on[0]
        item = spec.shapes[s]
        if item.type not in (ShapeType.CAPSULE, ShapeType.SPHERE):
            raise ValueError(f"shape '{item.name}' is a {item.type.name.lower()}: a sub-chain's contact shape is a "
                             f"capsule or a sphere")
        i = index[item.body]
        k = link_of[i]
        local = C[k] @ (item.position - bodies[i].com)
        angle, half = 0.0, 0.0
        if item.type == ShapeType.CAPSULE:
            axis = C[k] @ quat_matrix(item.orientation)[:, 2]
            if abs(axis[1]) > PLANE_TOLERANCE:
                raise ValueError(f"shape '{item.name}': a capsule on a sub-chain must lie in its plane (its axis is "
                                 f"{np.round(axis, 6).tolist()} in its link's frame)")
            angle, half = math.atan2(axis[2], axis[0]), float(item.size[1])
        shape = (s, float(item.size[0]), half, angle, math.sqrt(item.friction * ground[1]))
        contact = (k, local / scale)
    key = (samples, K, tuple(zip(ja.tolist(), jb.tolist())), _rounded(ra), _rounded(rb), k_d, sign,
           _rounded([math.cos(offset), math.sin(offset)]),
           None if contact is None else (contact[0], _rounded(contact[1])))
    table = cached_table(key, planar, closed, q0, samples, contact, what)
    inertia = np.array([C[k] @ bodies[i].inertia @ C[k].T for k, i in enumerate(comp)])
    drive = driver.drive
    return SubChain(jd, list(comp), table, float(scale), origin, float(q0), rate,
                    np.array([bodies[i].mass for i in comp]), inertia, np.array([matrix_quat(c) for c in C]),
                    (float(drive.target_velocity), float(drive.damping), float(drive.effort_limit)), shape)
