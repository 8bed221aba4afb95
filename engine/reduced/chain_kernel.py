"""The step kernel of closed chains in reduced coordinates (engine.reduced.chains): a whole step
of a world in one thread block (chain_step_kernel), compiled per batch shape: its shared tiles
sized to the batch's largest world, and the code a batch does not need (contacts, an unrolled
prefix, inline loops, stage clocks) left out.

Why one kernel: the step is bound by latency, not bandwidth; one launch keeps a world's matrices
and factors on chip between stages. Measurements: benchmarks/results/README.md, "Reduced closed
chains: design notes".
"""

import functools

import warp as wp

from engine.contacts import contact_direction
from engine.linalg.lanes import block_sync, tile_set
from engine.padmm import project_cone, rho_update
from engine.reduced.chain_layout import KIND_REVOLUTE, KIND_ROOT, MAX_PREFIX, TILE_STEP, _tile_size
from engine.reduced.chain_stages import (DIVERGED, DYNAMICS, EFFORT_LIMIT, VELOCITIES, ChainArrays, ChainLoads,
                                         ChainWork, NoLoads, add_children, advance, angle_low, apply_control, apply_forces, body_out,
                                         candidates_within, contact_factor, contact_residuals, factor_lanes,
                                         keep_angle_low, kinematics, left_here, loop_errors, loop_row_bias,
                                         loop_rows_of, own_terms, plane_candidates, project, solve_column, solve_lanes,
                                         stamp, tree_factor, tree_solves)
from engine.spatial import two_sum

wp.set_module_options({"enable_backward": False})  # no gradients are taken: compile the forward code only

__all__ = ["CHAIN_BLOCK", "MAX_REGISTERS", "chain_step_kernel"]

REGULARIZATION = wp.constant(1.0e-6)  # relative diagonal shift of the loops' matrix (rounding guard)
CHAIN_BLOCK = 32  # threads per world on a GPU: one warp
# registers per thread on CUDA: 128 lets 16 blocks (worlds) share an SM (measured, with CHAIN_BLOCK:
# benchmarks/results/README.md, "Reduced closed chains: design notes")
MAX_REGISTERS = 128


