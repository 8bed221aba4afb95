"""The tabulated path's step: one kernel per (tiled, phase, register cap), built on demand and
composed of named stages: chain_columns (M(q) and the bias forces h(q, u), link by link), the
free velocity u_f = u + dt M^-1 h, the drive rows and contact_rows (slot_point: slot k < BASE_SLOTS
is the base's point k, slot BASE_SLOTS + 2 g + e end e of sub-chain g's shape), precondition_pass
and warm_dual_pass (Jacobi preconditioner, warm start by slot), PADMM iterations (rhs_pass,
woodbury_apply, update_pass; the linear solves by the Woodbury identity
(D + S)^-1 = S^-1 - S^-1 J (M + J^T S^-1 J)^-1 J^T S^-1, a (6 + L)-square factor), then
u+ = u_f + M^-1 J^T lambda and integrate.

Tiled (a GPU batch up to tiled_max_worlds): one block of lanes per world sharing sub-chains, rows and
the factor, held to TILED_REGISTERS; otherwise one thread per world as two kernels (set-up; solve).
Both compute the same step. Why the layout (vec4 row state, one call site for the factor), with the
measurements: benchmarks/results/README.md, "Tabulated sub-chains: design notes".
"""

import functools
from typing import Any

import warp as wp

from engine.linalg.lanes import block_sync
from engine.reduced.tabulated_forces import TabulatedForces, applied_forces
from engine.reduced.tabulated_kernel import (BASE_SLOTS, DIVERGED_FAST, DIVERGED_NONFINITE, F_COL, F_FREE, F_HI,
                                             F_INV, F_LO, F_MU, F_P, F_PEN, F_R, F_RHS, KINV_VECS, MAX_GROUPS,
                                             MAX_LINKS, MAX_ROWS, NV, ROW_VECS, TWO_PI, TabulatedState,
                                             TabulatedWorlds, chol_solve, cholesky, contact_read, forward_norm2,
                                             jrow_dot, link_read, max4_sum1, penalty, plane, plane3, project_cone,
                                             project_row, rot_minus_y, row_add, row_at, row_dot, set_penalties,
                                             set_row, table_index, table_read, vecgroups, vecnv, vecsetup, vecstats)

wp.set_module_options({"enable_backward": False})  # no gradients are taken: compile the forward code only

__all__ = ["HISTORY", "step_kernel"]

# Moreau-Jean's per-world history (TabulatedModel.history, float (W, HISTORY)): the rates the last
# step started from (H_PREV, NV; its end's rates where a contact impulse moved them), the rates it
# ended with (H_END, NV) and the pose it ended at (H_POSE: position 3, orientation 4 (x, y, z, w),
# driving coordinates MAX_GROUPS; during a step the pose it started from). A step extrapolates the
# rates to its midpoint only where the state is where the last step left it (NaN at first).
H_PREV = 0
H_END = NV
H_POSE = 2 * NV
HISTORY = 3 * NV + 1


@wp.func
def extrapolated(a1: wp.vec4, a2: wp.vec4, f0: wp.vec4, beta: float, eta: float):
    """A row's extrapolated y^ = y + beta (y - y_before), z^ likewise, and the right-hand side
    b = -v_f + eta x + penalty y^ - z^ of its PADMM step (a1, a2: its state; f0: its first fields)."""
    yh = a2[0] + beta * (a2[0] - a2[2])
    zh = a2[1] + beta * (a2[1] - a2[3])
    return wp.vec3(yh, zh, -f0[0] + eta * a1[0] + f0[2] * yh - zh)


@wp.func
def unit_rows(unit: int, L: int):
    """A unit's first row and its row count: drive row unit (1), or contact triplet unit - L (3)."""
    if unit < L:
        return unit, 1
    return L + 3 * (unit - L), 3


@wp.func
def rhs_pass(Jc: wp.array2d(dtype=wp.vec4), rows: wp.array2d(dtype=wp.vec4), s1: wp.array2d(dtype=wp.vec4),
             s2: wp.array2d(dtype=wp.vec4), w: int, L: int, units: int, beta: float, eta: float, lane: int,
             lanes: int):
    """A PADMM iteration's first pass over this lane's units (drive rows, contact triplets): each
    row's right-hand side b at the extrapolated (y, z), with the De Saxce shift from the velocity
    at the last iterate, t = S^-1 b, and the lane's share of J^T t (returned)."""
    gl = vecnv()
    unit = lane
    while unit < units:
        if unit < L:
            i = unit
            a1 = s1[w, i]
            a2 = s2[w, i]
            f0 = rows[w, ROW_VECS * i]  # v_f, mu, penalty, 1 / S
            bi = extrapolated(a1, a2, f0, beta, eta)[2]
            gl = row_add(Jc, w, i, False, 6 + i, bi * f0[3], gl)  # drive row i turns sub-chain i
        else:
            r0 = L + 3 * (unit - L)
            col = int(rows[w, ROW_VECS * r0 + 1][2])
            mu = float(0.0)
            bs = wp.vec3()
            vts = wp.vec3()
            invs = wp.vec3()
            for c in range(3):
                i = r0 + c
                a1 = s1[w, i]
                a2 = s2[w, i]
                f0 = rows[w, ROW_VECS * i]
                if c == 0:
                    mu = f0[1]
                bs[c] = extrapolated(a1, a2, f0, beta, eta)[2]
                vts[c] = a1[2]  # the velocity at the last iterate
                invs[c] = f0[3]
            bs[0] = bs[0] - mu * wp.sqrt(vts[1] * vts[1] + vts[2] * vts[2])
            for c in range(3):
                gl = row_add(Jc, w, r0 + c, True, col, bs[c] * invs[c], gl)
        unit += lanes
    return gl


@wp.func
def woodbury_apply(Kinv: wp.array2d(dtype=wp.vec4), w: int, n: int, gsum: vecnv, lane: int, lanes: int):
    """(M + J^T S^-1 J)^-1 J^T t from the factored inverse (its rows and columns past n are zero):
    a lane per entry when the block has NV lanes (they share the entries through one tile), else
    one lane reading the symmetric inverse's lower triangle once."""
    yv = vecnv()
    if lanes >= NV:
        # a lane per entry: lane k takes row k of the inverse (four entries per load), the
        # lanes share the entries through one tile
        yk = float(0.0)
        if lane < n:
            for kv in range(KINV_VECS):
                kq = Kinv[w, lane * KINV_VECS + kv]
                for t in range(4):
                    if 4 * kv + t < NV:
                        yk += kq[t] * gsum[4 * kv + t]
        entries = wp.tile(yk)
        for k in range(NV):
            yv[k] = wp.tile_extract(entries, k)
    else:
        # one lane (the CPU, or a thread per world): the symmetric inverse's lower triangle
        # read once
        for k in range(NV):
            if k < n:
                for kv in range(KINV_VECS):
                    if 4 * kv <= k:
                        kq = Kinv[w, k * KINV_VECS + kv]
                        for t in range(4):
                            j = 4 * kv + t
                            if j < k:
                                yv[k] += kq[t] * gsum[j]
                                yv[j] += kq[t] * gsum[k]
                            elif j == k:
                                yv[k] += kq[t] * gsum[k]
    return yv


