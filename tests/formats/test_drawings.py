"""Fabrication drawings (morphopt.formats.drawing): SVG and DXF of Jansen's leg and a four-bar.

The oracles are independent of the module: link lengths from the kinematics (solve_at at the crank
phase), the outline checked against the distance to the bars' segments (NumPy), areas by the
shoelace formula, containment by matplotlib's Path, the files read back by xml.etree and ezdxf.
"""

from __future__ import annotations

import itertools
import json
import math
import re
import xml.etree.ElementTree as ET

import ezdxf
import numpy as np
import pytest
from matplotlib.path import Path

from morphopt.families import load_family
from morphopt.formats.drawing import (
    APPID,
    CHORD_TOLERANCE,
    METADATA_KEY,
    link_parts,
    read_dxf_metadata,
    write_dxf,
    write_svg,
)
from morphopt.linkage import Link
from morphopt.linkage.kinematics import solve_at
from morphopt.linkage.to_spec import BarStyle

SVG = "{http://www.w3.org/2000/svg}"
METADATA = {"family": "x", "params": {"a": 0.038, "b": 0.0415}, "objectives": [1.25, -3.0], "generation": 7,
            "note": None, "feasible": True}


def design(family: str, **overrides):
    module = load_family(family)
    return module.generate({**module.space.default(), **overrides})


@pytest.fixture(params=["jansen_leg", "four_bar"])
def linkage(request):
    return design(request.param)


def link_lengths(linkage) -> dict:
    """link name -> {(a, b): centre distance [mm]} from the kinematics at the crank phase."""
    nodes = solve_at([linkage], np.array([[linkage.crank.phase]]))[0].nodes
    return {link.name: {(a, b): 1000.0 * math.dist(nodes[a][0], nodes[b][0])
                        for a, b in itertools.combinations(link.nodes, 2)} for link in linkage.links}


def rings_of_path(d: str) -> list[np.ndarray]:
    return [np.array([float(v) for v in ring.replace("L", " ").split()]).reshape(-1, 2)
            for ring in re.findall(r"M([^MZ]*)Z", d)]


def shoelace(ring: np.ndarray) -> float:
    x, y = ring[:, 0], ring[:, 1]
    return 0.5 * abs(float(x @ np.roll(y, -1) - y @ np.roll(x, -1)))


