"""Each body's rows (engine.pack.body_row_lists) and the impulse sums through them
(engine.integrate.row_sum_listed) against a dense NumPy sum over all rows."""

import numpy as np
import warp as wp

from engine import pack_worlds, step
from engine.integrate import add_row_share, apply_impulses, row_sum_listed
from engine.model import ModelArrays, WorkArrays
from engine.scenes import fourbar, pendulum, sixbar
from engine.scenes_contact import CONTACT_SCENES


def test_body_row_lists_hold_each_bodys_static_rows_in_row_order():
    """Per world and body: exactly the rows below contact_row_start that touch the body, in row
    order, with the side it is on (a mixed batch: joints of several kinds, drives, contacts)."""
    specs = [pendulum().spec, sixbar().spec, CONTACT_SCENES["walker"]().spec, fourbar().spec]
    model = pack_worlds(specs, device="cpu")
    begin, end = model.body_row_begin.numpy(), model.body_row_end.numpy()
    codes = model.body_row.numpy()
    body_c, body_p = model.row_body_c.numpy(), model.row_body_p.numpy()
    start = model.contact_row_start.numpy()
    for w in range(len(specs)):
        for b in range(model.max_bodies):
            expected = [2 * i + side for i in range(start[w]) for side, bodies in enumerate((body_c, body_p))
                        if bodies[w, i] == b]
            assert codes[w, begin[w, b]:end[w, b]].tolist() == expected, (w, b)
    assert end[2].max() > 0 and start[2] < model.max_rows  # the walker has joint rows and contact rows


def test_impulse_sums_through_the_lists_match_a_dense_sum_with_contact_rows():
    """u+ = u_free + sum_i (M^-1 J^T)_b,i lambda_i over every row touching the body, contact rows
    (whose bodies change per step) included: apply_impulses against NumPy after a few steps of
    walkers standing on the ground with random impulses."""
    specs = [CONTACT_SCENES["walker"]().spec, sixbar().spec, CONTACT_SCENES["walker"]().spec]
    model = pack_worlds(specs, device="cpu", dt=2e-3)
    state, other, control = model.state(), model.state(), model.control()
    for _ in range(40):  # the walkers settle onto their feet: contact rows appear
        step(model, state, other, control)
        state, other = other, state
    work = model.work
    counts = work.row_count.numpy()
    assert (counts > model.contact_row_start.numpy())[[0, 2]].all()
    rng = np.random.default_rng(3)
    impulses = rng.normal(size=(len(specs), model.max_rows)).astype(np.float32)
    free = rng.normal(size=(len(specs), model.max_bodies, 6)).astype(np.float32)
    lam = wp.array(impulses, dtype=float, device="cpu")
    qd_free = wp.array(free, dtype=wp.spatial_vector, device="cpu")
    out = wp.zeros((len(specs), model.max_bodies), dtype=wp.spatial_vector, device="cpu")
    # the free twists' low parts (engine.integrate's compensated sum): in, and the new twists' out
    low_in = rng.normal(scale=1e-8, size=(len(specs), model.max_bodies, 6)).astype(np.float32)
    low = wp.array(low_in, dtype=wp.spatial_vector, device="cpu")
    poses = wp.zeros((len(specs), model.max_bodies), dtype=wp.transform, device="cpu")  # its pose step's outputs
    poses_low = wp.zeros_like(poses)
    work.body_qd_free = qd_free  # the kernel reads the free twists from the workspace (work.arrays follows)
    wp.launch(apply_impulses, dim=(len(specs), model.max_bodies), device="cpu",
              inputs=[model.arrays, work.arrays, lam, 1, state.body_q, state.body_q_low, out, poses, poses_low, low])
    MJ_c, MJ_p = work.row_MJ_c.numpy().astype(np.float64), work.row_MJ_p.numpy().astype(np.float64)
    body_c, body_p = work.row_body_c.numpy(), work.row_body_p.numpy()
    got = out.numpy().astype(np.float64) + low.numpy()
    for w in range(len(specs)):
        for b in range(model.body_count.numpy()[w]):
            rows = np.arange(counts[w])
            expected = free[w, b].astype(np.float64) + low_in[w, b] + (
                (impulses[w, rows] * (body_c[w, rows] == b))[:, None] * MJ_c[w, rows]
                + (impulses[w, rows] * (body_p[w, rows] == b))[:, None] * MJ_p[w, rows]).sum(axis=0)
            np.testing.assert_allclose(got[w, b], expected, rtol=1e-5, atol=1e-5 * np.abs(expected).max())


@wp.kernel
def scanned_and_listed(m: ModelArrays, w: WorkArrays, weight: wp.array2d(dtype=float), scale: int,
                       scanned: wp.array2d(dtype=wp.spatial_vector), listed: wp.array2d(dtype=wp.spatial_vector)):
    """Each body's sum by a scan of every row (what the lists replace) and through its list."""
    world, b = wp.tid()
    total = wp.spatial_vector()
    for i in range(w.row_count[world]):
        total = add_row_share(total, world, b, i, w.row_body_c, w.row_body_p, w.row_MJ_c, w.row_MJ_p, weight,
                              w.row_precond, scale)
    scanned[world, b] = total
    listed[world, b] = row_sum_listed(world, b, m, w, weight, scale)


def test_listed_sums_are_bit_identical_to_a_scan_of_every_row():
    """The lists visit the same rows in the same order as a scan of all rows, contact rows included,
    with and without the preconditioner scaling (apply_projection's form): equal to the last bit."""
    specs = [CONTACT_SCENES["walker"]().spec, sixbar().spec]
    model = pack_worlds(specs, device="cpu", dt=2e-3)
    state, other, control = model.state(), model.state(), model.control()
    for _ in range(40):
        step(model, state, other, control)
        state, other = other, state
    work = model.work
    assert work.row_count.numpy()[0] > model.contact_row_start.numpy()[0]  # contact rows in use
    weight = wp.array(np.random.default_rng(4).normal(size=(len(specs), model.max_rows)).astype(np.float32),
                      dtype=float, device="cpu")
    for scale in (0, 1):
        scanned = wp.zeros((len(specs), model.max_bodies), dtype=wp.spatial_vector, device="cpu")
        listed = wp.zeros_like(scanned)
        wp.launch(scanned_and_listed, dim=(len(specs), model.max_bodies), device="cpu",
                  inputs=[model.arrays, work.arrays, weight, scale], outputs=[scanned, listed])
        assert np.abs(scanned.numpy()).max() > 0
        np.testing.assert_array_equal(listed.numpy(), scanned.numpy())
