"""The document tier: pydantic v2 models of a layer stack (``stack.json``) and of learned-layer
presets, blend names, JSON load/save and JSON Schema generation. No torch here (docs/ARCHITECTURE.md).
"""

from lasagna.document.blend import (
    ACCEPTED_BLEND_NAMES,
    BLEND_ALIASES,
    BLEND_MODES,
    RANGED_BLENDS,
    BlendMode,
    canonical_blend,
)
from lasagna.document.files import STACK_FILE, load_document, save_document, stack_file
from lasagna.document.models import (
    FORMAT,
    LAYER_KINDS,
    VERSION,
    Canvas,
    Condition,
    Document,
    GeneratorRef,
    GroupLayer,
    Layer,
    LearnedLayer,
    Offset,
    PixelsLayer,
    Size,
    SolidLayer,
)
from lasagna.document.preset import (
    LOSS_NAMES,
    ControlNetRef,
    DiffusersOptions,
    DistillDefaults,
    LossName,
    Preset,
    PriorLink,
    default_catalogues,
    load_preset,
    resolve_preset,
)
from lasagna.document.schema import SCHEMA_BASE, schemas, write_schemas
from lasagna.document.types import check_id, check_relative_path
from lasagna.document.validation import RuleError, format_validation_error, parse_json

__all__ = [
    "ACCEPTED_BLEND_NAMES",
    "BLEND_ALIASES",
    "BLEND_MODES",
    "RANGED_BLENDS",
    "BlendMode",
    "canonical_blend",
    "STACK_FILE",
    "load_document",
    "save_document",
    "stack_file",
    "FORMAT",
    "LAYER_KINDS",
    "VERSION",
    "Canvas",
    "Condition",
    "Document",
    "GeneratorRef",
    "GroupLayer",
    "Layer",
    "LearnedLayer",
    "Offset",
    "PixelsLayer",
    "Size",
    "SolidLayer",
    "LOSS_NAMES",
    "ControlNetRef",
    "DiffusersOptions",
    "DistillDefaults",
    "LossName",
    "Preset",
    "PriorLink",
    "default_catalogues",
    "load_preset",
    "resolve_preset",
    "SCHEMA_BASE",
    "schemas",
    "write_schemas",
    "check_id",
    "check_relative_path",
    "RuleError",
    "format_validation_error",
    "parse_json",
]