@functools.cache
def chain_step_kernel(coords: int, rows: int, contacts: int = 0, slots: int = TILE_STEP,
                      registers: int | None = MAX_REGISTERS, packed_size: int = TILE_STEP,
                      stages: bool = False, unroll: int = MAX_PREFIX, handover: int = 0, inline: bool = False,
                      forces: bool = False, control: bool = False):
    """The step kernel with shared tiles sized by coords (tree coordinates, at least MAX_PREFIX),
    rows (kept loop rows), contacts (contact rows; 0: no contact code), slots (candidate contacts)
    and packed_size (the packed mass matrix), each a multiple of TILE_STEP (coords may be MAX_PREFIX
    instead), and at most ``registers`` registers per thread on CUDA.
    stages: lane 0 writes a clock reading at the end of each of STAGES into work.stage_clock (the
    same step otherwise; without it the readings are compiled out). unroll: the longest prefix
    (ChainArrays.prefix) the tree solves take unrolled (tree_solves; 0: none, every prefix read as 0).
    handover (ChainModel.contact_working): 0 the only kernel of a step; 1 the first of two, handing a
    world that finds more contacts than its tiles hold to 2, the second, which steps only those
    (the code of each role compiled only into its kernel). inline: some world has an inline loop
    (loop_rows_of; without, its code is compiled out). forces: some world has force elements
    (apply_forces; without, their code is compiled out). control: the step reads a Control's
    body_f (W, B) and joint_effort (W, J) every step (apply_control; without, its code is compiled
    out). The loads argument is a ChainLoads where either is compiled in, else NoLoads.

    The step, one thread block per world (the lanes share each stage, a barrier between stages; on
    the CPU a block is one thread): (1) Moreau-Jean: q += dt/2 u first; (2) kinematics level by
    level of the tree; (3) composite rigid-body sums up the tree (the force elements' and the
    Control's wrenches added to their bodies' first, at the evaluation poses), the mass matrix and
    generalized forces; (4) damping and PD drives implicit, M~ = M + dt C packed and factored along the tree
    (no fill); (5) the loops' rows G, X = M~^-1 G^T, A = G X factored: the loops' velocity
    constraint holds exactly; (6) contacts (compiled only with shapes): rows with the loops held,
    PADMM (engine.padmm's method) warm-started from each slot's last impulse and the world's last
    penalty; (7) q += h u and Gauss-Newton projections onto the loops, skipped below the rounding
    floors; (8) body poses and velocities, and the divergence guard. Each stage in full:
    benchmarks/results/README.md, "Engine design notes (moved from the code)".

    The midpoint step is second order on passive mechanisms (benchmarks/convergence.py): its
    velocity-product and gyroscopic terms take the midpoint's rates, extrapolated from the last
    step's change (u + (u - u_last) / 2; the step's own rates on a trajectory's first step, after
    contact impulses and where the state was set between steps, see left_here), and the loops' rows
    ask G(q_mid) u+ = -dt/2 d/dt(G) u (loop_row_bias), the rates tangent to the loops where the step
    ends rather than at its midpoint (which lost energy steadily and was first order). The angles
    are summed compensated across steps (angle_low). The drives' and damping terms stay backward
    (stable for stiff drives): first order in dt wherever those matter, as is semi-implicit Euler."""

    per_contact = _tile_size(contacts // 3)  # the tiles of one entry per contact
    Loads = ChainLoads if forces or control else NoLoads  # the loads argument's type (ChainModel.loads_for)
    tree_solve_column, tree_solve_vector = tree_solves(unroll)
    # tile_matmul: Warp's register-blocked scalar product (against cuBLASDx: benchmarks/results/README.md,
    # "Reduced closed chains: design notes")
    @wp.kernel(enable_backward=False, module="unique", cuda_max_registers=registers,
               module_options={"enable_mathdx_gemm": False})
    def chain_step_body(m: ChainArrays, w: ChainWork, loads: Loads, dt: float, baumgarte: float, iterations: int, max_speed: float,
                        midpoint: int, record: int, margin: float, stabilization: float, eta: float, rho0: float,
                        adaptive: int, rho_interval: int, tolerance: float, relative_tolerance: float,
                        max_iterations: int, skip_floor: float, skip_floor_angular: float, working: int,
                        q: wp.array2d(dtype=float), u: wp.array2d(dtype=float),
                        root: wp.array2d(dtype=wp.transform), body_q: wp.array2d(dtype=wp.transform),
                        body_qd: wp.array2d(dtype=wp.spatial_vector)):
        world, lane = wp.tid()
        lanes = wp.block_dim()
        if wp.static(handover == 2):  # the full-capacity kernel steps only the worlds the first one handed over
            if w.contact_overflow[world] == 0:
                return
        Mt = wp.tile_zeros(shape=packed_size, dtype=float, storage="shared")  # M~, then its factor (packed)
        # G, then J, then (D + (eta + rho) I)^-1
        Gt = wp.tile_zeros(shape=(wp.static(max(rows, contacts)), wp.static(max(coords, contacts))), dtype=float,
                           storage="shared")
        Xt = wp.tile_zeros(shape=(coords, rows), dtype=float, storage="shared")  # X = M~^-1 G^T
        At = wp.tile_zeros(shape=(rows, rows), dtype=float, storage="shared")  # A = G X, then its factor
        diag_a = wp.tile_zeros(shape=rows, dtype=float, storage="shared")
        vec = wp.tile_zeros(shape=coords, dtype=float, storage="shared")  # dt tau, then du = M~^-1 dt tau
        rhs = wp.tile_zeros(shape=rows, dtype=float, storage="shared")
        sizes = wp.tile_zeros(shape=rows, dtype=float, storage="shared")  # the projections' check
        # the tree's parents: the solves and the factor walk them in dependent steps (shared: no
        # global load on that path)
        par = wp.tile_zeros(shape=coords, dtype=wp.int32, storage="shared")
        lvl = wp.tile_zeros(shape=coords, dtype=wp.int32, storage="shared")  # ancestors (of the entry)
        rstart = wp.tile_zeros(shape=coords, dtype=wp.int32, storage="shared")  # packed M~'s row starts
        moved = wp.tile_zeros(shape=1, dtype=wp.int32, storage="shared")  # 1: not where the last step left it
        low = wp.tile_zeros(shape=coords, dtype=float, storage="shared")  # the angles' low parts (Moreau-Jean)
        if wp.static(contacts > 0):  # per entry: the contacts' rate change (its next extrapolation leaves it out)
            jolt = wp.tile_zeros(shape=coords, dtype=float, storage="shared")
        if wp.static(handover == 1):  # u_start as the last step left it, put back for the kernel taking over
            history = wp.tile_zeros(shape=coords, dtype=float, storage="shared")
        n = m.tree_count[world]
        for i in range(lane, n, lanes):
            tile_set(par, i, m.parent[world, i])
            tile_set(lvl, i, m.level[world, i])
            tile_set(rstart, i, m.row_start[world, i])
            if midpoint != 0 and not left_here(m, w, world, i, q, root):
                tile_set(moved, 0, 1)
        R = m.row_count[world]
        chain_prefix = int(0)
        if wp.static(unroll > 0):
            chain_prefix = m.prefix[world]
        depths = m.depth_count[world]
        frozen = w.diverged[world]
        block_sync()
        if wp.static(handover == 2):
            if lane == 0:  # (every lane has read the flag)
                w.contact_overflow[world] = 0
        if wp.static(stages):
            stamp(w, world, lane, 0)
        lead = dt  # q+ = q_eval + lead u+
        carried = int(0)  # Moreau-Jean continuing its own last step: the angles' low parts carry over
        extrapolate = float(0.0)  # the velocity-product terms' rates: u + extrapolate (u - u_last)
        if midpoint != 0:
            lead = 0.5 * dt
            if moved[0] == 0:  # (every lane alike)
                carried = 1
                extrapolate = 0.5  # the midpoint's rates, to second order, from the last step's change
        if frozen == 0:
            for i in range(lane, n, lanes):  # kept for a step that diverges; Moreau-Jean: to the midpoint
                if carried != 0:
                    tile_set(low, i, angle_low(m, w, world, i))
                w.q_start[world, i] = q[world, i]
                ui = u[world, i]  # u_start: the midpoint's rates until own_terms is done with them
                last = w.u_start[world, i]
                if wp.static(handover == 1):
                    tile_set(history, i, last)
                w.u_start[world, i] = ui + extrapolate * (ui - last)
                if m.kind[world, i] == KIND_ROOT:  # (an angle's entry keeps its low part there)
                    w.root_start[world, i] = root[world, i]
                if midpoint != 0:
                    advance(m, world, i, q, root, u, lead)
            block_sync()
            kinematics(m, w, world, lane, lanes, q, w.u_start, root, DYNAMICS)
            g = m.gravity[world]
            for k in range(lane, n, lanes):
                own_terms(m, w, world, k, g)
                w.u_start[world, k] = u[world, k]  # the step's initial rates again (a frozen world's restore)
            block_sync()
            if wp.static(forces):  # the force elements onto their bodies' own terms, one lane
                if lane == 0:
                    apply_forces(loads, w, world)
                block_sync()
            if wp.static(control):  # a Control's body wrenches and joint efforts, one lane
                if lane == 0:
                    apply_control(loads, w, world)
                block_sync()
            if wp.static(stages):
                stamp(w, world, lane, 1)
            for step in range(depths - 1):  # subtree sums, deepest parents first
                level = depths - 2 - step
                for t in range(m.depth_start[world, level] + lane, m.depth_start[world, level + 1], lanes):
                    add_children(m, w, world, m.by_depth[world, t])
                block_sync()
            for i in range(lane, n, lanes):  # per coordinate: its subtree's inertia applied to its motion, its force
                a = w.axis[world, i]
                s_lin = w.lin[world, i]
                b = m.sub_of[world, i]
                cm = w.sub_mass[world, b]
                ch = w.sub_moment[world, b]
                w.force_n[world, i] = w.sub_inertia[world, b] * a + wp.cross(ch, s_lin)
                w.force_f[world, i] = cm * s_lin - wp.cross(ch, a)
                ui = u[world, i]
                tau = wp.dot(a, w.wrench_t[world, b]) + wp.dot(s_lin, w.wrench_f[world, b]) - m.damping[world, i] * ui
                tau += m.kp[world, i] * (m.q_target[world, i] - q[world, i] - lead * ui)
                tau += m.kd[world, i] * (m.v_target[world, i] - ui)
                tile_set(vec, i, dt * tau)
            loop_errors(m, w, world, lane, lanes)
            block_sync()
            if wp.static(stages):
                stamp(w, world, lane, 2)
            for i in range(lane, n, lanes):  # M~: row i against its ancestors j (packed: at rstart[i] + lvl[j])
                j = i
                e = rstart[i] + lvl[i]
                while j >= 0:
                    value = wp.dot(w.axis[world, j], w.force_n[world, i]) + wp.dot(w.lin[world, j], w.force_f[world, i])
                    if j == i:
                        value += m.armature[world, i] + dt * (m.damping[world, i] + m.kd[world, i]
                                                              + lead * m.kp[world, i])
                    tile_set(Mt, e, value)
                    if record != 0:
                        w.matrix[world, i, j] = value
                        w.matrix[world, j, i] = value
                    j = par[j]
                    e -= 1
            for r in range(lane, R, lanes):  # G along the two bodies' ancestors, and G^T into X
                rate = loop_rows_of(m, w, world, par, r, Gt, Xt, u, wp.static(int(inline)))  # (G u, for the rhs)
                if midpoint != 0 and m.row_part[world, r] < 5:  # a kept row: rates tangent where the step ends
                    rate += lead * loop_row_bias(m, w, world, r, wp.static(int(inline)))
                tile_set(rhs, r, rate)
            block_sync()
            if record != 0:
                for e in range(lane, R * n, lanes):
                    w.rows[world, e // n, e % n] = Gt[e // n, e % n]
            block_sync()
            if wp.static(stages):
                stamp(w, world, lane, 3)
            tree_factor(m, world, lane, lanes, lvl, rstart, n, Mt)
            if wp.static(stages):
                stamp(w, world, lane, 4)
            for col in range(lane, R + 1, lanes):  # X = M~^-1 G^T a column per lane, and du = M~^-1 (dt tau)
                if col < R:
                    tree_solve_column(par, lvl, rstart, n, chain_prefix, Mt, Xt, col)
                else:
                    tree_solve_vector(par, lvl, rstart, n, chain_prefix, Mt, vec)
            block_sync()
            if wp.static(stages):
                stamp(w, world, lane, 5)
            wp.tile_matmul(wp.tile_view(Gt, offset=(0, 0), shape=(rows, coords)), Xt, At, 1.0, 0.0)  # A = G X
            block_sync()
            for r in range(lane, R, lanes):  # (a soft row's compliance on its diagonal)
                tile_set(At, r, r, At[r, r] + m.row_compliance[world, r])
            block_sync()
            if wp.static(stages):
                stamp(w, world, lane, 6)
            for r in range(lane, R, lanes):  # the right-hand side: -(G u_f) - baumgarte phi / dt (+ keep G u)
                start = rhs[r]  # G u (u_f = u + du, du in vec; a soft row's armature keeps a share of G u)
                acc = start  # (a kept row's: G u + dt/2 its bias, loop_row_bias; its keep is 0)
                for j in range(n):
                    acc += Gt[r, j] * vec[j]
                tile_set(rhs, r, -acc + m.row_keep[world, r] * start
                         - baumgarte / dt * w.phi[world, 6 * m.row_loop[world, r] + m.row_part[world, r]])
            factor_lanes(lane, lanes, R, At, diag_a, REGULARIZATION)  # (At keeps A's factor to the step's end)
            solve_lanes(lane, lanes, R, At, diag_a, rhs)
            for i in range(lane, n, lanes):  # u = u_f + X A^-1 rhs (the change summed first: one rounding of u)
                acc = vec[i]
                for r in range(R):
                    acc += Xt[i, r] * rhs[r]
                u[world, i] = u[world, i] + acc
            block_sync()
            if wp.static(stages):
                stamp(w, world, lane, 7)
            if wp.static(contacts > 0):
                Yt = wp.tile_zeros(shape=(coords, contacts), dtype=float, storage="shared")  # M~^-1 J^T, then P J^T
                # G M~^-1 J^T, then D (upper triangle) and its factor
                Dt = wp.tile_zeros(shape=(wp.static(max(rows, contacts)), contacts), dtype=float, storage="shared")
                # per candidate slot: point (3), distance; then per contact: point, distance, friction, slot, entry
                cand = wp.tile_zeros(shape=(slots, 8), dtype=float, storage="shared")
                vf = wp.tile_zeros(shape=contacts, dtype=float, storage="shared")
                pre = wp.tile_zeros(shape=contacts, dtype=float, storage="shared")
                ddiag = wp.tile_zeros(shape=contacts, dtype=float, storage="shared")
                fdiag = wp.tile_zeros(shape=contacts, dtype=float, storage="shared")
                xs = wp.tile_zeros(shape=contacts, dtype=float, storage="shared")
                xn = wp.tile_zeros(shape=contacts, dtype=float, storage="shared")
                ys = wp.tile_zeros(shape=contacts, dtype=float, storage="shared")
                zs = wp.tile_zeros(shape=contacts, dtype=float, storage="shared")
                bs = wp.tile_zeros(shape=contacts, dtype=float, storage="shared")
                res_p = wp.tile_zeros(shape=per_contact, dtype=float, storage="shared")
                res_d = wp.tile_zeros(shape=per_contact, dtype=float, storage="shared")
                res_y = wp.tile_zeros(shape=per_contact, dtype=float, storage="shared")
                mus = wp.tile_zeros(shape=per_contact, dtype=float, storage="shared")  # friction per contact
                shapes = m.shape_count[world]
                nrm = m.ground_normal[world]
                off = m.ground_offset[world]
                for s in range(lane, shapes, lanes):  # candidates: a lane per shape, at the evaluation poses
                    plane_candidates(m, w, world, s, nrm, off, margin, cand)
                block_sync()
                if lane == 0:  # the contacts within the margin, in slot order, up to the capacity (rows of cand)
                    found = int(0)
                    if wp.static(handover == 1):
                        found = candidates_within(cand, shapes, margin)
                    if found > working and working < m.contact_capacity[world]:  # more than these tiles hold:
                        w.contact_overflow[world] = 1  # the full-capacity kernel takes the step over
                        w.contact_redone[world] = w.contact_redone[world] + 1
                    else:
                        count = int(0)
                        dropped = int(0)
                        for slot in range(4 * shapes):  # (row count <= slot: its columns 4-7 are free)
                            if cand[slot, 3] < margin:
                                if count < m.contact_capacity[world]:
                                    for f in range(4):
                                        tile_set(cand, count, 4 + f, cand[slot, f])
                                    w.contact_slot[world, count] = slot
                                    count += 1
                                else:
                                    dropped += 1
                                    w.contact_impulse[world, slot] = wp.vec3()
                            else:
                                w.contact_impulse[world, slot] = wp.vec3()
                        w.contact_count[world] = count
                        if count == 0:  # off the ground: the next contacts start from CONTACT_RHO
                            w.contact_rho[world] = 0.0
                        w.contact_dropped[world] = dropped
                        w.iterations[world] = 0
                block_sync()
                if wp.static(handover == 1):
                    if w.contact_overflow[world] != 0:  # handed over: the step's start restored, nothing else written
                        for i in range(lane, n, lanes):
                            q[world, i] = w.q_start[world, i]
                            u[world, i] = w.u_start[world, i]
                            w.u_start[world, i] = history[i]
                            if m.kind[world, i] == KIND_ROOT:
                                root[world, i] = w.root_start[world, i]
                        return
                if wp.static(stages):
                    stamp(w, world, lane, 8)
                nc = w.contact_count[world]
                m3 = 3 * nc
                if nc > 0:
                    for ct in range(lane, nc, lanes):  # J^T into Y: a lane per contact, along its body's ancestors
                        slot = w.contact_slot[world, ct]
                        x = wp.vec3(cand[ct, 4], cand[ct, 5], cand[ct, 6])
                        tile_set(mus, ct, m.shape_mu[world, slot // 4])
                        for part in range(3):
                            d = contact_direction(nrm, part)
                            j = m.shape_entry[world, slot // 4]
                            while j >= 0:
                                value = wp.dot(d, wp.cross(w.axis[world, j], x) + w.lin[world, j])
                                tile_set(Yt, j, 3 * ct + part, value)
                                j = par[j]
                    block_sync()
                    for col in range(lane, m3, lanes):  # Y = M~^-1 J^T
                        tree_solve_column(par, lvl, rstart, n, chain_prefix, Mt, Yt, col)
                    block_sync()
                    if wp.static(stages):
                        stamp(w, world, lane, 9)
                    wp.tile_matmul(wp.tile_view(Gt, offset=(0, 0), shape=(rows, coords)), Yt,  # G Y
                                   wp.tile_view(Dt, offset=(0, 0), shape=(rows, contacts)), 1.0, 0.0)
                    block_sync()
                    for col in range(lane, m3, lanes):  # A^-1 G Y, a column per lane
                        solve_column(R, At, diag_a, Dt, col)
                    block_sync()
                    # Y := Y - X A^-1 G Y = P J^T, P = M~^-1 - X A^-1 X^T
                    wp.tile_matmul(Xt, wp.tile_view(Dt, offset=(0, 0), shape=(rows, contacts)), Yt, -1.0, 1.0)
                    for e in range(lane, R * n, lanes):  # G is done with: its tile takes J (rows 0 .. m3)
                        tile_set(Gt, e // n, e % n, float(0.0))
                    block_sync()
                    if wp.static(stages):
                        stamp(w, world, lane, 10)
                    for ct in range(lane, nc, lanes):  # J, and v_f = J u + bias: a lane per contact
                        slot = w.contact_slot[world, ct]
                        x = wp.vec3(cand[ct, 4], cand[ct, 5], cand[ct, 6])
                        for part in range(3):
                            d = contact_direction(nrm, part)
                            acc = float(0.0)
                            j = m.shape_entry[world, slot // 4]
                            while j >= 0:
                                value = wp.dot(d, wp.cross(w.axis[world, j], x) + w.lin[world, j])
                                tile_set(Gt, 3 * ct + part, j, value)
                                acc += value * u[world, j]
                                j = par[j]
                            if part == 0:  # closing a gap d > 0 at most, a penetration pushed out by a share per step
                                dist = cand[ct, 7]  # (at the evaluation pose: the next one is a step of u+ away)
                                if dist > 0.0:
                                    acc += dist / dt
                                else:
                                    acc += stabilization * dist / dt
                            tile_set(vf, 3 * ct + part, acc)
                    block_sync()
                    wp.tile_matmul(wp.tile_view(Gt, offset=(0, 0), shape=(contacts, coords)), Yt,  # D = J P J^T
                                   wp.tile_view(Dt, offset=(0, 0), shape=(contacts, contacts)), 1.0, 0.0)
                    block_sync()
                    if wp.static(stages):
                        stamp(w, world, lane, 11)
                    for ct in range(lane, nc, lanes):  # Jacobi preconditioner, one scale per contact (cones keep)
                        mean = (Dt[3 * ct, 3 * ct] + Dt[3 * ct + 1, 3 * ct + 1] + Dt[3 * ct + 2, 3 * ct + 2]) / 3.0
                        scale = 1.0 / wp.sqrt(wp.max(mean, 1.0e-20))
                        for part in range(3):
                            tile_set(pre, 3 * ct + part, scale)
                    block_sync()
                    for e in range(lane, m3 * m3, lanes):
                        ra = e // m3
                        rb = e % m3
                        if rb >= ra:
                            tile_set(Dt, ra, rb, Dt[ra, rb] * pre[ra] * pre[rb])
                    for ct in range(lane, nc, lanes):  # warm start: the slot's last impulse
                        impulse = w.contact_impulse[world, w.contact_slot[world, ct]]
                        for part in range(3):
                            r = 3 * ct + part
                            tile_set(vf, r, vf[r] * pre[r])
                            tile_set(xs, r, impulse[part] / pre[r])
                            tile_set(ys, r, impulse[part] / pre[r])
                    block_sync()
                    for r in range(lane, m3, lanes):  # z = D x + v_f: the rows' velocity at the warm start
                        tile_set(ddiag, r, Dt[r, r])  # (a new contact's 0: its approach speed / rho would
                        acc = float(0.0)  # make the first projections' impulses huge, wrong if the cap stops them)
                        c0 = 3 * (r / 3)
                        if xs[c0] != 0.0 or xs[c0 + 1] != 0.0 or xs[c0 + 2] != 0.0:
                            acc = vf[r]
                            for j in range(m3):
                                acc += Dt[wp.min(r, j), wp.max(r, j)] * xs[j]
                        tile_set(zs, r, acc)
                    block_sync()
                    if wp.static(stages):
                        stamp(w, world, lane, 12)
                    rho = rho0  # J is done with: Gt takes (D + (eta + rho) I)^-1 (At keeps A's factor)
                    if adaptive != 0 and w.contact_rho[world] > 0.0:  # where the last step's adaptation left it,
                        warm = int(0)  # while a contact carries its impulse over (new ones alone: CONTACT_RHO)
                        for r in range(m3):
                            if xs[r] != 0.0:
                                warm = 1
                        if warm != 0:
                            rho = w.contact_rho[world]
                    contact_factor(lane, lanes, m3, Dt, ddiag, fdiag, Gt, eta + rho)
                    its = int(0)
                    done = int(0)
                    while its < max_iterations and done == 0:  # PADMM (engine.padmm's method), every lane alike
                        for r in range(lane, m3, lanes):
                            shift = float(0.0)  # De Saxce
                            if r % 3 == 0:
                                shift = mus[r / 3] * wp.sqrt(
                                    zs[r + 1] * zs[r + 1] + zs[r + 2] * zs[r + 2])
                            tile_set(bs, r, -(vf[r] + shift) + eta * xs[r] + rho * ys[r] + zs[r])
                        block_sync()
                        for r in range(lane, m3, lanes):
                            acc = float(0.0)
                            for j in range(m3):
                                acc += Gt[r, j] * bs[j]
                            tile_set(xn, r, acc)
                        block_sync()
                        for ct in range(lane, nc, lanes):
                            r = 3 * ct
                            mu = mus[ct]
                            y = project_cone(xn[r] - zs[r] / rho, xn[r + 1] - zs[r + 1] / rho,
                                             xn[r + 2] - zs[r + 2] / rho, mu)
                            rp = float(0.0)
                            rd = float(0.0)
                            ym = float(0.0)
                            for part in range(3):
                                rp = wp.max(rp, wp.abs(xn[r + part] - y[part]))
                                dual = eta * (xn[r + part] - xs[r + part]) + rho * (y[part] - ys[r + part])
                                rd = wp.max(rd, wp.abs(dual))
                                ym = wp.max(ym, wp.abs(y[part]))
                                tile_set(zs, r + part, zs[r + part] - rho * (xn[r + part] - y[part]))
                                tile_set(xs, r + part, xn[r + part])
                                tile_set(ys, r + part, y[part])
                            tile_set(res_p, ct, rp)
                            tile_set(res_d, ct, rd)
                            tile_set(res_y, ct, ym)
                        block_sync()
                        largest = contact_residuals(nc, res_p, res_d, res_y)
                        its += 1
                        tol = tolerance + relative_tolerance * largest[2]
                        if largest[0] <= tol and largest[1] <= tol:
                            done = 1
                        elif adaptive != 0 and its % rho_interval == 0:
                            new_rho = rho_update(rho, largest[0], largest[1])
                            if new_rho != rho:
                                rho = new_rho
                                contact_factor(lane, lanes, m3, Dt, ddiag, fdiag, Gt, eta + rho)
                    for ct in range(lane, nc, lanes):  # the impulses (unscaled), kept per slot for the next step
                        r = 3 * ct
                        w.contact_impulse[world, w.contact_slot[world, ct]] = wp.vec3(
                            pre[r] * ys[r], pre[r + 1] * ys[r + 1], pre[r + 2] * ys[r + 2])
                    if lane == 0:
                        w.iterations[world] = its
                        w.contact_rho[world] = rho
                    for i in range(lane, n, lanes):  # u += P J^T lambda
                        acc = float(0.0)
                        for r in range(m3):
                            acc += Yt[i, r] * pre[r] * ys[r]
                        u[world, i] = u[world, i] + acc
                        tile_set(jolt, i, acc)
                    block_sync()
                    if wp.static(stages):
                        stamp(w, world, lane, 13)
            for i in range(lane, n, lanes):  # q += lead u; a drive past its effort limit stops the world
                ui = u[world, i]
                effort = m.kp[world, i] * (m.q_target[world, i] - q[world, i] - lead * ui)
                effort += m.kd[world, i] * (m.v_target[world, i] - ui)
                if wp.abs(effort) > m.effort[world, i]:
                    w.diverged[world] = EFFORT_LIMIT
                if midpoint != 0 and m.kind[world, i] == KIND_REVOLUTE:  # an angle: from the step's start, compensated
                    angle, rest = two_sum(w.q_start[world, i], low[i] + lead * (w.u_start[world, i] + ui))
                    q[world, i] = angle
                    tile_set(low, i, rest)
                else:
                    advance(m, world, i, q, root, u, lead)
            block_sync()
            if wp.static(stages):
                stamp(w, world, lane, 14)
            fresh = int(0)  # the last kinematics pass was at the final angles, with velocities
            applied = int(0)
            for it in range(iterations):  # Gauss-Newton projections onto the loops with the step's factors
                kinematics(m, w, world, lane, lanes, q, u, root, VELOCITIES)
                loop_errors(m, w, world, lane, lanes)
                block_sync()
                for r in range(lane, R, lanes):  # the kept rows' errors (a soft row's: 0), their sizes
                    part = m.row_part[world, r]  # signed by kind for the check (angular: negative)
                    err = w.phi[world, 6 * m.row_loop[world, r] + part]
                    tile_set(rhs, r, err)
                    size = wp.abs(err)
                    if part >= 3:
                        size = -size
                    tile_set(sizes, r, size)
                block_sync()
                worst = float(0.0)  # every lane alike: the largest errors, linear and angular
                worst_angular = float(0.0)
                for r in range(R):
                    size = sizes[r]
                    if size >= 0.0:
                        worst = wp.max(worst, size)
                    else:
                        worst_angular = wp.max(worst_angular, -size)
                if (skip_floor > 0.0 or skip_floor_angular > 0.0) and worst <= skip_floor and (
                        worst_angular <= skip_floor_angular):  # closed to rounding: no correction, final poses
                    fresh = 1
                    break
                solve_lanes(lane, lanes, R, At, diag_a, rhs)
                for i in range(lane, n, lanes):
                    project(m, world, i, q, root, Xt, rhs, R, low, midpoint)
                applied += 1
                block_sync()
            if lane == 0:
                w.projections[world] = applied
            if fresh == 0:
                kinematics(m, w, world, lane, lanes, q, u, root, VELOCITIES)
            for k in range(lane, n, lanes):  # the divergence guard
                c = w.centre[world, k]
                v = w.vel[world, k]
                om = w.omega[world, k]
                if not (wp.isfinite(c) and wp.isfinite(v) and wp.isfinite(om)) or wp.length(v) > max_speed:
                    w.diverged[world] = DIVERGED
            block_sync()
            if wp.static(stages):
                stamp(w, world, lane, 15)
            if w.diverged[world] == 0:
                for k in range(lane, n, lanes):
                    w.q_start[world, k] = q[world, k]  # where this step leaves the state (left_here)
                    if m.kind[world, k] == KIND_ROOT:
                        w.root_start[world, k] = root[world, k]
                    elif midpoint != 0:
                        keep_angle_low(m, w, world, k, low[k])
                    if wp.static(contacts > 0):
                        if jolt[k] != 0.0:  # a contact impulse moved it: no extrapolation from this step
                            w.u_start[world, k] = u[world, k]
                    body_out(m, w, world, k, body_q, body_qd)
            else:  # frozen at the last good step: its coordinates, rates and bodies
                for i in range(lane, n, lanes):
                    q[world, i] = w.q_start[world, i]
                    u[world, i] = w.u_start[world, i]
                    if m.kind[world, i] == KIND_ROOT:
                        root[world, i] = w.root_start[world, i]
            if wp.static(stages):
                stamp(w, world, lane, 16)

    return chain_step_body
