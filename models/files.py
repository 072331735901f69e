"""Atomic file output: a reader sees the old file or the whole new one, never a partial write.

The one place files are written this way (recordings' summaries, datasets, calibrations,
checkpoints, command results), so a crash or a full disk never leaves a truncated output.
"""

from __future__ import annotations

import json
import os
import shutil
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import Any


def write_atomically(path: Path, write: Callable[[Path], None]) -> Path:
    """Call ``write`` on a temporary file in ``path``'s folder, then rename it onto ``path``."""
    path.parent.mkdir(parents=True, exist_ok=True)
    handle, temp_name = tempfile.mkstemp(
        prefix=f".{path.name}.", suffix=path.suffix, dir=path.parent
    )
    os.close(handle)
    try:
        os.chmod(temp_name, 0o644)  # mkstemp makes it private; outputs are ordinary files
        write(Path(temp_name))
        os.replace(temp_name, path)
    except BaseException:
        Path(temp_name).unlink(missing_ok=True)
        raise
    return path


def write_text_atomically(path: Path, text: str) -> Path:
    return write_atomically(path, lambda temp: temp.write_text(text, encoding="utf-8"))


def write_json_atomically(path: Path, value: Any) -> Path:
    """Indented JSON with a final newline."""
    return write_text_atomically(path, json.dumps(value, indent=2) + "\n")


def write_folder_atomically(out: Path, writers: dict[str, Callable[[Path], None]]) -> list[Path]:
    """Write files into a temporary folder beside ``out``, then move them into place.

    A new ``out`` appears in one rename; into an existing folder each file is replaced in one
    rename. If any writer fails, nothing under ``out`` changes.
    """
    if out.exists() and not out.is_dir():
        raise NotADirectoryError(f"output {out} exists and is not a folder")
    out.parent.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix=f".{out.name}.", dir=out.parent))
    try:
        staging.chmod(0o755)  # mkdtemp makes it private; the output is an ordinary folder
        for file_name, write in writers.items():
            write(staging / file_name)
        if not out.exists():
            os.replace(staging, out)
        else:
            for file_name in writers:
                os.replace(staging / file_name, out / file_name)
            staging.rmdir()
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        raise
    return [out / file_name for file_name in writers]
