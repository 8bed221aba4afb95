"""Fabrication drawings of planar linkage designs: SVG and DXF at 1:1 in millimetres, ready to laser-cut.

Every link of a Linkage becomes one flat Part: the union of its bars (a "stadium" per pair of
nodes: a rectangle of the bar width around the segment, with semicircular ends of radius width/2
about each node), with a pivot hole at each node. Positions come from assembling the linkage at
its crank phase (morphopt.linkage.kinematics.solve_at); each part is drawn in its own frame (origin
at the link's first node, x axis towards its second node), so the drawing does not depend on the
crank angle. The polygon union is shapely's; arcs are polylines with at most CHORD_TOLERANCE [mm]
chord error (vertices on the true circle).

write_svg and write_dxf lay the parts side by side on shelves (no overlap), with the link name as a
label and the centre-to-centre distance of every pair of holes (the design's link lengths) as a
dimension with 0.1 mm precision. Design metadata (a JSON-able dict) goes into the SVG's
<metadata> element, and into the DXF as an XRECORD named METADATA_KEY in the root dictionary
(read it back with read_dxf_metadata). SVG: cut lines (outline, holes) red, annotations blue.
DXF: one layer per part, named by its link; holes carry the node name as XDATA of APPID.
"""

from __future__ import annotations

import json
import math
import pathlib
import xml.etree.ElementTree as ET
from dataclasses import dataclass

import numpy as np
import shapely
from shapely.geometry import LineString, Polygon
from shapely.geometry.polygon import orient

from morphopt.formats.tree import metadata_json
from morphopt.linkage.graph import Linkage
from morphopt.linkage.kinematics import solve_at
from morphopt.linkage.to_spec import BarStyle

__all__ = ["APPID", "CHORD_TOLERANCE", "METADATA_KEY", "Part", "layout", "link_parts", "read_dxf_metadata",
           "write_dxf", "write_svg"]

CHORD_TOLERANCE = 1e-3  # [mm] largest distance between a drawn arc's chord and the true arc
METADATA_KEY = "MORPHOPT_METADATA"  # XRECORD in the DXF root dictionary holding the metadata JSON
APPID = "MORPHOPT"  # DXF application id of the XDATA naming each hole's node
TEXT = 3.0  # [mm] height of labels and dimension texts
GAP = 5.0  # [mm] between parts and around the sheet
DEFAULT_STYLE = BarStyle()  # 10 mm wide bars


@dataclass(frozen=True)
class Part:
    """One flat link, in its own frame [mm]: ``holes`` maps node name -> (x, y) hole centre;
    ``hole_diameter`` and ``width`` (of the bars) [mm]; ``outline`` the shapely Polygon of the
    union of the bars (exterior and interior rings, counter-clockwise exterior)."""

    name: str
    holes: dict
    hole_diameter: float
    width: float
    outline: Polygon

    def distances(self) -> list[tuple[str, str, float]]:
        """(node a, node b, centre-to-centre distance [mm]) for every pair of holes, in link order."""
        items = list(self.holes.items())
        return [(a, b, math.dist(pa, pb)) for i, (a, pa) in enumerate(items) for b, pb in items[i + 1:]]


