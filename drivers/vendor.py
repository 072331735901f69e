"""Lazy imports of vendor SDKs: a backend imports its SDK when it is built, and a missing SDK is
an error that names the extra to install."""

from __future__ import annotations

import importlib
from types import ModuleType

from drivers.base import DeviceConnectionError


class MissingSDKError(DeviceConnectionError, ImportError):
    """A device backend's vendor SDK is not installed (or its native library is missing)."""


def import_sdk(module: str, *, extra: str, device: str, note: str = "") -> ModuleType:
    """``import module``, or MissingSDKError saying ``pip install 'touchshape[extra]'``."""
    try:
        return importlib.import_module(module)
    except ImportError as error:
        hint = f"; {note}" if note else ""
        raise MissingSDKError(
            f"the {device} backend needs the '{module}' package: "
            f"pip install 'touchshape[{extra}]'{hint} ({error})"
        ) from error