@wp.func
def update_pass(Jc: wp.array2d(dtype=wp.vec4), rows: wp.array2d(dtype=wp.vec4), s1: wp.array2d(dtype=wp.vec4),
                s2: wp.array2d(dtype=wp.vec4), w: int, L: int, units: int, beta: float, eta: float, yv: vecnv,
                lane: int, lanes: int):
    """A PADMM iteration's second pass over this lane's units: x = t - S^-1 J yv, y (the
    projection), z and the row state stored once; returns the lane's residuals and merit
    (vecstats: primal, dual, natural, largest |y|, change)."""
    rp = float(0.0)
    rd = float(0.0)
    rn = float(0.0)
    ymax = float(0.0)
    change = float(0.0)
    unit = lane
    while unit < units:
        # b and t again as in the first pass (the state is not written there), x, the
        # projection of x + z / rho, the velocities at the new x, D x + v_f =
        # b - (eta + rho) x + v_f, the natural residual x - Pi(x - v^) (v^ with the De Saxce
        # shift: in the dual cone at a solution), then y, z and the residuals
        if unit < L:
            i = unit
            a1 = s1[w, i]
            a2 = s2[w, i]
            f0 = rows[w, ROW_VECS * i]
            f1 = rows[w, ROW_VECS * i + 1]
            pen = f0[2]
            e = extrapolated(a1, a2, f0, beta, eta)
            yh = e[0]
            zh = e[1]
            bi = e[2]
            tv = bi * f0[3]
            xr = tv - row_dot(Jc, w, i, False, 6 + i, yv) * f0[3]
            yn = wp.clamp(xr + zh / pen, f1[0], f1[1])
            vd = bi - (eta + pen) * xr + f0[0]
            rn = wp.max(rn, wp.abs(xr - wp.clamp(xr - vd, f1[0], f1[1])))
            zn = zh + pen * (xr - yn)
            dy = yn - yh
            dz = zn - zh
            rp = wp.max(rp, wp.abs(xr - yn))
            rd = wp.max(rd, wp.abs(eta * (xr - a1[0]) + pen * dy))
            change += pen * dy * dy + dz * dz / pen
            s2[w, i] = wp.vec4(yn, zn, a2[0], a2[1])
            s1[w, i] = wp.vec4(xr, a1[0], vd, tv)
            ymax = wp.max(ymax, wp.abs(yn))
        else:
            r0 = L + 3 * (unit - L)
            col = int(rows[w, ROW_VECS * r0 + 1][2])
            mu = float(0.0)
            pen = float(0.0)
            xs = wp.vec3()
            xps = wp.vec3()
            bs = wp.vec3()
            ts = wp.vec3()
            yo = wp.vec3()
            zo = wp.vec3()
            yhs = wp.vec3()
            zhs = wp.vec3()
            rhs = wp.vec3()
            vts = wp.vec3()
            invs = wp.vec3()
            for c in range(3):
                i = r0 + c
                a1 = s1[w, i]
                a2 = s2[w, i]
                f0 = rows[w, ROW_VECS * i]
                if c == 0:
                    mu = f0[1]
                    pen = f0[2]
                e = extrapolated(a1, a2, f0, beta, eta)
                yh = e[0]
                zh = e[1]
                bs[c] = e[2]
                vts[c] = a1[2]
                invs[c] = f0[3]
                rhs[c] = f0[0]
                xps[c] = a1[0]
                yo[c] = a2[0]
                zo[c] = a2[1]
                yhs[c] = yh
                zhs[c] = zh
            bs[0] = bs[0] - mu * wp.sqrt(vts[1] * vts[1] + vts[2] * vts[2])
            for c in range(3):
                ts[c] = bs[c] * invs[c]
                xs[c] = ts[c] - row_dot(Jc, w, r0 + c, True, col, yv) * invs[c]
            pj = project_cone(mu, xs[0] + zhs[0] / pen, xs[1] + zhs[1] / pen, xs[2] + zhs[2] / pen)
            vel = wp.vec3()
            for c in range(3):
                vel[c] = bs[c] - (eta + pen) * xs[c] + rhs[c]
            vels3 = wp.vec3(vel[0], vel[1], vel[2])  # kept for the next iteration's De Saxce shift
            vel[0] = vel[0] + mu * wp.sqrt(vel[1] * vel[1] + vel[2] * vel[2])
            nat = xs - project_cone(mu, xs[0] - vel[0], xs[1] - vel[1], xs[2] - vel[2])
            rn = wp.max(rn, wp.max(wp.abs(nat[0]), wp.max(wp.abs(nat[1]), wp.abs(nat[2]))))
            for c in range(3):
                yn = pj[c]
                xr = xs[c]
                zn = zhs[c] + pen * (xr - yn)
                dy = yn - yhs[c]
                dz = zn - zhs[c]
                rp = wp.max(rp, wp.abs(xr - yn))
                rd = wp.max(rd, wp.abs(eta * (xr - xps[c]) + pen * dy))
                change += pen * dy * dy + dz * dz / pen
                s2[w, r0 + c] = wp.vec4(yn, zn, yo[c], zo[c])
                s1[w, r0 + c] = wp.vec4(xr, xps[c], vels3[c], ts[c])
                ymax = wp.max(ymax, wp.abs(yn))
        unit += lanes
    return vecstats(rp, rd, rn, ymax, change)