def link_parts(linkage: Linkage, *, style: BarStyle = DEFAULT_STYLE, hole_diameter: float | None = None) -> list[Part]:
    """One Part per link of ``linkage`` (one design, not a batch), assembled at its crank phase.

    style.width [m] is the bar width; hole_diameter [mm] defaults to 0.4 x the bar width and must
    be positive and smaller than it. Raises ValueError naming the linkage, link or parameter.
    """
    where = f"linkage '{linkage.name}'"
    if not (style.width > 0.0 and math.isfinite(style.width)):
        raise ValueError(f"{where}: bar width (style.width) must be positive, got {style.width}")
    width = 1000.0 * style.width
    hole = 0.4 * width if hole_diameter is None else float(hole_diameter)
    if not 0.0 < hole < width:
        raise ValueError(f"{where}: hole_diameter must be positive and smaller than the bar width "
                         f"{width:g} mm, got {hole:g} mm")
    if linkage.batch_size is not None:
        raise ValueError(f"{where}: is a batch of {linkage.batch_size} designs; draw one design at a time")
    for link in linkage.links:
        if len(link.nodes) < 2 or len(set(link.nodes)) != len(link.nodes):
            raise ValueError(f"{where}: link '{link.name}' needs at least two distinct nodes, got {link.nodes}")
    solution = solve_at([linkage], np.array([[linkage.crank.phase]]))[0]
    if not solution.feasible:
        raise ValueError(f"{where} cannot be assembled at its crank phase: {solution.reason}")
    radius = 0.5 * width
    # segments per quarter circle so that the sagitta r (1 - cos(step / 2)) <= CHORD_TOLERANCE
    quad_segs = max(4, math.ceil(0.5 * math.pi / (2.0 * math.acos(1.0 - min(CHORD_TOLERANCE / radius, 1.0)))))
    parts = []
    for link in linkage.links:
        xy = np.array([solution.nodes[n][0] for n in link.nodes], dtype=float) * 1000.0  # [mm], world frame
        axis = xy[1] - xy[0]
        length = float(np.hypot(*axis))
        if not length > 1e-9:
            raise ValueError(f"{where}: link '{link.name}' has its first two nodes at the same place")
        c, s = axis / length
        local = (xy - xy[0]) @ np.array([[c, -s], [s, c]])  # rotate by -angle: first node at 0, second on +x
        local[0], local[1] = (0.0, 0.0), (length, 0.0)
        bars = [LineString([local[i], local[j]]).buffer(radius, quad_segs=quad_segs, cap_style="round")
                for i in range(len(local)) for j in range(i + 1, len(local))]
        outline = shapely.union_all(bars)
        if outline.geom_type != "Polygon":  # bars of one link always touch at shared nodes
            raise ValueError(f"{where}: link '{link.name}' outline is not one piece")
        outline = orient(outline, 1.0)
        holes = {n: (float(p[0]), float(p[1])) for n, p in zip(link.nodes, local)}
        parts.append(Part(link.name, holes, hole, width, outline))
    return parts


def _dimensions(part: Part) -> list[tuple[str, str, float, np.ndarray, np.ndarray, np.ndarray, float]]:
    """(a, b, distance, p, q, n, offset) per pair of holes: the dimension line runs from p + n
    offset to q + n offset, n the unit normal pointing away from the holes' centroid [mm]."""
    centre = np.mean(list(part.holes.values()), axis=0)
    out = []
    for k, (a, b, distance) in enumerate(part.distances()):
        p, q = np.array(part.holes[a]), np.array(part.holes[b])
        normal = np.array([p[1] - q[1], q[0] - p[0]]) / distance  # left of p -> q
        if normal @ (0.5 * (p + q) - centre) < -1e-9:
            normal = -normal
        out.append((a, b, distance, p, q, normal, 0.5 * part.width + 2.0 + (TEXT + 2.0) * k))
    return out


def _extent(part: Part) -> tuple[float, float, float, float]:
    """Bounding box (xmin, ymin, xmax, ymax) [mm] of the part with its dimensions and label."""
    xs, ys = list(part.outline.exterior.xy)
    points = [np.array([x, y]) for x, y in zip(xs, ys)]
    for _, _, _, p, q, n, offset in _dimensions(part):
        points += [p + n * (offset + TEXT + 1.0), q + n * (offset + TEXT + 1.0)]
    points = np.array(points)
    x0, y0 = points.min(axis=0)
    x1, y1 = points.max(axis=0)
    label = 0.6 * TEXT * len(part.name)
    return float(x0), float(y0 - 2.0 * TEXT), float(max(x1, x0 + label)), float(y1)


def layout(parts: list[Part], gap: float = GAP) -> tuple[list[tuple[float, float]], float, float]:
    """Shelf layout: for each part the sheet position (x, y) [mm] of its extent's top-left corner
    (y down), and the sheet's width and height [mm], margins of ``gap`` included."""
    sizes = [(x1 - x0, y1 - y0) for x0, y0, x1, y1 in map(_extent, parts)]
    row = max([w for w, _ in sizes] + [1.3 * math.sqrt(sum(w * h for w, h in sizes))])
    places, x, y, shelf, width = [], gap, gap, 0.0, 0.0
    for w, h in sizes:
        if x > gap and x + w > gap + row:
            x, y, shelf = gap, y + shelf + gap, 0.0
        places.append((x, y))
        x, shelf, width = x + w + gap, max(shelf, h), max(width, x + w + gap)
    return places, max(width, 2.0 * gap), y + shelf + gap


def _placed(parts: list[Part]):
    """(part, to_sheet) pairs and sheet size: to_sheet maps part-frame points [mm] to sheet
    points with y down (SVG); DXF uses (x, height - y)."""
    places, width, height = layout(parts)
    out = []
    for part, (ox, oy) in zip(parts, places):
        x0, _, _, y1 = _extent(part)
        out.append((part, lambda p, ox=ox, oy=oy, x0=x0, y1=y1: np.array([ox + p[0] - x0, oy + y1 - p[1]])))
    return out, width, height


