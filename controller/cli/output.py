"""How commands hand results to the user: JSON on stdout, and to a file when asked."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from models.files import write_json_atomically


def print_json(result: Any, path: Path | None = None, *, shown: Any = None) -> None:
    """Print ``shown`` (default: ``result``) as indented JSON; write ``result`` to ``path``."""
    print(json.dumps(result if shown is None else shown, indent=2))
    if path is not None:
        write_json_atomically(path, result)
