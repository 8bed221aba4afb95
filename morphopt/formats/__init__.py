"""Designs to files other tools read: USD (UsdPhysics), URDF (+ a loop-closure extension), MJCF,
and SVG / DXF drawings of the planar links for fabrication; USD and URDF read back as well.

``export_design`` builds one design of a family as a study simulates it and writes it in one
format, in a folder of its own named by the design, with its parameters, objective values and the
study's settings as metadata; ``morphopt export`` calls it for the best designs of a study.
"""

from __future__ import annotations

import pathlib

import numpy as np

__all__ = ["FORMATS", "MOTION_FORMATS", "design_meshes", "export_design"]

FORMATS = {"usd": ".usda", "urdf": ".urdf", "mjcf": ".xml", "svg": ".svg", "dxf": ".dxf"}
MOTION_FORMATS = ("usd",)  # formats that carry a simulated motion (time samples)


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
                  crank_speed: float | None = None, dt: float = 1e-3, config=None,
                  motion_seconds: float = 0.0) -> pathlib.Path:
    """Build the design ``params`` of ``family`` (a module from morphopt.families.load_family) as
    a study simulates it (morphopt.build.build_spec: driven at ``crank_speed`` [rad/s], None: the
    study default) and write it in format ``fmt`` (usd, urdf, mjcf, svg, dxf) as
    ``out_dir/<name>/<name><suffix>``, its meshes in the same folder, so designs never share files.

    metadata (JSON-able: parameters, objective values, settings) goes into the file. dt [s]: the
    study's time step; MuJoCo's step (MJCF's timestep, USD's mjc:option:timestep) is the smaller
    of dt and mjcf.MJCF_TIMESTEP (stable in MuJoCo). motion_seconds > 0 (USD only: MOTION_FORMATS)
    adds the motion simulated at time step dt with the engine.SolverConfig ``config`` (None: the
    defaults) as time samples. Returns the path written. Raises ValueError naming the format or
    the design when the design cannot be built or written in that format.
    """
    if fmt not in FORMATS:
        raise ValueError(f"unknown format '{fmt}': choose one of {', '.join(FORMATS)}")
    if motion_seconds > 0 and fmt not in MOTION_FORMATS:
        raise ValueError(f"format '{fmt}' cannot carry a motion (only {', '.join(MOTION_FORMATS)} has time samples)")
    from morphopt.build import build_spec

    params = family.space.validate(params)
    linkage = family.generate(params) if hasattr(family, "generate") else None  # the links' shapes
    if fmt in ("svg", "dxf") and linkage is None:
        raise ValueError(f"design '{name}': {fmt} drawings need a planar linkage family; this family builds a "
                         f"whole world (build_spec)")
    folder = pathlib.Path(out_dir) / name
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / f"{name}{FORMATS[fmt]}"
    if fmt in ("svg", "dxf"):
        from morphopt.formats.drawing import write_dxf, write_svg

        return (write_svg if fmt == "svg" else write_dxf)(linkage, path, metadata=metadata)
    from morphopt.formats.mjcf import MJCF_TIMESTEP

    spec = build_spec(family, params, crank_speed)
    meshes = design_meshes(linkage, spec) if linkage is not None and not hasattr(family, "build_spec") else None
    if fmt == "usd":
        from morphopt.formats.usd import record_motion, write_usd

        motion = record_motion(spec, motion_seconds, dt=dt, config=config) if motion_seconds > 0 else None
        return write_usd(spec, path, metadata=metadata, meshes=meshes, motion=motion,
                         timestep=min(dt, MJCF_TIMESTEP))
    if fmt == "urdf":
        from morphopt.formats.urdf import write_urdf

        return write_urdf(spec, path, metadata=metadata, meshes=meshes)
    from morphopt.formats.mjcf import write_mjcf

    return write_mjcf(spec, path, metadata=metadata, meshes=meshes, timestep=min(dt, MJCF_TIMESTEP))
