"""Change an exported model folder's card without exporting again.

The card lives in ``model.json`` and is mirrored in each graph's ``metadata_props``
(``parq.model_card``, parq_export.export); a change must reach all three, and the graphs'
sha256 in the card must follow their new bytes.  Only the metadata changes: the graphs'
weights and nodes are read and written back untouched.  parq_train.tune uses this to choose a
model folder's post-processing again (the shipped demo's ``ray`` fusion was chosen that way).
"""
from __future__ import annotations

import hashlib
import json
import pathlib

import onnx

from parq_runtime import files, model_card
from parq_runtime.errors import ParqError
from parq_runtime.model_card import METADATA_KEY

ROLES = ("backbone", "layer")


def rewrite(source, out_dir, update, overwrite: bool = False) -> dict:
    """Write a copy of the model folder ``source`` (its graphs and model.json) to ``out_dir``
    with ``update(card)`` applied, in place, to its card and to each graph's mirrored card;
    returns the new card.  Nothing is written when ``source`` is not a valid model folder or
    the result would not load."""
    source, out_dir = pathlib.Path(source), pathlib.Path(out_dir)
    card = json.loads(json.dumps(model_card.load(source).raw))   # a deep copy, validated
    if out_dir.exists() and not overwrite:
        raise ParqError(f"{out_dir}: already exists")
    if out_dir.resolve() == source.resolve():
        raise ParqError(f"{out_dir}: is the source folder; write the copy elsewhere")
    with files.atomic_folder(out_dir, "the model folder") as tmp:
        for role in ROLES:
            name = card["graphs"][role]["file"]
            proto = onnx.load(str(source / name))
            mirrored = [e for e in proto.metadata_props if e.key == METADATA_KEY]
            if len(mirrored) != 1:
                raise ParqError(f"{source / name}: holds no mirrored model card "
                                f"({METADATA_KEY} in metadata_props)")
            inner = json.loads(mirrored[0].value)
            update(inner)
            mirrored[0].value = json.dumps(inner, sort_keys=True)
            onnx.save(proto, str(tmp / name))
            card["graphs"][role]["sha256"] = hashlib.sha256((tmp / name).read_bytes()).hexdigest()
        update(card)
        (tmp / "model.json").write_text(json.dumps(card, indent=1) + "\n")
        model_card.load(tmp)       # the new card must load (and its hashes match)
    return card
