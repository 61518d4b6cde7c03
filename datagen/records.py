"""The JSON records datagen writes (atomically, so a crash never leaves half a record) and reads back."""
from __future__ import annotations

import json
from pathlib import Path

from dibrpp.io import DataError, atomic_path


def write_json(path: Path, data) -> None:
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps(data, indent=1, sort_keys=True))


def read_json(path: Path):
    try:
        return json.loads(Path(path).read_text())
    except (OSError, json.JSONDecodeError) as e:
        raise DataError(f"{path}: unreadable or corrupt JSON ({e}); delete its folder to regenerate it") from e