@wp.func
def chain_columns(worlds: TabulatedWorlds, state: TabulatedState, M: wp.array2d(dtype=float), w: int, L: int,
                  R: wp.mat33, axis: wp.vec3, om: wp.vec3, g: wp.vec3, lane: int, lanes: int, mid: int,
                  half: float, ext: float, history: wp.array2d(dtype=float)):
    """This lane's sub-chains' columns of M (written) and their shares of the base blocks and bias
    forces, packed as a vecsetup to be summed over the lanes in one reduction: sum m_k, sum m_k d_k,
    the angular block, the base's bias force and torque, and each sub-chain's bias force. mid != 0
    (Moreau-Jean): at the angles advanced by half (dt / 2) times their rates, with the rates
    extrapolated by ext (u + ext (u - u_last), u_last from history)."""
    m_part = float(0.0)  # this lane's sub-chains: sum of m_k
    md_part = wp.vec3()  # sum of m_k d_k
    rot_part = wp.mat33()  # angular block
    f_part = wp.vec3()  # bias force on the base
    t_part = wp.vec3()  # bias torque on the base
    h_groups = vecgroups()  # each sub-chain's bias force (its own lane's entry)
    for gi in range(lane, L, lanes):
        t = worlds.group_table[w, gi]
        s = worlds.group_scale[w, gi]
        ang = state.coord[w, gi]
        rate = state.coord_rate[w, gi]
        if mid != 0:
            ang = ang + half * rate
            if ext != 0.0:  # (the history is NaN before a first step)
                rate = rate + ext * (rate - history[w, H_PREV + 6 + gi])
        i0, i1, f = table_index(ang, worlds.samples)
        col = 6 + gi
        o = worlds.group_origin[w, gi]
        me_sum = wp.vec3()  # the sub-chain's column: linear part
        mw_sum = wp.vec3()  # angular part
        mjj = float(0.0)
        hj = float(0.0)
        for k in range(worlds.table_links[t]):
            c0 = link_read(worlds.links0, t, i0, i1, f, k)
            c1 = table_read(worlds.links1, t, i0, i1, f, k)
            c2 = table_read(worlds.links2, t, i0, i1, f, k)
            mk = worlds.link_mass[w, gi * MAX_LINKS + k]
            d = R * (o + wp.vec3(s * c0[0], 0.0, s * c0[1]))
            e = plane(R, c1) * s
            e2 = plane(R, c2) * s
            Rk = R * rot_minus_y(c0[2])
            Ik = Rk * worlds.link_inertia[w, gi * MAX_LINKS + k] * wp.transpose(Rk)
            ax = axis * c1[2]
            m_part += mk
            md_part += mk * d
            rot_part += Ik + mk * (wp.dot(d, d) * wp.identity(n=3, dtype=float) - wp.outer(d, d))
            me_sum += mk * e
            mw_sum += mk * wp.cross(d, e) + Ik * ax
            mjj += mk * wp.dot(e, e) + wp.dot(ax, Ik * ax)
            wk = om + ax * rate
            acc = wp.cross(om, wp.cross(om, d)) + 2.0 * rate * wp.cross(om, e) + e2 * (rate * rate)
            alpha = rate * wp.cross(om, ax) + axis * (c2[2] * rate * rate)
            f_lin = mk * (g - acc)
            f_ang = -(Ik * alpha) - wp.cross(wk, Ik * wk)
            f_part += f_lin
            t_part += wp.cross(d, f_lin) + f_ang
            hj += wp.dot(e, f_lin) + wp.dot(ax, f_ang)
        for c in range(MAX_GROUPS):  # a select over constant indices keeps h_groups in registers
            if c == gi:
                h_groups[c] = hj
        for i in range(3):
            M[w, i * NV + col] = me_sum[i]
            M[w, col * NV + i] = me_sum[i]
            M[w, (3 + i) * NV + col] = mw_sum[i]
            M[w, col * NV + 3 + i] = mw_sum[i]
        M[w, col * NV + col] = mjj
    part = vecsetup()
    part[0] = m_part
    for i in range(3):
        part[1 + i] = md_part[i]
        part[13 + i] = f_part[i]
        part[16 + i] = t_part[i]
        for j in range(3):
            part[4 + 3 * i + j] = rot_part[i, j]
    for c in range(MAX_GROUPS):
        part[19 + c] = h_groups[c]
    return part


@wp.func
def slot_point(worlds: TabulatedWorlds, state: TabulatedState, w: int, k: int, R: wp.mat33, p: wp.vec3,
               axis: wp.vec3, mid: int, half: float):
    """Contact slot k's point below the ground's normal: its arm from the base's origin, its
    velocity per unit driving rate (a sub-chain's shape; zero on the base), its sub-chain (-1: the
    base), friction, height above the ground (1e30: an empty slot, never within the margin) and
    the radius of the shape below the point.
    mid != 0: the sub-chains at their angles advanced by half (dt / 2) times their rates (R and p
    are then the midpoint's)."""
    ground = worlds.base[w][2]
    arm = wp.vec3()
    lin = wp.vec3()  # the point's velocity per unit driving rate (a sub-chain's shape)
    grp = int(-1)
    mu = float(0.0)
    dist = float(1.0e30)  # an empty slot: never within the margin
    radius = float(0.0)
    if k < BASE_SLOTS:
        # a base point (a box corner, a sphere's or capsule end's centre) and the radius below it
        sp = worlds.base_slot[w, k]
        if sp[3] >= 0.0:
            arm = R * wp.vec3(sp[0], sp[1], sp[2]) + wp.vec3(0.0, 0.0, -sp[3])
            dist = p[2] + arm[2] - ground
            mu = worlds.base_slot_mu[w, k]
            radius = sp[3]
    else:
        grp = (k - BASE_SLOTS) / 2
        end = float(1.0)
        if (k - BASE_SLOTS) % 2 == 1:
            end = -1.0
        sh = worlds.group_shape[w, grp]
        # none (radius < 0), or a sphere's second slot (half length 0): empty
        if sh[0] >= 0.0 and (end > 0.0 or sh[1] > 0.0):
            t = worlds.group_table[w, grp]
            s = worlds.group_scale[w, grp]
            ang = state.coord[w, grp]
            if mid != 0:
                ang = ang + half * state.coord_rate[w, grp]
            i0, i1, f = table_index(ang, worlds.samples)
            fl = worlds.table_contact_link[t]
            phi = link_read(worlds.links0, t, i0, i1, f, fl)
            phi1 = table_read(worlds.links1, t, i0, i1, f, fl)
            beta = phi[2] + sh[2]
            dirn = wp.vec3(wp.cos(beta), wp.sin(beta), 0.0)
            perp = wp.vec3(-wp.sin(beta), wp.cos(beta), 0.0)
            fp = contact_read(worlds.contact0, t, i0, i1, f) * s + dirn * (end * sh[1])
            fv = contact_read(worlds.contact1, t, i0, i1, f) * s + perp * (end * sh[1] * phi1[2])
            # the contact point: on the shape's surface, one radius below its end's centre; it moves
            # with its link (turning at axis * phi' per unit driving rate about the end's centre)
            down = wp.vec3(0.0, 0.0, -sh[0])
            arm = R * worlds.group_origin[w, grp] + plane3(R, fp) + down
            lin = plane(R, fv) + wp.cross(axis * phi1[2], down)
            dist = p[2] + arm[2] - ground
            mu = sh[3]
            radius = sh[0]
    return arm, lin, grp, mu, dist, radius


