"""The committed training state keeps the rules it may be committed under: one folder of
float16 checkpoints, at most 40 MB in all."""

from __future__ import annotations

from pathlib import Path

import torch

STATE = Path(__file__).resolve().parents[2] / "training_state"
MAX_BYTES = 40_000_000


def _checkpoints() -> list[Path]:
    return sorted(STATE.rglob("*.pt"))


def test_the_training_state_is_at_most_40_mb() -> None:
    assert sum(p.stat().st_size for p in _checkpoints()) <= MAX_BYTES


def test_every_floating_tensor_of_the_training_state_is_float16() -> None:
    for path in _checkpoints():
        state = torch.load(path, map_location="cpu", weights_only=False)
        # A checkpoint ("model", "optimizer"), or a finished run's weights file ("state_dict").
        tensors = list(state.get("model", state.get("state_dict", {})).values())
        if state.get("optimizer") is not None:
            tensors += [
                t
                for slot in state["optimizer"]["state"].values()
                for k, t in slot.items()
                if k != "step"
            ]
        floats = [t for t in tensors if t.is_floating_point()]
        assert floats, path
        assert {t.dtype for t in floats} == {torch.float16}, path
