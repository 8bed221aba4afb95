"""Each body's rows (engine.pack.body_row_lists) and the impulse sums through them
(engine.integrate.row_sum_listed) against a dense NumPy sum over all rows."""

import numpy as np
import warp as wp

from engine import pack_worlds, step
from engine.integrate import apply_impulses
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
    wp.launch(apply_impulses, dim=(len(specs), model.max_bodies), device="cpu",
              inputs=[model.body_count, work.row_count, model.contact_row_start, model.body_row_begin,
                      model.body_row_end, model.body_row, work.row_body_c, work.row_body_p, work.row_MJ_c,
                      work.row_MJ_p, lam, work.row_precond, qd_free],
              outputs=[out])
    MJ_c, MJ_p = work.row_MJ_c.numpy().astype(np.float64), work.row_MJ_p.numpy().astype(np.float64)
    body_c, body_p = work.row_body_c.numpy(), work.row_body_p.numpy()
    got = out.numpy()
    for w in range(len(specs)):
        for b in range(model.body_count.numpy()[w]):
            rows = np.arange(counts[w])
            expected = free[w, b].astype(np.float64) + (
                (impulses[w, rows] * (body_c[w, rows] == b))[:, None] * MJ_c[w, rows]
                + (impulses[w, rows] * (body_p[w, rows] == b))[:, None] * MJ_p[w, rows]).sum(axis=0)
            np.testing.assert_allclose(got[w, b], expected, rtol=1e-5, atol=1e-5 * np.abs(expected).max())
