"""Designs to files other tools read: USD (UsdPhysics), URDF (+ a loop-closure extension), MJCF,
and SVG / DXF drawings of the planar links for fabrication; USD and URDF read back as well.

``export_design`` builds one design of a family and writes it in one format, named by the design,
with its parameters and objective values as metadata; ``morphopt export`` calls it for the best
designs of a study.
"""

from __future__ import annotations

import pathlib

import numpy as np

__all__ = ["FORMATS", "design_meshes", "export_design"]

FORMATS = {"usd": ".usda", "urdf": ".urdf", "mjcf": ".xml", "svg": ".svg", "dxf": ".dxf"}


def design_meshes(linkage, spec) -> dict:
    """Visual meshes of a linkage's links (the bars of morphopt.linkage.to_spec, as trimesh
    meshes) in the frames of the spec's bodies: {body name: Trimesh}."""
    from morphopt.formats.tree import body_frame
    from morphopt.linkage.kinematics import solve_at
    from morphopt.linkage.to_spec import BarStyle, link_mesh, world

    solution = solve_at([linkage], np.array([[linkage.crank.phase]]))[0]
    meshes = {}
    for link in linkage.links:
        if link.name not in spec.body_index:
            continue
        mesh = link_mesh([world(solution.nodes[n][0]) for n in link.nodes], BarStyle())
        mesh.apply_transform(np.linalg.inv(body_frame(spec, link.name)))
        meshes[link.name] = mesh
    return meshes


def export_design(family, params: dict, fmt: str, out_dir, *, name: str, metadata: dict | None = None,
                  motion_seconds: float = 0.0, motion_dt: float = 1e-3, config=None) -> pathlib.Path:
    """Build the design ``params`` of ``family`` (a module from morphopt.families.load_family)
    and write it as ``out_dir/<name><suffix>`` in format ``fmt`` (usd, urdf, mjcf, svg, dxf).

    metadata (JSON-able: parameters, objective values) goes into the file; motion_seconds > 0
    adds the motion simulated at time step motion_dt [s] with the engine.SolverConfig ``config``
    (None: the defaults) to a USD file (time samples). Returns the path written. Raises
    ValueError naming the format or the design when the design cannot be built or drawn.
    """
    if fmt not in FORMATS:
        raise ValueError(f"unknown format '{fmt}': choose one of {', '.join(FORMATS)}")
    out_dir = pathlib.Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    path = out_dir / f"{name}{FORMATS[fmt]}"
    params = family.space.validate(params)
    linkage = family.generate(params) if hasattr(family, "generate") else None
    if fmt in ("svg", "dxf"):
        if linkage is None:
            raise ValueError(f"design '{name}': {fmt} drawings need a planar linkage family; this family builds a "
                             f"whole world (build_spec)")
        from morphopt.formats.drawing import write_dxf, write_svg

        return (write_svg if fmt == "svg" else write_dxf)(linkage, path, metadata=metadata)
    if linkage is not None:
        from morphopt.linkage.to_spec import to_spec

        spec = to_spec(linkage)
        meshes = design_meshes(linkage, spec)
    else:
        spec, meshes = family.build_spec(params), None
    if fmt == "usd":
        from morphopt.formats.usd import record_motion, write_usd

        motion = record_motion(spec, motion_seconds, dt=motion_dt, config=config) if motion_seconds > 0 else None

        return write_usd(spec, path, metadata=metadata, meshes=meshes, motion=motion)
    if fmt == "urdf":
        from morphopt.formats.urdf import write_urdf

        return write_urdf(spec, path, metadata=metadata, meshes=meshes)
    from morphopt.formats.mjcf import write_mjcf

    return write_mjcf(spec, path, metadata=metadata, meshes=meshes)