@wp.func
def relief_at(relief: wp.vec4, x: float, y: float):
    """The relief's height above the plane and its unit normal at (x, y)."""
    a, k = relief[0], relief[1]
    sx = wp.sin(k * x + relief[2])
    sy = wp.sin(k * y + relief[3])
    n = wp.normalize(wp.vec3(-a * k * wp.cos(k * x + relief[2]) * sy, -a * k * sx * wp.cos(k * y + relief[3]), 1.0))
    return a * sx * sy, n


@wp.func
def on_relief(relief: wp.vec4, p: wp.vec3, arm: wp.vec3, dist: float, radius: float):
    """A contact slot over the ground's relief (engine.spec.Relief; relief = amplitude, 2 pi /
    wavelength, phases): its arm, height and normal against the relief's tangent plane at the
    contact point, where the normal through the shape's centre c = p + arm + radius z meets the
    surface (one fixed-point step from the point below c; the centre then follows the surface's
    offset curve, to second order in radius times curvature). The contact point's rate per
    driving rate keeps its flat-ground value (a radius times the slope off)."""
    up = wp.vec3(0.0, 0.0, 1.0)
    if relief[0] == 0.0:
        return arm, dist, up
    c = p + arm + radius * up
    h0, n0 = relief_at(relief, c[0], c[1])
    h, n = relief_at(relief, c[0] - radius * n0[0], c[1] - radius * n0[1])
    # the centre's distance from the tangent plane at the contact point, less the radius
    height = radius * (n0[0] * n[0] + n0[1] * n[1]) + (dist + radius - h) * n[2] - radius
    return arm + radius * (up - n), height, n


@wp.func
def base_advanced(p: wp.vec3, q: wp.quat, un: vecnv, L: int, h: float):
    """The base's position and orientation (exponential map) moved by h [s] at the velocities un, and
    whether they and un are finite: (p, q, ok)."""
    v = wp.vec3(un[0], un[1], un[2])
    om = wp.vec3(un[3], un[4], un[5])
    p = p + h * v
    spin = wp.length(om)
    if spin > 1.0e-12:
        q = wp.normalize(wp.quat_from_axis_angle(om / spin, spin * h) * q)
    ok = wp.isfinite(p) and wp.isfinite(v) and wp.isfinite(om) and wp.isfinite(q)
    for gi in range(L):
        if not wp.isfinite(un[6 + gi]):
            ok = False
    return p, q, ok


@wp.func
def integrate(state: TabulatedState, w: int, L: int, un: vecnv, dt: float, max_speed: float,
              diverged: wp.array(dtype=wp.int32), frozen: wp.array(dtype=wp.int32)):
    """The base's position, its orientation (exponential map) and the driving coordinates (wrapped to
    [0, 2 pi)) integrated with the new velocities un; a non-finite world is flagged and left at its
    last finite state, a too fast one flagged after the step; both are frozen."""
    v = wp.vec3(un[0], un[1], un[2])
    om = wp.vec3(un[3], un[4], un[5])
    p, q, ok = base_advanced(state.position[w], state.orientation[w], un, L, dt)
    if not ok:  # frozen at its last finite state (the tables are never read at a non-finite angle)
        diverged[w] = DIVERGED_NONFINITE
        frozen[w] = 1
    else:
        for gi in range(L):
            rate = un[6 + gi]
            ang = state.coord[w, gi] + dt * rate
            state.coord[w, gi] = ang - TWO_PI * wp.floor(ang / TWO_PI)
            state.coord_rate[w, gi] = rate
        state.position[w] = p
        state.orientation[w] = q
        state.velocity[w] = v
        state.angular_velocity[w] = om
        if wp.length(v) >= max_speed:
            diverged[w] = DIVERGED_FAST
            frozen[w] = 1


@wp.func
def left_here(state: TabulatedState, history: wp.array2d(dtype=float), w: int, L: int):
    """Whether world w's state is where its last Moreau-Jean step left it (not set between steps)."""
    same = True
    p = state.position[w]
    q = state.orientation[w]
    v = state.velocity[w]
    om = state.angular_velocity[w]
    for i in range(3):
        if p[i] != history[w, H_POSE + i] or v[i] != history[w, H_END + i] or om[i] != history[w, H_END + 3 + i]:
            same = False
    for i in range(4):
        if q[i] != history[w, H_POSE + 3 + i]:
            same = False
    for gi in range(L):
        if (state.coord[w, gi] != history[w, H_POSE + 7 + gi]
                or state.coord_rate[w, gi] != history[w, H_END + 6 + gi]):
            same = False
    return same


