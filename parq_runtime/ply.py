"""Scene boxes as coloured wireframes in a PLY file (``parq-run --ply``).

ASCII PLY with two elements, which MeshLab, Open3D (``o3d.io.read_line_set``) and CloudCompare
read as a line set:

    element vertex 8N    x y z (float, metres, the capture's world frame), red green blue
    element edge 12N     vertex1 vertex2 (int), red green blue

Box b owns vertices 8b .. 8b + 7 (its corners in geometry.CORNER_SIGNS order) and edges
12b .. 12b + 11 (geometry.BOX_EDGES); the colour is the class's (:func:`class_color`), and a
comment line per box gives its class and score.
"""
from __future__ import annotations

import numpy as np

from . import files, geometry

# Distinct, saturated colours (RGB), one per class index, repeating after ten.
PALETTE = ((230, 25, 75), (60, 180, 75), (255, 225, 25), (0, 130, 200), (245, 130, 48),
           (145, 30, 180), (70, 240, 240), (240, 50, 230), (210, 245, 60), (250, 190, 190))


def class_color(label: int) -> tuple:
    """RGB of a class index."""
    return PALETTE[int(label) % len(PALETTE)]


def ply_text(boxes) -> str:
    """The PLY file for ``boxes`` (objects with ``corners`` (8, 3), ``label``, ``class_name``,
    ``score``)."""
    boxes = list(boxes)
    lines = ["ply", "format ascii 1.0",
             "comment parq-onnx scene boxes: world frame, metres; 8 vertices and 12 edges a box"]
    for i, b in enumerate(boxes):
        name = str(b.class_name).replace("\n", " ")
        lines.append(f"comment box {i}: {name} {float(b.score):.4f}")
    lines += [f"element vertex {8 * len(boxes)}", "property float x", "property float y",
              "property float z", "property uchar red", "property uchar green",
              "property uchar blue", f"element edge {12 * len(boxes)}", "property int vertex1",
              "property int vertex2", "property uchar red", "property uchar green",
              "property uchar blue", "end_header"]
    for b in boxes:
        r, g, bl = class_color(b.label)
        for x, y, z in np.asarray(b.corners, dtype=np.float64).reshape(8, 3):
            lines.append(f"{x:.6f} {y:.6f} {z:.6f} {r} {g} {bl}")
    for i, b in enumerate(boxes):
        r, g, bl = class_color(b.label)
        for a, c in geometry.BOX_EDGES:
            lines.append(f"{8 * i + a} {8 * i + c} {r} {g} {bl}")
    return "\n".join(lines) + "\n"


def write(path, boxes) -> None:
    """Write the PLY atomically (complete or absent)."""
    files.atomic_write(path, ply_text(boxes))
