"""The JSON records datagen writes (atomically, so a crash never leaves half a record) and reads back."""
from __future__ import annotations

import json
from pathlib import Path

from dibrpp.io import DataError, atomic_path


def write_json(path: Path, data) -> None:
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps(data, indent=1, sort_keys=True))


def read_record(path: Path, fix: str = "delete its folder to regenerate it") -> dict:
    """A JSON object written by datagen; DataError naming the file if it is unreadable, not JSON or not an
    object. ``fix`` says what the user can do about it."""
    try:
        data = json.loads(Path(path).read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise DataError(f"{path}: unreadable or corrupt JSON ({e}); {fix}") from e
    if not isinstance(data, dict):
        raise DataError(f"{path}: expected a JSON object ({{...}}), found {type(data).__name__}; {fix}")
    return data
