"""A training run's checkpoint in float16: small enough to commit, exact to resume.

A machine is not kept from one working session to the next, so the object-frame runs keep their
checkpoints in the repository (``training_state/``, <= 40 MB in all). Every floating tensor of
the model and the optimizer is stored in float16; Adam's second moment as its square root (its
values reach 1e-12, below float16's range, while their roots do not). A finished run keeps its
model only.

Resume is bit-exact because the live run is *rounded to what the file holds* each time it
writes one (:func:`round_to_stored`): a run resumed from the file and one never stopped hold the
same numbers from then on. Checkpoints are written at fixed steps and at epoch ends, and a run
asked to stop goes on to the next checkpoint step, so the rounding happens at the same steps in
every run, stopped or not. The rounding perturbs the weights by 2^-11 relative once per
checkpoint, far below one optimiser step's noise.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import torch
from torch import Tensor, nn

from models.files import write_atomically

STATE_VERSION = 1
_SQRT_KEYS = ("exp_avg_sq", "max_exp_avg_sq")  # Adam's second moments: stored as their roots


class TrainingStateError(ValueError):
    """A checkpoint is unreadable, corrupt or of another run; the message names the file."""


def _encode(key: str, value: Any) -> Any:
    if not isinstance(value, Tensor) or not value.is_floating_point():
        return value
    stored = value.detach().sqrt() if key in _SQRT_KEYS else value.detach()
    half = stored.to(torch.float16)
    if not torch.isfinite(half).all():
        raise OverflowError(f"{key}: values beyond float16's range cannot be checkpointed")
    return half


def _decode(key: str, value: Any, like: Tensor | None = None) -> Any:
    if not isinstance(value, Tensor) or not value.is_floating_point():
        return value
    full = value.float()
    full = full.square() if key in _SQRT_KEYS else full
    return full.to(like.dtype) if like is not None else full


def _optimizer_state(optimizer: torch.optim.Optimizer, code) -> dict:
    state = optimizer.state_dict()
    return {
        "state": {
            index: {key: code(key, value) for key, value in slot.items()}
            for index, slot in state["state"].items()
        },
        "param_groups": state["param_groups"],
    }


def encode_state(model: nn.Module, optimizer: torch.optim.Optimizer | None, progress: dict) -> dict:
    """The float16 checkpoint of a run: model, optimizer (None when finished), progress."""
    return {
        "version": STATE_VERSION,
        "model": {key: _encode(key, value) for key, value in model.state_dict().items()},
        "optimizer": None if optimizer is None else _optimizer_state(optimizer, _encode),
        **progress,
    }


@torch.no_grad()
def round_to_stored(model: nn.Module, optimizer: torch.optim.Optimizer) -> None:
    """Round the live model and optimizer to exactly what :func:`encode_state` stores."""
    for key, value in model.state_dict().items():  # state_dict tensors share storage
        value.copy_(_decode(key, _encode(key, value), value))
    for slot in optimizer.state.values():
        for key, value in slot.items():
            if isinstance(value, Tensor) and value.is_floating_point():
                value.copy_(_decode(key, _encode(key, value), value))


def save_state(path: Path, state: dict) -> None:
    write_atomically(path, lambda temporary: torch.save(state, temporary))


def load_state(path: Path, model: nn.Module, optimizer: torch.optim.Optimizer) -> dict:
    """Restore ``model`` and ``optimizer`` from a checkpoint; returns its progress entries.

    A finished run's checkpoint has no optimizer state: the optimizer starts afresh (a run
    asked for more epochs than it had). Raises :class:`TrainingStateError` naming the file.
    """
    try:
        state = torch.load(path, map_location="cpu", weights_only=False)
        if not isinstance(state, dict) or state.get("version") != STATE_VERSION:
            raise ValueError(f"not a version-{STATE_VERSION} training checkpoint")
        current = model.state_dict()
        model.load_state_dict(
            {key: _decode(key, value, current.get(key)) for key, value in state["model"].items()}
        )
        if state["optimizer"] is not None:
            optimizer.load_state_dict(
                {
                    "state": {
                        index: {key: _decode(key, value) for key, value in slot.items()}
                        for index, slot in state["optimizer"]["state"].items()
                    },
                    "param_groups": state["optimizer"]["param_groups"],
                }
            )
    except Exception as error:  # torch.load and load_state_dict raise many kinds
        reason = str(error).strip().splitlines()[0][:200] if str(error).strip() else repr(error)
        raise TrainingStateError(f"{path}: not a usable training checkpoint ({reason})") from None
    return {key: value for key, value in state.items() if key not in ("model", "optimizer")}