def _f(value: float) -> str:
    return f"{value:.6f}".rstrip("0").rstrip(".")


def write_svg(linkage: Linkage, path, *, style: BarStyle = DEFAULT_STYLE, metadata: dict | None = None,
              hole_diameter: float | None = None) -> pathlib.Path:
    """Write the fabrication drawing of ``linkage`` as one SVG at 1:1 (width, height and viewBox
    in mm). Each part is a <g id="link name"> holding the outline <path class="outline">, the
    holes <circle class="hole" data-node="...">, the label <text class="label"> and one
    <g class="dimension" data-holes="a b"> per pair of holes whose <text> is the centre-to-centre
    distance [mm] to 0.1 mm. ``metadata`` goes as JSON into <metadata>. Returns the path."""
    parts = link_parts(linkage, style=style, hole_diameter=hole_diameter)
    placed, width, height = _placed(parts)
    svg = ET.Element("svg", xmlns="http://www.w3.org/2000/svg", version="1.1", width=f"{_f(width)}mm",
                     height=f"{_f(height)}mm", viewBox=f"0 0 {_f(width)} {_f(height)}")
    ET.SubElement(svg, "title").text = f"{linkage.name}: fabrication drawing, 1:1, millimetres"
    ET.SubElement(svg, "metadata", id="design").text = metadata_json(metadata)
    marker = ET.SubElement(ET.SubElement(svg, "defs"), "marker", id="arrow", viewBox="0 0 10 10", refX="10",
                           refY="5", markerWidth="6", markerHeight="6", orient="auto-start-reverse")
    ET.SubElement(marker, "path", d="M 0 1 L 10 5 L 0 9 z", fill="blue")
    cut = {"fill": "none", "stroke": "red", "stroke-width": "0.1"}
    note = {"stroke": "blue", "stroke-width": "0.1"}
    for part, sheet in placed:
        group = ET.SubElement(svg, "g", id=part.name)
        rings = [part.outline.exterior, *part.outline.interiors]
        d = " ".join("M " + " L ".join(f"{_f(x)} {_f(y)}" for x, y in (sheet(p) for p in ring.coords[:-1])) + " Z"
                     for ring in rings)
        ET.SubElement(group, "path", {"class": "outline", "d": d, "fill-rule": "evenodd", **cut})
        for node, centre in part.holes.items():
            x, y = sheet(centre)
            ET.SubElement(group, "circle", {"class": "hole", "data-node": node, "cx": _f(x), "cy": _f(y),
                                            "r": _f(0.5 * part.hole_diameter), **cut})
        x0, y0, _, _ = _extent(part)
        x, y = sheet((x0, y0 + 0.5 * TEXT))
        label = ET.SubElement(group, "text", {"class": "label", "x": _f(x), "y": _f(y), "font-size": _f(TEXT),
                                              "font-family": "sans-serif", "fill": "blue"})
        label.text = part.name
        for a, b, distance, p, q, n, offset in _dimensions(part):
            dim = ET.SubElement(group, "g", {"class": "dimension", "data-holes": f"{a} {b}"})
            for end in (p, q):
                (x1, y1), (x2, y2) = sheet(end + n * (0.5 * part.hole_diameter + 1.0)), sheet(end + n * (offset + 1.0))
                ET.SubElement(dim, "line", {"x1": _f(x1), "y1": _f(y1), "x2": _f(x2), "y2": _f(y2), **note})
            (x1, y1), (x2, y2) = sheet(p + n * offset), sheet(q + n * offset)
            ET.SubElement(dim, "line", {"x1": _f(x1), "y1": _f(y1), "x2": _f(x2), "y2": _f(y2), **note,
                                        "marker-start": "url(#arrow)", "marker-end": "url(#arrow)"})
            tx, ty = sheet(0.5 * (p + q) + n * (offset + 0.5 * TEXT + 0.6))
            angle = math.degrees(math.atan2(y2 - y1, x2 - x1))
            angle = angle - 180.0 if angle > 90.0 else angle + 180.0 if angle <= -90.0 else angle
            text = ET.SubElement(dim, "text", {"x": _f(tx), "y": _f(ty), "font-size": _f(TEXT), "fill": "blue",
                                               "font-family": "sans-serif", "text-anchor": "middle",
                                               "dominant-baseline": "middle",
                                               "transform": f"rotate({_f(angle)} {_f(tx)} {_f(ty)})"})
            text.text = f"{distance:.1f}"
    path = pathlib.Path(path)
    ET.indent(svg)
    ET.ElementTree(svg).write(path, encoding="utf-8", xml_declaration=True)
    return path