def distance_to_segments(points: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(P,) distance of each point to the nearest of the segments a[k] -> b[k]."""
    ab = b - a
    t = np.clip(np.einsum("pkd,kd->pk", points[:, None] - a, ab) / np.einsum("kd,kd->k", ab, ab), 0.0, 1.0)
    return np.linalg.norm(points[:, None] - (a + t[..., None] * ab), axis=-1).min(axis=1)


def inside(rings: list[np.ndarray], points: np.ndarray) -> np.ndarray:
    """Even-odd containment in the region bounded by the rings."""
    return np.logical_xor.reduce([Path(ring).contains_points(points) for ring in rings])


def check_outline(rings: list[np.ndarray], centres: np.ndarray, width: float, hole: float):
    """The outline is the union of stadiums of radius width / 2 around every pair of hole centres."""
    r = 0.5 * width
    pairs = list(itertools.combinations(range(len(centres)), 2))
    a, b = centres[[i for i, _ in pairs]], centres[[j for _, j in pairs]]
    lengths = np.linalg.norm(b - a, axis=1)
    # every hole inside, with the bar's half width of material around its centre
    assert inside(rings, centres).all()
    edges = np.concatenate([np.stack([ring, np.roll(ring, -1, axis=0)], axis=1) for ring in rings])
    clearance = distance_to_segments(centres, edges[:, 0], edges[:, 1])
    assert (clearance >= r - CHORD_TOLERANCE - 1e-9).all() and (clearance - 0.5 * hole > 0.0).all()
    # area between the largest bar's stadium and the sum of all the stadiums
    area = shoelace(rings[0]) - sum(shoelace(ring) for ring in rings[1:])
    cap = math.pi * r * r
    assert max(lengths) * width + cap * (1.0 - 1e-3) <= area <= lengths.sum() * width + len(pairs) * cap
    if len(centres) == 2:  # one stadium: exact up to the chord error along its perimeter
        assert area == pytest.approx(lengths[0] * width + cap, abs=2.0 * math.pi * r * CHORD_TOLERANCE)
    # membership of a grid of points agrees with the distance to the bars (away from the boundary)
    lo, hi = centres.min(axis=0) - width, centres.max(axis=0) + width
    grid = np.stack(np.meshgrid(np.linspace(lo[0], hi[0], 90), np.linspace(lo[1], hi[1], 90)), -1).reshape(-1, 2)
    d = distance_to_segments(grid, a, b)
    sure = np.abs(d - r) > 2.0 * CHORD_TOLERANCE
    assert sure.sum() > 1000
    np.testing.assert_array_equal(inside(rings, grid[sure]), d[sure] < r)


def test_parts_are_in_their_own_frame_and_do_not_depend_on_the_crank_angle():
    leg, turned = design("jansen_leg"), load_family("jansen_leg").generate(
        load_family("jansen_leg").space.default(), phase=2.0)
    lengths = link_lengths(leg)
    parts, parts_turned = link_parts(leg), link_parts(turned)
    assert [p.name for p in parts] == [link.name for link in leg.links]
    for part, other, link in zip(parts, parts_turned, leg.links):
        first, second = link.nodes[:2]
        assert part.holes[first] == (0.0, 0.0) and part.holes[second][1] == 0.0 and part.holes[second][0] > 0.0
        assert part.hole_diameter == pytest.approx(0.4 * 10.0) and part.width == pytest.approx(10.0)
        for node, xy in part.holes.items():
            np.testing.assert_allclose(xy, other.holes[node], rtol=0.0, atol=1e-9)
        for a, b, distance in part.distances():
            assert distance == pytest.approx(lengths[link.name][(a, b)], rel=1e-9)


def test_svg(linkage, tmp_path):
    lengths = link_lengths(linkage)
    style = BarStyle(width=0.008)
    path = write_svg(linkage, tmp_path / "design.svg", style=style, metadata=METADATA, hole_diameter=3.0)
    root = ET.parse(path).getroot()
    assert root.tag == SVG + "svg"
    x0, y0, w, h = (float(v) for v in root.get("viewBox").split())
    assert (x0, y0) == (0.0, 0.0)
    for key, size in (("width", w), ("height", h)):
        assert re.fullmatch(r"\d+(\.\d+)?mm", root.get(key)) and float(root.get(key)[:-2]) == pytest.approx(size)
    assert json.loads(root.find(SVG + "metadata").text) == METADATA
    groups = root.findall(SVG + "g")
    assert [g.get("id") for g in groups] == [link.name for link in linkage.links]
    boxes = []
    for group, link in zip(groups, linkage.links):
        circles = {c.get("data-node"): c for c in group.findall(SVG + "circle")}
        assert sorted(circles) == sorted(link.nodes)
        assert all(float(c.get("r")) == pytest.approx(1.5) for c in circles.values())
        centre = {n: np.array([float(c.get("cx")), float(c.get("cy"))]) for n, c in circles.items()}
        for (a, b), distance in lengths[link.name].items():
            assert np.linalg.norm(centre[a] - centre[b]) == pytest.approx(distance, rel=1e-6)
        dims = {tuple(g.get("data-holes").split()): g.find(SVG + "text").text
                for g in group.findall(SVG + "g[@class='dimension']")}
        assert dims == {pair: f"{distance:.1f}" for pair, distance in lengths[link.name].items()}
        assert group.find(SVG + "text[@class='label']").text == link.name
        (outline,) = group.findall(SVG + "path")
        assert outline.get("fill") == "none" and outline.get("stroke")
        rings = rings_of_path(outline.get("d"))
        check_outline(rings, np.array([centre[n] for n in link.nodes]), 8.0, 3.0)
        everything = np.concatenate(rings)
        boxes.append((*everything.min(axis=0), *everything.max(axis=0)))
    for bx0, by0, bx1, by1 in boxes:
        assert 0.0 <= bx0 and 0.0 <= by0 and bx1 <= w and by1 <= h
    for (ax0, ay0, ax1, ay1), (bx0, by0, bx1, by1) in itertools.combinations(boxes, 2):
        assert ax1 <= bx0 or bx1 <= ax0 or ay1 <= by0 or by1 <= ay0


def test_dxf(linkage, tmp_path):
    lengths = link_lengths(linkage)
    path = write_dxf(linkage, tmp_path / "design.dxf", metadata=METADATA)
    doc = ezdxf.readfile(path)
    assert doc.header["$INSUNITS"] == 4 and doc.header["$MEASUREMENT"] == 1
    record = doc.rootdict[METADATA_KEY]
    assert json.loads("".join(value for code, value in record.tags if code == 1)) == METADATA
    assert read_dxf_metadata(path) == METADATA
    assert doc.header.custom_vars.get("morphopt_linkage") == linkage.name
    msp = doc.modelspace()
    for link in linkage.links:
        on_layer = msp.query(f'*[layer=="{link.name}"]')
        circles = {c.get_xdata(APPID)[0].value: c for c in on_layer.query("CIRCLE")}
        assert sorted(circles) == sorted(link.nodes)
        assert all(c.dxf.radius == pytest.approx(2.0) for c in circles.values())
        centre = {n: np.array(c.dxf.center)[:2] for n, c in circles.items()}
        for (a, b), distance in lengths[link.name].items():
            assert np.linalg.norm(centre[a] - centre[b]) == pytest.approx(distance, rel=1e-6)
        polylines = on_layer.query("LWPOLYLINE")
        assert len(polylines) >= 1 and all(p.closed for p in polylines)
        rings = sorted((np.array(p.get_points("xy")) for p in polylines), key=shoelace, reverse=True)
        check_outline(rings, np.array([centre[n] for n in link.nodes]), 10.0, 4.0)
        measured = sorted(d.get_measurement() for d in on_layer.query("DIMENSION"))
        np.testing.assert_allclose(measured, sorted(lengths[link.name].values()), rtol=1e-6)
        assert on_layer.query("TEXT")[0].dxf.text == link.name


def test_bad_input_names_the_link_or_parameter(tmp_path):
    leg = design("jansen_leg")
    with pytest.raises(ValueError, match="width"):
        link_parts(leg, style=BarStyle(width=0.0))
    with pytest.raises(ValueError, match="hole_diameter"):
        write_svg(leg, tmp_path / "x.svg", hole_diameter=10.0)
    with pytest.raises(ValueError, match="hole_diameter"):
        write_dxf(leg, tmp_path / "x.dxf", hole_diameter=-1.0)
    leg.links.append(Link("stub", ("O",)))
    with pytest.raises(ValueError, match="link 'stub'"):
        link_parts(leg)
    locked = design("four_bar", ground=0.45, crank=0.04, coupler=0.15, rocker=0.10)  # |MD| > coupler + rocker
    with pytest.raises(ValueError, match="four_bar.*cannot be assembled"):
        write_svg(locked, tmp_path / "y.svg")
    module = load_family("four_bar")
    batch = module.generate({k: np.full(3, v) for k, v in module.space.default().items()})
    with pytest.raises(ValueError, match="batch"):
        link_parts(batch)
    assert not list(tmp_path.iterdir())
