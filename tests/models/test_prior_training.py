"""Training: the paper's losses lower on a tiny dataset; checkpoints resume; DDP on gloo."""

from __future__ import annotations

import json
import os
import socket
from pathlib import Path

import pytest
import torch
import torch.multiprocessing as mp

from models.prior import networks
from models.prior.dataset import BuildSpec, SketchVoxelDataset, ViewRecipe, build_dataset
from models.prior.networks import NetworkPreset, ShapeNet, SketchNet, normalise_rgb
from models.prior.training import (
    TrainConfig,
    _mix_predicted_sketches,
    epoch_learning_rate,
    ground_truth_shape_input,
    paper_optimizer,
    predicted_shape_input,
    save_weights,
    sensor_shape_input,
    shape_loss,
    sketch_loss,
    train,
)
from models.prior.training_state import TrainingStateError

TINY_PRESET = NetworkPreset("tiny", 64, 16, 8, (16, 16, 8, 8, 8), (16, 8))


@pytest.fixture(autouse=True)
def tiny_preset(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(networks.PRESETS, "tiny", TINY_PRESET)


@pytest.fixture(scope="module")
def tiny_data(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("data")
    build_dataset(
        BuildSpec(
            str(out),
            categories=("mug", "box", "bowl"),
            shapes_per_category=3,
            views=2,
            shapes_per_shard=3,
            recipe=ViewRecipe(image_size=64, voxel_resolution=16),
        ),
        workers=1,
        progress=False,
    )
    return out


def _batch(data: Path) -> dict[str, torch.Tensor]:
    dataset = SketchVoxelDataset(data)
    samples = [dataset[i] for i in range(8)]
    return {key: torch.stack([s[key] for s in samples]) for key in samples[0]}


def test_sketch_loss_decreases(tiny_data: Path) -> None:
    torch.manual_seed(0)
    batch = _batch(tiny_data)
    model = SketchNet(TINY_PRESET)
    optimizer = paper_optimizer("sketch", model, None)
    losses = []
    for _ in range(15):
        loss = sketch_loss(model(normalise_rgb(batch["rgb"])), batch)["total"]
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        losses.append(loss.item())
    assert losses[-1] < 0.5 * losses[0]


def test_shape_loss_decreases(tiny_data: Path) -> None:
    torch.manual_seed(0)
    batch = _batch(tiny_data)
    model = ShapeNet(TINY_PRESET)
    optimizer = paper_optimizer("shape", model, None)
    losses = []
    for _ in range(25):
        loss = shape_loss(model(ground_truth_shape_input(batch)), batch["voxels"])
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        losses.append(loss.item())
    assert losses[-1] < 0.5 * losses[0]


def test_train_writes_metrics_weights_and_resumes(tiny_data: Path, tmp_path: Path) -> None:
    sketch_config = TrainConfig(
        "sketch",
        (str(tiny_data),),
        str(tmp_path / "sketch"),
        preset="tiny",
        epochs=1,
        batch_size=4,
        val_fraction=0.3,
    )
    train(sketch_config, progress=False)
    sketch_weights = tmp_path / "sketch" / "sketch.pt"
    assert sketch_weights.exists()

    config = TrainConfig(
        "shape",
        (str(tiny_data),),
        str(tmp_path / "shape"),
        preset="tiny",
        epochs=1,
        batch_size=4,
        val_fraction=0.3,
        sketch_weights=str(sketch_weights),
    )
    first = train(config, progress=False)
    assert {"val_loss", "val_iou_gt_sketch", "val_iou_pred_sketch"} <= set(first)
    checkpoint = torch.load(tmp_path / "shape" / "checkpoint.pt", weights_only=False)
    assert checkpoint["epoch"] == 1
    # Asking for two epochs resumes at epoch 1 and trains only the second.
    train(TrainConfig(**{**config.__dict__, "epochs": 2}), progress=False)
    records = [json.loads(line) for line in (tmp_path / "shape" / "metrics.jsonl").open()]
    epochs = [r["epoch"] for r in records if "val_loss" in r]
    assert epochs == [1, 2]
    assert torch.load(tmp_path / "shape" / "checkpoint.pt", weights_only=False)["epoch"] == 2


@pytest.mark.parametrize("stage", ["sketch", "shape"])
def test_a_resumed_run_trains_bit_exact(tiny_data: Path, tmp_path: Path, stage: str) -> None:
    """Stopped after its first batch and resumed from the float16 checkpoint on another machine
    (a fresh run folder, the committed state file only), a run ends with the same weights as
    one never stopped: the next batch sees the same samples, jitter and noise, and the live run
    holds the checkpoint's numbers."""
    common: dict = {
        "preset": "tiny",
        "epochs": 2,
        "batch_size": 2,
        "val_fraction": 0.3,
        "checkpoint_every_steps": 1,
    }
    if stage == "shape":  # half the samples from a sketch net's predictions: drawn per step too
        save_weights(SketchNet(TINY_PRESET), "sketch", "tiny", tmp_path / "sketch.pt")
        common |= {"sketch_weights": str(tmp_path / "sketch.pt"), "predicted_sketch_prob": 0.5}
    whole = TrainConfig(stage, (str(tiny_data),), str(tmp_path / "whole"), **common)
    train(whole, progress=False)
    state = tmp_path / "training_state" / f"{stage}.pt"
    first_machine = TrainConfig(
        stage, (str(tiny_data),), str(tmp_path / "first"), checkpoint=str(state), **common
    )
    train(TrainConfig(**{**first_machine.__dict__, "max_minutes": 1e-9}), progress=False)
    stopped = torch.load(state, weights_only=False)
    assert (stopped["epoch"], stopped["batch_in_epoch"], stopped["step"]) == (0, 1, 1)
    floats = [t for t in stopped["model"].values() if t.is_floating_point()]
    floats += [
        t
        for slot in stopped["optimizer"]["state"].values()
        for key, t in slot.items()
        if key != "step" and t.is_floating_point()
    ]
    assert floats and all(t.dtype == torch.float16 for t in floats)
    second_machine = TrainConfig(**{**first_machine.__dict__, "out_dir": str(tmp_path / "next")})
    train(second_machine, progress=False)
    ends = [torch.load(f, weights_only=False) for f in (tmp_path / "whole/checkpoint.pt", state)]
    assert ends[0]["step"] == ends[1]["step"] > 2
    assert ends[1]["optimizer"] is None  # a finished run keeps its model only
    for name, tensor in ends[0]["model"].items():
        assert torch.equal(tensor, ends[1]["model"][name]), name


def test_a_corrupt_checkpoint_is_refused_naming_the_file(tiny_data: Path, tmp_path: Path) -> None:
    state = tmp_path / "shape.pt"
    state.write_bytes(b"not a checkpoint")
    config = TrainConfig(
        "shape", (str(tiny_data),), str(tmp_path / "run"), preset="tiny", checkpoint=str(state)
    )
    with pytest.raises(TrainingStateError, match=r"shape\.pt: not a usable training checkpoint"):
        train(config, progress=False)
    assert state.read_bytes() == b"not a checkpoint"  # left as it was for the user to look at


def test_the_learning_rate_decays_by_epoch() -> None:
    config = TrainConfig("shape", ("data",), "out", lr_decay_epochs=(2, 4), lr_decay_factor=0.5)
    rates = [epoch_learning_rate(config, epoch) for epoch in range(6)]
    assert rates == pytest.approx([2e-2, 2e-2, 1e-2, 1e-2, 5e-3, 5e-3])


def test_predicted_sketches_replace_the_true_ones_for_their_fraction(tiny_data: Path) -> None:
    torch.manual_seed(0)
    batch = _batch(tiny_data)
    sketch_net = SketchNet(TINY_PRESET).eval()
    true_inputs = ground_truth_shape_input(batch)
    with torch.no_grad():
        predicted = predicted_shape_input(sketch_net(normalise_rgb(batch["rgb"])))
    assert not torch.equal(predicted, true_inputs)
    every = _mix_predicted_sketches(
        true_inputs, batch, sketch_net, 1.0, torch.Generator().manual_seed(1)
    )
    assert torch.equal(every, predicted)
    none = _mix_predicted_sketches(
        true_inputs, batch, sketch_net, 0.0, torch.Generator().manual_seed(1)
    )
    assert torch.equal(none, true_inputs)
    half = _mix_predicted_sketches(
        true_inputs, batch, sketch_net, 0.5, torch.Generator().manual_seed(1)
    )
    from_prediction = [torch.equal(half[i], predicted[i]) for i in range(len(half))]
    assert 0 < sum(from_prediction) < len(half)
    assert all(torch.equal(half[i], true_inputs[i]) for i, p in enumerate(from_prediction) if not p)


def test_object_frame_views_carry_the_normals_of_their_sensor_depth(tiny_data: Path) -> None:
    """The loader rebuilds each view's virtual camera and takes the normals of its simulated
    Kinect depth as RGB-D inference does: they follow the true normals on the object."""
    batch = _batch(tiny_data)
    measured, true = batch["sensor_normals"], batch["normals"]
    known = (measured.abs().sum(dim=1) > 0) & (batch["silhouette"][:, 0] > 0)
    assert known.sum() > 0.1 * (batch["silhouette"] > 0).sum()  # 64 px crops: coarse pixels
    cosine = (measured * true).sum(dim=1)[known]
    assert float(torch.rad2deg(torch.arccos(cosine.clamp(-1, 1))).median()) < 15.0


def test_sensor_samples_take_the_sensor_normals_where_known(tiny_data: Path) -> None:
    batch = _batch(tiny_data)
    generator = torch.Generator().manual_seed(0)
    inputs = ground_truth_shape_input(batch, 1.0, generator, sensor_normals=True)
    known = batch["sensor_normals"].abs().sum(dim=1, keepdim=True) > 0
    silhouette = batch["silhouette"] > 0
    expected = torch.where(known, batch["sensor_normals"], batch["normals"])
    assert torch.equal(inputs[:, 1:] * silhouette, expected * silhouette)
    assert not torch.equal(expected * silhouette, batch["normals"] * silhouette)
    # Without the flag the normals stay the true ones (the committed weights' recipe).
    plain = ground_truth_shape_input(batch, 1.0, torch.Generator().manual_seed(0))
    assert torch.equal(plain[:, 1:], batch["normals"] * batch["silhouette"])
    # Validation's RGB-D input: the sensor where it measured, the prediction elsewhere.
    prediction = {"depth": torch.zeros_like(batch["nearness"]), "normals": batch["normals"]}
    rgbd = sensor_shape_input(batch, prediction)
    assert torch.equal(rgbd[:, 1:], expected * batch["silhouette"])


def test_training_on_predicted_sketches_needs_the_sketch_weights(
    tiny_data: Path, tmp_path: Path
) -> None:
    config = TrainConfig(
        "shape", (str(tiny_data),), str(tmp_path / "s"), preset="tiny", predicted_sketch_prob=0.5
    )
    with pytest.raises(ValueError, match="sketch_weights"):
        train(config, progress=False)


def _ddp_worker(rank: int, port: int, data: str, out: str) -> None:
    os.environ.update(
        MASTER_ADDR="127.0.0.1",
        MASTER_PORT=str(port),
        RANK=str(rank),
        WORLD_SIZE="2",
        LOCAL_RANK=str(rank),
    )
    networks.PRESETS["tiny"] = TINY_PRESET  # spawned processes start from a fresh import
    torch.set_num_threads(1)
    train(
        TrainConfig("shape", (data,), out, preset="tiny", epochs=1, batch_size=2, val_fraction=0.3),
        progress=False,
    )


@pytest.mark.slow  # spawning two processes takes ~20 s on two cores
def test_ddp_two_processes_on_gloo(tiny_data: Path, tmp_path: Path) -> None:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    mp.spawn(_ddp_worker, args=(port, str(tiny_data), str(tmp_path)), nprocs=2)
    assert (tmp_path / "shape.pt").exists()
    records = [json.loads(line) for line in (tmp_path / "metrics.jsonl").open()]
    assert records[-1]["epoch"] == 1