@wp.func
def integrate_midpoint(state: TabulatedState, history: wp.array2d(dtype=float), w: int, L: int, un: vecnv,
                       dt: float, max_speed: float, jolt: int, diverged: wp.array(dtype=wp.int32),
                       frozen: wp.array(dtype=wp.int32)):
    """Moreau-Jean's second half step: the state holds the midpoint pose (the set-up moved it there),
    q+ = q_mid + dt/2 u+ (the orientation by the exponential map, the driving coordinates wrapped to
    [0, 2 pi)); the history keeps the step's end (jolt: a contact impulse moved the rates, so the
    next step does not extrapolate from this one). A non-finite world is flagged, put back at the
    pose it started from and frozen; a too fast one flagged after the step and frozen."""
    half = 0.5 * dt
    v = wp.vec3(un[0], un[1], un[2])
    om = wp.vec3(un[3], un[4], un[5])
    p, q, ok = base_advanced(state.position[w], state.orientation[w], un, L, half)
    if not ok:  # frozen at the pose the step started from, with its rates (never moved)
        diverged[w] = DIVERGED_NONFINITE
        frozen[w] = 1
        state.position[w] = wp.vec3(history[w, H_POSE], history[w, H_POSE + 1], history[w, H_POSE + 2])
        state.orientation[w] = wp.quat(history[w, H_POSE + 3], history[w, H_POSE + 4], history[w, H_POSE + 5],
                                       history[w, H_POSE + 6])
        for gi in range(L):
            state.coord[w, gi] = history[w, H_POSE + 7 + gi]
    else:
        for gi in range(L):
            rate = un[6 + gi]
            ang = state.coord[w, gi] + half * rate
            ang = ang - TWO_PI * wp.floor(ang / TWO_PI)
            state.coord[w, gi] = ang
            state.coord_rate[w, gi] = rate
            history[w, H_POSE + 7 + gi] = ang
            history[w, H_END + 6 + gi] = rate
            if jolt != 0:
                history[w, H_PREV + 6 + gi] = rate
        state.position[w] = p
        state.orientation[w] = q
        state.velocity[w] = v
        state.angular_velocity[w] = om
        for i in range(3):
            history[w, H_POSE + i] = p[i]
            history[w, H_END + i] = v[i]
            history[w, H_END + 3 + i] = om[i]
            if jolt != 0:
                history[w, H_PREV + i] = v[i]
                history[w, H_PREV + 3 + i] = om[i]
        for i in range(4):
            history[w, H_POSE + 3 + i] = q[i]
        if wp.length(v) >= max_speed:
            diverged[w] = DIVERGED_FAST
            frozen[w] = 1


@wp.func
def contact_rows(J: wp.array2d(dtype=float), rows: wp.array2d(dtype=wp.vec4), slot_of: wp.array2d(dtype=wp.int32),
                 w: int, m: int, n: int, k: int, arm: wp.vec3, lin: wp.vec3, grp: int, mu: float, dist: float,
                 uf: vecnv, dt: float, stabilization: float, normal: wp.vec3, t1: wp.vec3, t2: wp.vec3):
    """Slot k's contact triplet (normal, then the tangents t1 and t2; on flat ground z, x and y) as
    rows m, m + 1, m + 2: their J, free velocity (the normal's with the gap closed over the step, or
    the stabilization's share of the penetration) and fields; returns the next row."""
    for comp in range(3):
        nrm = normal
        if comp == 1:
            nrm = t1
        if comp == 2:
            nrm = t2
        rxn = wp.cross(arm, nrm)
        for c in range(NV):
            J[w, m * NV + c] = 0.0
        for i in range(3):
            J[w, m * NV + i] = nrm[i]
            J[w, m * NV + 3 + i] = rxn[i]
        if grp >= 0:
            J[w, m * NV + 6 + grp] = wp.dot(nrm, lin)
        vrow = jrow_dot(J, w, m, n, uf)
        if comp == 0:
            if dist > 0.0:
                vrow += dist / dt
            else:
                vrow += stabilization * dist / dt
        set_row(rows, w, m, F_R, 0.0)
        set_row(rows, w, m, F_RHS, vrow)
        set_row(rows, w, m, F_MU, mu)
        set_row(rows, w, m, F_COL, float(6 + grp))  # -1 + 6 < 6 for a base slot
        slot_of[w, m] = MAX_GROUPS + 3 * k + comp
        m += 1
    return m


@wp.func
def precondition_pass(J: wp.array2d(dtype=float), Jc: wp.array2d(dtype=wp.vec4), rows: wp.array2d(dtype=wp.vec4),
                      s1: wp.array2d(dtype=wp.vec4), s2: wp.array2d(dtype=wp.vec4), LM: wp.array2d(dtype=float),
                      impulse: wp.array2d(dtype=float), slot_of: wp.array2d(dtype=wp.int32), w: int, n: int,
                      L: int, units: int, rho0: float, lane: int, lanes: int):
    """This lane's units: the Jacobi preconditioner P = diag(J M^-1 J^T + R)^-1/2 (one value per
    contact triplet; LM holds the factor of M), the compact copy of the preconditioned rows, and the
    warm start y from the last step's impulses by slot; returns the lane's share of J^T y. A drive
    row whose warm start lies within half its bounds is flagged free (F_FREE): its penalty stays at
    or below rho0 (its projection is then the identity, and a large penalty only slows it)."""
    gyl = vecnv()
    unit = lane
    while unit < units:
        r, span = unit_rows(unit, L)
        dsum = float(0.0)
        for rr in range(r, r + span):
            jr = vecnv()
            for c in range(NV):
                jr[c] = J[w, rr * NV + c]
            first = int(0)  # a drive row: zero before its sub-chain column
            if row_at(rows, w, rr, F_MU) < 0.0:
                first = int(row_at(rows, w, rr, F_COL))
            dsum += forward_norm2(LM, w, n, jr, first) + row_at(rows, w, rr, F_R)
        pr = 1.0 / wp.sqrt(wp.max(dsum / float(span), 1.0e-12))
        xs = wp.vec3()
        for c in range(span):
            rr = r + c
            set_row(rows, w, rr, F_P, pr)
            set_row(rows, w, rr, F_RHS, pr * row_at(rows, w, rr, F_RHS))
            set_row(rows, w, rr, F_LO, row_at(rows, w, rr, F_LO) / pr)
            set_row(rows, w, rr, F_HI, row_at(rows, w, rr, F_HI) / pr)
            set_row(rows, w, rr, F_PEN, rho0)
            for k in range(NV):
                J[w, rr * NV + k] = pr * J[w, rr * NV + k]
            col = int(row_at(rows, w, rr, F_COL))
            driving = float(0.0)
            for k in range(6, NV):
                if k == col:
                    driving = J[w, rr * NV + k]
            row0 = rr * NV
            Jc[w, 2 * rr] = wp.vec4(J[w, row0], J[w, row0 + 1], J[w, row0 + 2], J[w, row0 + 3])
            Jc[w, 2 * rr + 1] = wp.vec4(J[w, row0 + 4], J[w, row0 + 5], driving, 0.0)
            xs[c] = impulse[w, slot_of[w, rr]] / pr
        pj = project_row(rows, w, r, xs[0], xs[1], xs[2])
        for c in range(span):
            s1[w, r + c] = wp.vec4(xs[c], xs[c], 0.0, 0.0)
            s2[w, r + c] = wp.vec4(pj[c], 0.0, pj[c], 0.0)  # y and its last value; z below
            for k in range(NV):
                gyl[k] += J[w, (r + c) * NV + k] * pj[c]
        free = float(0.0)
        if span == 1 and wp.abs(xs[0]) < 0.5 * row_at(rows, w, r, F_HI):
            free = 1.0
        set_row(rows, w, r, F_FREE, free)
        unit += lanes
    return gyl


