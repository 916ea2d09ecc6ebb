"""Rotational symmetry of the generated shapes about their up axis, for the rotation loss.

A shape that looks the same after a turn of 360/n degrees about object y gets n folds; its
rotation target is ambiguous between those turns, so the loss takes the nearest one (as the
authors do with Scan2CAD's symmetry tags).  Round shapes use 36 folds.
"""
from __future__ import annotations

# Read off parq_synth.shapes: tables and bathtubs are symmetric front-to-back and left-to-right
# (2 folds), trash bins are round; chairs, sofas, bookshelves, cabinets and displays have a
# front; "other" is a plain box or cylinder, taken as 2-fold.
FOLDS = {"chair": 1, "table": 2, "cabinet": 1, "trash bin": 2, "bookshelf": 1, "display": 1,
         "sofa": 1, "bathtub": 2, "other": 2}


def folds_of_class(classes) -> list:
    return [FOLDS.get(name, 1) for name in classes]
