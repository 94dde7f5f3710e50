"""JSON Schemas of every file relocdepth writes or reads, and a validator for them.

The schema files sit beside this module (``<name>.schema.json``); readers call
:func:`validate` on what they load so that a malformed file fails with one clear line.
"""

from __future__ import annotations

import functools
import json
from pathlib import Path
from typing import Any

from relocdepth.errors import UserError

SCHEMA_DIR = Path(__file__).resolve().parent


@functools.cache
def load_schema(name: str) -> dict:
    """The schema ``name`` (e.g. ``"manifest"``), read from ``<name>.schema.json``."""
    path = SCHEMA_DIR / f"{name}.schema.json"
    return json.loads(path.read_text())


def validate(name: str, obj: Any, what: str | None = None) -> None:
    """Validate ``obj`` against schema ``name``; a failure is a :class:`UserError` naming the field."""
    import jsonschema

    try:
        jsonschema.validate(obj, load_schema(name))
    except jsonschema.ValidationError as e:
        field = "/".join(str(p) for p in e.absolute_path) or "(top level)"
        raise UserError(f"{what or name}: invalid field '{field}': {e.message}") from None
