"""Every model family by the `kind` its files carry, and reading a model file of any of them. Nothing inside
sma_stage.model imports this module: a family knows only itself."""

from __future__ import annotations

import os
from pathlib import Path

from sma_stage.errors import InputError
from sma_stage.io.safe_yaml import parse_yaml, read_text_file
from sma_stage.model.bouc_wen import BoucWenModel
from sma_stage.model.identified import IdentifiedModel
from sma_stage.model.parameters import MODEL_KIND
from sma_stage.model.two_wire import TwoWireModel

AnyModel = IdentifiedModel | TwoWireModel | BoucWenModel
StreamModel = TwoWireModel | BoucWenModel  # the families run one held current at a time (their `stream`)
KINDS: dict[str, type[IdentifiedModel] | type[TwoWireModel] | type[BoucWenModel]] = {
    MODEL_KIND: IdentifiedModel, TwoWireModel.KIND: TwoWireModel, BoucWenModel.KIND: BoucWenModel}


def any_model_from_yaml_text(text: str) -> AnyModel:
    """A model of any family from YAML text, by its `kind` (gpi when it names none)."""
    document = parse_yaml(text)
    kind = document.get("kind") if isinstance(document, dict) else None
    family = KINDS.get(kind, IdentifiedModel) if isinstance(kind, str) else IdentifiedModel
    return family.from_dict(document)


def load_any_model_file(path: str | os.PathLike) -> AnyModel:
    """A model file of any family, by its `kind`; any problem is one InputError line naming the file."""
    text = read_text_file(path, "model file")
    try:
        return any_model_from_yaml_text(text)
    except InputError as error:
        raise InputError(f"model file {Path(path)}: {error}") from None