@wp.func
def warm_dual_pass(J: wp.array2d(dtype=float), rows: wp.array2d(dtype=wp.vec4), s1: wp.array2d(dtype=wp.vec4),
                   s2: wp.array2d(dtype=wp.vec4), w: int, n: int, L: int, units: int, my: vecnv, lane: int,
                   lanes: int):
    """This lane's units: the dual variable from the warm start, z = -(D y + v_f + s), the (De Saxce
    shifted) velocity it gives (my = M^-1 J^T y), so that an unchanged contact set starts at its
    fixed point."""
    unit = lane
    while unit < units:
        r, span = unit_rows(unit, L)
        vels = wp.vec3()
        for c in range(span):
            i = r + c
            pr = row_at(rows, w, i, F_P)
            vc = (jrow_dot(J, w, i, n, my) + pr * pr * row_at(rows, w, i, F_R) * s2[w, i][0]
                  + row_at(rows, w, i, F_RHS))
            prior = s1[w, i]
            s1[w, i] = wp.vec4(prior[0], prior[1], vc, prior[3])
            vels[c] = vc
        shift = float(0.0)
        if span == 3:
            shift = row_at(rows, w, r, F_MU) * wp.sqrt(vels[1] * vels[1] + vels[2] * vels[2])
        for c in range(span):
            zc = -vels[c]
            if c == 0:
                zc -= shift
            prior = s2[w, r + c]
            s2[w, r + c] = wp.vec4(prior[0], zc, prior[2], zc)
        unit += lanes