def write_dxf(linkage: Linkage, path, *, style: BarStyle = DEFAULT_STYLE, metadata: dict | None = None,
              hole_diameter: float | None = None) -> pathlib.Path:
    """Write the fabrication drawing of ``linkage`` as a DXF (R2010) in millimetres ($INSUNITS 4,
    $MEASUREMENT 1), laid out as write_svg lays it (y up). Each part is a layer named by its link
    holding the outline as closed LWPOLYLINEs (exterior and any interior rings), the holes as
    CIRCLEs (node name as XDATA of APPID), the label as TEXT and one rendered ALIGNED DIMENSION per
    pair of holes (0.1 mm precision). ``metadata`` is stored as JSON in the XRECORD METADATA_KEY of
    the root dictionary (chunks of group code 1), the linkage name as the custom header variable
    'morphopt_linkage'. Returns the path."""
    import ezdxf
    from ezdxf.lldxf.validator import is_valid_layer_name

    parts = link_parts(linkage, style=style, hole_diameter=hole_diameter)
    for part in parts:
        if not is_valid_layer_name(part.name):
            raise ValueError(f"linkage '{linkage.name}': link '{part.name}' is not a valid DXF layer name")
    placed, _, height = _placed(parts)
    doc = ezdxf.new("R2010", setup=True, units=ezdxf.units.MM)
    doc.header["$INSUNITS"] = 4
    doc.header["$MEASUREMENT"] = 1
    doc.header.custom_vars.append("morphopt_linkage", linkage.name)
    doc.appids.add(APPID)
    doc.dimstyles.duplicate_entry("EZDXF", "MORPHOPT_MM")
    dimstyle = doc.dimstyles.get("MORPHOPT_MM")
    mm = {"dimtxt": TEXT * 0.8, "dimasz": 2.0, "dimdec": 1, "dimlfac": 1.0, "dimexo": 1.0, "dimexe": 1.0,
          "dimgap": 0.6, "dimblk": "", "dimtad": 1, "dimtih": 0, "dimtoh": 0, "dimzin": 0}  # 0.1 mm, "50.0"
    for key, value in mm.items():
        dimstyle.dxf.set(key, value)
    payload = metadata_json(metadata)
    record = doc.rootdict.add_xrecord(METADATA_KEY)
    record.reset([(1, payload[i:i + 250]) for i in range(0, len(payload), 250)] or [(1, "")])
    msp = doc.modelspace()

    def at(sheet, p):
        x, y = sheet(p)
        return float(x), float(height - y)

    for part, sheet in placed:
        doc.layers.add(part.name)
        attribs = {"layer": part.name}
        for ring in [part.outline.exterior, *part.outline.interiors]:
            msp.add_lwpolyline([at(sheet, p) for p in ring.coords[:-1]], format="xy", close=True, dxfattribs=attribs)
        for node, centre in part.holes.items():
            circle = msp.add_circle(at(sheet, centre), 0.5 * part.hole_diameter, dxfattribs=attribs)
            circle.set_xdata(APPID, [(1000, node)])
        x0, y0, _, _ = _extent(part)
        msp.add_text(part.name, height=TEXT, dxfattribs=attribs).set_placement(at(sheet, (x0, y0 + 0.5 * TEXT)))
        for _, _, _, p, q, n, offset in _dimensions(part):
            p1, p2 = at(sheet, p), at(sheet, q)
            left = np.array([p1[1] - p2[1], p2[0] - p1[0]])  # left of p1 -> p2 on the sheet
            pn = np.subtract(at(sheet, p + n), p1)
            side = 1.0 if left @ pn > 0.0 else -1.0
            msp.add_aligned_dim(p1, p2, distance=side * offset, dimstyle="MORPHOPT_MM",
                                dxfattribs=attribs).render()
    path = pathlib.Path(path)
    doc.saveas(path)
    return path


def read_dxf_metadata(doc_or_path) -> dict:
    """The metadata dict that write_dxf stored in a DXF (an ezdxf document or a path)."""
    import ezdxf

    doc = doc_or_path if hasattr(doc_or_path, "rootdict") else ezdxf.readfile(doc_or_path)
    record = doc.rootdict[METADATA_KEY]
    return json.loads("".join(value for code, value in record.tags if code == 1))