@functools.cache
def step_kernel(tiled: bool, phase: str = "all", registers: int | None = None, midpoint: bool = False,
                forces: bool = False, controlled: bool = False, relief: bool = False):
    """The step kernel: tiled (launch_tiled, one block of lanes per world, lanes sharing the
    PADMM rows) or one thread per world (wp.launch; no block operations). phase: the whole step
    ("all"), or its set-up (through the warm start, "setup") and the Woodbury factor, the PADMM
    iterations and the integration ("solve") as two kernels, each with the registers it needs.
    registers: at most this many registers per thread on CUDA (None: the compiler's choice; see
    TILED_REGISTERS). midpoint: the Moreau-Jean step (False: semi-implicit Euler): the set-up moves
    the pose to q_mid = q + dt/2 u (the state holds it until the step's end), evaluates M, the bias
    forces and the contacts there with the rates extrapolated to the midpoint, u + (u - u_last) / 2
    (the step's own rates on a trajectory's first step, where the state was set between steps or a
    contact impulse moved the last step's rates: left_here, history), and the integration ends at
    q+ = q_mid + dt/2 u+ (integrate_midpoint). No second pass of the dynamics. forces, controlled:
    the force elements' and a Control's generalized forces (tabulated_forces.applied_forces) join the
    bias forces there, compiled in only where the batch has them. relief: some world's ground has
    relief (on_relief; without, its code is compiled out)."""

    @wp.func
    def sync():
        """Barrier of the world's lanes (tiled only)."""
        if wp.static(tiled):
            block_sync()

    @wp.func
    def reduce_vector(value: Any):
        """Sum of a vector over the world's lanes, in one reduction."""
        if wp.static(tiled):
            return wp.tile_extract(wp.tile_reduce(wp.add, wp.tile(value, preserve_type=True)), 0)
        return value

    @wp.func
    def reduce_stats(value: vecstats):
        """An iteration's statistics over the world's lanes (max4_sum1), in one reduction."""
        if wp.static(tiled):
            return wp.tile_extract(wp.tile_reduce(max4_sum1, wp.tile(value, preserve_type=True)), 0)
        return value

    @wp.func
    def woodbury_factor(J: wp.array2d(dtype=float), rows: wp.array2d(dtype=wp.vec4), M: wp.array2d(dtype=float),
                        K: wp.array2d(dtype=float), Kinv: wp.array2d(dtype=wp.vec4), w: int, m: int, n: int,
                        sigma_base: float, tmp: wp.array2d(dtype=float), lane: int, lanes: int):
        """Kinv <- (M + J^T S^-1 J)^-1 (K holds its Cholesky factor on the way; the rows' 1 / S go
        to their field F_INV and to tmp). The lanes share the rows, then the matrix's entries, then
        the inverse's columns; lane 0 factors. Every lane of the block must call it."""
        for r in range(lane, m, lanes):
            p = row_at(rows, w, r, F_P)
            inverse = 1.0 / (sigma_base + penalty(rows, w, r) + p * p * row_at(rows, w, r, F_R))
            tmp[w, r] = inverse
            set_row(rows, w, r, F_INV, inverse)
        sync()
        entries = n * (n + 1) / 2
        for e in range(lane, entries, lanes):
            i = int((wp.sqrt(8.0 * float(e) + 1.0) - 1.0) * 0.5)
            while i * (i + 1) / 2 > e:
                i -= 1
            while (i + 1) * (i + 2) / 2 <= e:
                i += 1
            j = e - i * (i + 1) / 2
            acc = M[w, i * NV + j]
            for r in range(m):
                acc += J[w, r * NV + i] * J[w, r * NV + j] * tmp[w, r]
            K[w, i * NV + j] = acc
        sync()
        if lane == 0:
            cholesky(K, w, n, K)  # in place: each entry is read before it is overwritten
        sync()
        for j in range(lane, NV, lanes):
            col = vecnv()
            if j < n:
                col[j] = 1.0
                col = chol_solve(K, w, n, col)
            for kv in range(KINV_VECS):  # symmetric: column j is row j, written whole by its lane
                part = wp.vec4()
                for t in range(4):
                    if 4 * kv + t < NV:
                        part[t] = col[4 * kv + t]
                Kinv[w, j * KINV_VECS + kv] = part
        sync()

    @wp.kernel(enable_backward=False, module="unique", cuda_max_registers=registers)
    def tabulated_step(
        dt: float, eta: float, rho0: float, tolerance: float, relative_tolerance: float, max_iterations: int,
        rho_update_interval: int, margin: float, stabilization: float, max_speed: float,
        worlds: TabulatedWorlds, state: TabulatedState, impulse: wp.array2d(dtype=float),
        frozen: wp.array(dtype=wp.int32), diverged: wp.array(dtype=wp.int32),
        # out
        iterations_out: wp.array(dtype=wp.int32), contacts_out: wp.array(dtype=wp.int32),
        drive_torque: wp.array2d(dtype=float),
        # scratch
        J: wp.array2d(dtype=float), Jc: wp.array2d(dtype=wp.vec4), rows: wp.array2d(dtype=wp.vec4),
        M: wp.array2d(dtype=float), LM: wp.array2d(dtype=float), K: wp.array2d(dtype=float),
        s1: wp.array2d(dtype=wp.vec4), s2: wp.array2d(dtype=wp.vec4), tmp: wp.array2d(dtype=float),
        slot_of: wp.array2d(dtype=wp.int32), row_count: wp.array(dtype=wp.int32), ufree: wp.array2d(dtype=float),
        Kinv: wp.array2d(dtype=wp.vec4), history: wp.array2d(dtype=float),
        # force elements and a Control (read only where compiled in: forces, controlled)
        fo: TabulatedForces, body_f: wp.array2d(dtype=wp.spatial_vector), joint_effort: wp.array2d(dtype=float),
    ):
        """One step of every world (a block of lanes or one thread per world): mass matrix and bias
        forces, free velocity, drive and contact rows, preconditioned PADMM with Woodbury solves,
        velocity update and integration; a non-finite or too fast world is flagged diverged (its
        code) and frozen."""
        if wp.static(tiled):
            w, lane = wp.tid()
            lanes = wp.block_dim()
        else:
            w = wp.tid()
            lane = 0
            lanes = 1
        if frozen[w] != 0:
            return
        L = worlds.group_count[w]
        n = 6 + L
        if wp.static(phase != "solve"):
            # set-up: every sub-chain's column of M and its share of the base blocks and bias forces, one
            # sub-chain per lane (summed over the lanes as one vector); then on lane 0 the base blocks, the
            # factor of M, the free velocity and the rows
            p = state.position[w]
            q = state.orientation[w]
            v = state.velocity[w]
            om = state.angular_velocity[w]
            half = float(0.0)  # Moreau-Jean: the pose advanced by half the step, rates extrapolated by ext
            ext = float(0.0)
            om_e = om  # the base's angular velocity in the gyroscopic terms
            if wp.static(midpoint):
                half = 0.5 * dt
                if left_here(state, history, w, L):  # (every lane alike)
                    ext = 0.5
                    om_e = om + ext * (om - wp.vec3(history[w, H_PREV + 3], history[w, H_PREV + 4],
                                                    history[w, H_PREV + 5]))
                p = p + half * v
                spin = wp.length(om)
                if spin > 1.0e-12:
                    q = wp.normalize(wp.quat_from_axis_angle(om / spin, spin * half) * q)
            R = wp.quat_to_matrix(q)
            axis = -(R * wp.vec3(0.0, 1.0, 0.0))
            g = worlds.gravity[w]
            mb = worlds.base[w][0]
            for i in range(lane, NV * NV, lanes):
                M[w, i] = 0.0
            sync()
            part = chain_columns(worlds, state, M, w, L, R, axis, om_e, g, lane, lanes, wp.static(int(midpoint)),
                                 half, ext, history)
            total = reduce_vector(part)
            sync()  # every lane's sub-chain columns are in M
            if lane == 0:
                h = vecnv()
                It = R * worlds.base_inertia[w] * wp.transpose(R)
                gyro = -wp.cross(om_e, It * om_e)
                for i in range(3):
                    h[i] = mb * g[i] + total[13 + i]
                    h[3 + i] = gyro[i] + total[16 + i]
                for c in range(MAX_GROUPS):
                    h[6 + c] = total[19 + c]
                if wp.static(forces or controlled):  # at the pose and rates of the velocity products
                    ue = vecnv()
                    for i in range(3):
                        ue[i] = v[i]
                        ue[3 + i] = om_e[i]
                        if ext != 0.0:
                            ue[i] = v[i] + ext * (v[i] - history[w, H_PREV + i])
                    for gi in range(L):
                        rate = state.coord_rate[w, gi]
                        ue[6 + gi] = rate
                        if ext != 0.0:
                            ue[6 + gi] = rate + ext * (rate - history[w, H_PREV + 6 + gi])
                    h = h + applied_forces(worlds, state, fo, w, p, q, ue, half, wp.static(int(forces)),
                                           wp.static(int(controlled)), body_f, joint_effort)
                m_sum = mb + total[0]
                md_sum = wp.vec3(total[1], total[2], total[3])
                rot_sum = It + wp.mat33(total[4], total[5], total[6], total[7], total[8], total[9], total[10],
                                        total[11], total[12])
                # M_vv = m I, M_vw = -[sum m d]x, M_ww = the angular sum
                cross = wp.skew(md_sum)
                for i in range(3):
                    M[w, i * NV + i] = m_sum
                    for j in range(3):
                        M[w, i * NV + 3 + j] = -cross[i, j]
                        M[w, (3 + i) * NV + j] = cross[i, j]
                        M[w, (3 + i) * NV + 3 + j] = rot_sum[i, j]
                cholesky(M, w, n, LM)
                uu = vecnv()
                for i in range(3):
                    uu[i] = v[i]
                    uu[3 + i] = om[i]
                for gi in range(L):
                    uu[6 + gi] = state.coord_rate[w, gi]
                acc_free = chol_solve(LM, w, n, h)
                uf = uu + dt * acc_free
                # rows: drives, then contacts within the margin
                m = int(0)
                for gi in range(L):
                    dr = worlds.drive[w, gi]
                    for c in range(NV):
                        J[w, m * NV + c] = 0.0
                    J[w, m * NV + 6 + gi] = 1.0
                    kd = dr[1]
                    bound = dt * dr[2]
                    compliance = 1.0e6
                    if kd > 0.0:
                        compliance = 1.0 / (dt * kd)
                    set_row(rows, w, m, F_R, compliance)
                    set_row(rows, w, m, F_RHS, uf[6 + gi] - dr[0] * wp.min(1.0, kd * 1.0e6))
                    set_row(rows, w, m, F_MU, -1.0)
                    set_row(rows, w, m, F_LO, -bound)
                    set_row(rows, w, m, F_HI, bound)
                    set_row(rows, w, m, F_COL, float(6 + gi))
                    slot_of[w, m] = gi
                    m += 1
                count = int(0)
                if worlds.base[w][1] > 0.0:
                    for k in range(BASE_SLOTS + 2 * L):
                        arm, lin, grp, mu, dist, radius = slot_point(worlds, state, w, k, R, p, axis,
                                                                     wp.static(int(midpoint)), half)
                        normal = wp.vec3(0.0, 0.0, 1.0)
                        t1 = wp.vec3(1.0, 0.0, 0.0)
                        t2 = wp.vec3(0.0, 1.0, 0.0)
                        if wp.static(relief):  # the relief's tangent plane below the slot
                            arm, dist, normal = on_relief(worlds.relief[w], p, arm, dist, radius)
                            t1 = wp.normalize(t1 - normal[0] * normal)
                            t2 = wp.cross(normal, t1)
                        if dist < margin:
                            count += 1
                            m = contact_rows(J, rows, slot_of, w, m, n, k, arm, lin, grp, mu, dist, uf, dt,
                                             stabilization, normal, t1, t2)
                contacts_out[w] = count
                for c in range(NV):
                    ufree[w, c] = uf[c]
                row_count[w] = m
                if wp.static(midpoint):
                    # the step's start into the history (the next step's u_last; the pose, for a
                    # diverged step's restore) and the midpoint pose into the state, to the step's end
                    for i in range(3):
                        history[w, H_PREV + i] = v[i]
                        history[w, H_PREV + 3 + i] = om[i]
                        history[w, H_POSE + i] = state.position[w][i]
                    q0 = state.orientation[w]
                    for i in range(4):
                        history[w, H_POSE + 3 + i] = q0[i]
                    for gi in range(L):
                        rate = state.coord_rate[w, gi]
                        history[w, H_PREV + 6 + gi] = rate
                        history[w, H_POSE + 7 + gi] = state.coord[w, gi]
                        state.coord[w, gi] = state.coord[w, gi] + half * rate
                    state.position[w] = p
                    state.orientation[w] = q
            sync()
            m = row_count[w]
            units = L + (m - L) / 3
            # the preconditioner and the warm start (y, then z), unit by unit over the lanes
            gy = reduce_vector(precondition_pass(J, Jc, rows, s1, s2, LM, impulse, slot_of, w, n, L, units, rho0,
                                                 lane, lanes))
            my = chol_solve(LM, w, n, gy)
            warm_dual_pass(J, rows, s1, s2, w, n, L, units, my, lane, lanes)
        if wp.static(phase == "setup"):
            return
        m = row_count[w]  # (again, for the solve phase's kernel)
        units = L + (m - L) / 3
        rho = rho0
        its = int(0)
        converged = int(0)
        momentum = float(1.0)
        merit = float(1.0e30)
        beta = float(0.0)
        refactor = int(1)  # the Woodbury factor at the first iteration and after a new penalty
        while its < max_iterations and converged == 0 and m > 0:
            if refactor != 0:
                # one call site: the factor's code is large, and a second inlined copy costs the
                # instruction cache more than the branch costs
                sync()  # every lane is done with the rows (their set-up or the new penalties)
                woodbury_factor(J, rows, M, K, Kinv, w, m, n, eta, tmp, lane, lanes)
                refactor = 0
            # each lane takes units (a drive row or a contact triplet) lane, lane + lanes, ...; a row's
            # PADMM state is two vec4, (x, x before, its velocity at x, t) and (y, z, y and z before),
            # loaded once per pass and stored once (by the second pass, which recomputes b and t)
            gl = rhs_pass(Jc, rows, s1, s2, w, L, units, beta, eta, lane, lanes)
            # Woodbury: x = t - S^-1 J (M + J^T S^-1 J)^-1 J^T t
            yv = woodbury_apply(Kinv, w, n, reduce_vector(gl), lane, lanes)
            stats = reduce_stats(update_pass(Jc, rows, s1, s2, w, L, units, beta, eta, yv, lane, lanes))
            rp = stats[0]
            rd = stats[1]
            rn = stats[2]
            ymax = stats[3]
            change = stats[4]
            its += 1
            tol = tolerance + relative_tolerance * ymax
            if rp < tol and rd < tol and rn < tol:
                converged = 1
            else:
                beta = 0.0
                if change < 0.999 * merit:
                    a_next = 0.5 * (1.0 + wp.sqrt(1.0 + 4.0 * momentum * momentum))
                    beta = (momentum - 1.0) / a_next
                    momentum = a_next
                else:
                    momentum = 1.0
                merit = change
                if its % rho_update_interval == 0:
                    new_rho = rho
                    if rp > 10.0 * rd:
                        new_rho = wp.min(rho * 4.0, 1.0e3)
                    elif rd > 10.0 * rp:
                        new_rho = wp.max(rho / 4.0, 1.0e-5)
                    if new_rho != rho:
                        sync()  # every lane is done with the rows and the inverse
                        if lane == 0:
                            set_penalties(rows, w, m, new_rho, rho0)
                            for i in range(m):  # z is the unscaled multiplier: it stays; the momentum restarts
                                prior = s2[w, i]
                                s2[w, i] = wp.vec4(prior[0], prior[1], prior[0], prior[1])
                        refactor = 1  # at the next iteration, if there is one
                        rho = new_rho
                        momentum = 1.0
                        merit = 1.0e30
                        beta = 0.0
        sync()
        # the impulses by slot and J^T lambda, the rows over the lanes (summed as one vector); then
        # the velocity update and the integration on lane 0
        for i in range(lane, MAX_ROWS, lanes):
            impulse[w, i] = 0.0
        sync()
        jl = vecnv()
        for r in range(lane, m, lanes):
            yr = s2[w, r][0]
            f0 = rows[w, ROW_VECS * r]
            impulse[w, slot_of[w, r]] = yr * row_at(rows, w, r, F_P)
            # the compact rows are preconditioned: J~^T y = J^T lambda
            jl = row_add(Jc, w, r, f0[F_MU] >= 0.0, int(row_at(rows, w, r, F_COL)), yr, jl)
        jl = reduce_vector(jl)
        if lane != 0:
            return
        iterations_out[w] = its
        uf = vecnv()
        for c in range(NV):
            uf[c] = ufree[w, c]
        un = uf + chol_solve(LM, w, n, jl)
        for gi in range(L):
            drive_torque[w, gi] = impulse[w, gi] / dt
        if wp.static(midpoint):
            jolt = int(0)  # a contact impulse moved the rates: the next step does not extrapolate
            for r in range(L, m):
                if s2[w, r][0] != 0.0:
                    jolt = 1
            integrate_midpoint(state, history, w, L, un, dt, max_speed, jolt, diverged, frozen)
        else:
            integrate(state, w, L, un, dt, max_speed, diverged, frozen)

    return tabulated_step

