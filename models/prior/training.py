"""Training of the 2.5D sketch net and the shape net, as in the paper.

* Sketch net: Adam (lr 5e-4, betas 0.5 / 0.9), L2 losses on depth (nearness), normals and the
  silhouette probability, summed; colour and light jitter (kornia) on the RGB input.
* Shape net: SGD (lr 2e-2, momentum 0.9), binary cross-entropy on the voxels, trained on
  ground-truth sketches (depth + normals masked by the silhouette). ``sensor_depth_prob`` of the
  samples replace the depth by the simulated Kinect depth (holes filled from the clean depth),
  and with ``sensor_normals`` the normals by the sensor depth's where known, so the RGB-D mode
  sees what it was trained on. Validation also runs on *predicted* sketches when a
  sketch checkpoint is given.

Checkpoints (float16, ``models/prior/training_state.py``; ``checkpoint.pt`` in the run's folder
unless ``checkpoint`` names another file) are written every ``checkpoint_every_steps`` steps and
at epoch ends; a run resumes from one mid-epoch, bit-exact: the epoch's sample order is a
function of seed and epoch, a batch's random draws of seed and step, the learning rate of the
epoch, and the live run is rounded to the checkpoint's numbers when it writes one. Metrics go
to ``metrics.jsonl``. With ``torchrun`` (``WORLD_SIZE`` > 1) it trains with
DistributedDataParallel: NCCL on GPUs, gloo on CPU; each rank takes every WORLD_SIZE-th sample.
"""

from __future__ import annotations

import json
import logging
import os
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Literal

import torch
import torch.distributed as dist
import torch.nn.functional as F
from torch import Tensor, nn

from models.files import write_atomically, write_json_atomically
from models.metrics import voxel_iou
from models.prior.dataset import SketchVoxelDataset, split_by_shape
from models.prior.networks import (
    ShapeNet,
    SketchNet,
    get_preset,
    normalise_rgb,
    shape_input,
)
from models.prior.training_state import encode_state, load_state, round_to_stored, save_state

log = logging.getLogger(__name__)

Stage = Literal["sketch", "shape"]


@dataclass(frozen=True)
class TrainConfig:
    """One training run. Learning rates and momenta default to the paper's."""

    stage: Stage
    data_dirs: tuple[str, ...]
    """Dataset folders, trained on together (each split into train / validation on its own)."""
    out_dir: str
    preset: str = "cpu"
    epochs: int = 10
    batch_size: int = 16
    learning_rate: float | None = None
    """None: the paper's (sketch 5e-4 Adam, shape 2e-2 SGD)."""
    lr_decay_epochs: tuple[int, ...] = ()
    """Step decay: the learning rate is multiplied by ``lr_decay_factor`` from each of these
    epochs on (the paper's constant rate when empty). A function of the epoch, so a resumed run
    uses the same rate."""
    lr_decay_factor: float = 0.1
    max_minutes: float | None = None
    """Stop after this many minutes of training steps (data loading included, validation not),
    at the next checkpoint; a resumed run counts on from its checkpoint."""
    checkpoint_every_steps: int = 200
    checkpoint: str | None = None
    """The run's checkpoint file (None: ``checkpoint.pt`` in ``out_dir``); resumed from when it
    exists. The object-frame recipe keeps it in the committed ``training_state/``."""
    val_fraction: float = 0.05
    seed: int = 0
    init_weights: str | None = None
    """Start from these network weights (e.g. the general prior to fine-tune the box prior)."""
    sketch_weights: str | None = None
    """Shape stage: also validate on sketches predicted by these sketch-net weights."""
    predicted_sketch_prob: float = 0.0
    """Shape stage: the fraction of samples whose input is the sketches the ``sketch_weights``
    net predicts from the RGB, not the true ones: the shape net learns from what it will be
    given (0: the paper's, true sketches only)."""
    sensor_depth_prob: float = 0.5
    sensor_normals: bool = False
    """Shape stage: the samples with sensor depth also take its normals where they are known,
    as RGB-D inference does (False: the true normals, as the committed weights were trained)."""
    positive_weight: float = 1.0
    """Shape stage: BCE weight of occupied voxels (1 = the paper's plain BCE)."""
    augment: bool = True
    threads: int | None = None
    max_val_samples: int = 512


def paper_optimizer(stage: Stage, model: nn.Module, lr: float | None) -> torch.optim.Optimizer:
    """The paper's optimiser for a stage."""
    if stage == "sketch":
        return torch.optim.Adam(model.parameters(), lr=lr or 5e-4, betas=(0.5, 0.9))
    return torch.optim.SGD(model.parameters(), lr=lr or 2e-2, momentum=0.9)


def epoch_learning_rate(config: TrainConfig, epoch: int) -> float:
    """The learning rate of an epoch under the step decay."""
    base = config.learning_rate or (5e-4 if config.stage == "sketch" else 2e-2)
    return base * config.lr_decay_factor ** sum(epoch >= e for e in config.lr_decay_epochs)


def build_model(stage: Stage, preset: str) -> nn.Module:
    return SketchNet(get_preset(preset)) if stage == "sketch" else ShapeNet(get_preset(preset))


def colour_light_jitter() -> nn.Module:
    """Colour (brightness, contrast, saturation) and light (illuminant colour, gamma) jitter."""
    import kornia.augmentation as K

    return nn.Sequential(
        K.ColorJiggle(0.3, 0.3, 0.3, 0.0, p=0.8),
        K.RandomPlanckianJitter(mode="blackbody", p=0.5),
        K.RandomGamma((0.7, 1.4), p=0.5),
    )


def sketch_loss(prediction: dict[str, Tensor], batch: dict[str, Tensor]) -> dict[str, Tensor]:
    """The paper's L2 losses: depth (nearness), normals, silhouette probability; and their sum."""
    losses = {
        "depth": F.mse_loss(prediction["depth"], batch["nearness"]),
        "normals": F.mse_loss(prediction["normals"], batch["normals"]),
        "silhouette": F.mse_loss(
            torch.sigmoid(prediction["silhouette_logits"]), batch["silhouette"]
        ),
    }
    losses["total"] = losses["depth"] + losses["normals"] + losses["silhouette"]
    return losses


def ground_truth_shape_input(
    batch: dict[str, Tensor],
    sensor_depth_prob: float = 0.0,
    generator: torch.Generator | None = None,
    sensor_normals: bool = False,
) -> Tensor:
    """Shape-net input from ground-truth sketches; optionally sensor depth for some samples
    (and, with ``sensor_normals``, the sensor depth's normals where they are known)."""
    depth, normals = batch["nearness"], batch["normals"]
    if sensor_depth_prob > 0:
        sensor_depth, sensor_normal = _sensor_sketch(batch, depth, normals)
        if not sensor_normals:
            sensor_normal = normals
        # Drawn on the CPU generator (bit-exact resume on any device), used where the batch is.
        use = torch.rand(depth.shape[0], 1, 1, 1, generator=generator) < sensor_depth_prob
        use = use.to(depth.device)
        depth = torch.where(use, sensor_depth, depth)
        normals = torch.where(use, sensor_normal, normals)
    return shape_input(depth, normals, batch["silhouette"])


def sensor_shape_input(batch: dict[str, Tensor], prediction: dict[str, Tensor]) -> Tensor:
    """Shape-net input as RGB-D inference makes it (``ShapePrior.predict`` with depth): the
    sensor's depth and its normals where known, the predicted sketches elsewhere, inside the
    true silhouette (inference sees the object's outline in the depth)."""
    depth, normals = _sensor_sketch(batch, prediction["depth"], prediction["normals"])
    return shape_input(depth, normals, batch["silhouette"])


def _sensor_sketch(
    batch: dict[str, Tensor], depth: Tensor, normals: Tensor
) -> tuple[Tensor, Tensor]:
    """The sensor's nearness and normals, ``depth`` and ``normals`` where it has none."""
    sensor = batch["sensor_nearness"]
    measured = batch["sensor_normals"]
    known = measured.abs().sum(dim=1, keepdim=True) > 0
    return torch.where(sensor > 0, sensor, depth), torch.where(known, measured, normals)


def predicted_shape_input(
    prediction: dict[str, Tensor], sensor_nearness: Tensor | None = None
) -> Tensor:
    """Shape-net input from predicted sketches (silhouette > 0.5); RGB-D mode passes the sensor's
    nearness, which replaces the predicted depth wherever the sensor returned."""
    silhouette = (prediction["silhouette_logits"] > 0).float()
    depth = prediction["depth"]
    if sensor_nearness is not None:
        depth = torch.where(sensor_nearness > 0, sensor_nearness, depth)
    return shape_input(depth, prediction["normals"], silhouette)


def shape_loss(logits: Tensor, voxels: Tensor, positive_weight: float = 1.0) -> Tensor:
    """Binary cross-entropy over all voxels (``positive_weight`` > 1 up-weights occupied ones)."""
    weight = None if positive_weight == 1.0 else torch.tensor(positive_weight, device=logits.device)
    return F.binary_cross_entropy_with_logits(logits, voxels, pos_weight=weight)


def _mix_predicted_sketches(
    inputs: Tensor,
    batch: dict[str, Tensor],
    sketch_net: SketchNet,
    probability: float,
    generator: torch.Generator,
) -> Tensor:
    """``inputs`` with the sketch net's prediction (frozen) in place of the true sketches for a
    ``probability`` fraction of the samples."""
    use = torch.rand(inputs.shape[0], generator=generator) < probability
    if not bool(use.any()):
        return inputs
    chosen = use.nonzero().squeeze(1).to(inputs.device)
    # Only the chosen samples go through the sketch net (eval mode: each sample's prediction
    # does not depend on the others in the batch).
    with torch.no_grad():
        predicted = predicted_shape_input(sketch_net(normalise_rgb(batch["rgb"][chosen])))
    return inputs.index_copy(0, chosen, predicted)


def _collate(samples: list[dict[str, Tensor]]) -> dict[str, Tensor]:
    return {key: torch.stack([s[key] for s in samples]) for key in samples[0]}


def _batches(dataset: SketchVoxelDataset, indices: list[int], batch_size: int):
    for start in range(0, len(indices) - batch_size + 1, batch_size):
        yield _collate([dataset[i] for i in indices[start : start + batch_size]])


def save_weights(model: nn.Module, stage: Stage, preset: str, path: str | Path) -> None:
    """Network weights only, in float16 (half the size; inference runs in float32), written
    atomically."""
    module = model.module if hasattr(model, "module") else model
    state = {k: v.half() if v.is_floating_point() else v for k, v in module.state_dict().items()}
    blob = {"stage": stage, "preset": preset, "state_dict": state}
    write_atomically(Path(path), lambda temporary: torch.save(blob, temporary))


class WeightsError(ValueError):
    """A weights file is missing, corrupt or not the network's; the message names the file."""


def load_weights(model: nn.Module, path: str | Path) -> dict:
    """Load weights written by :func:`save_weights` (or a training checkpoint) into ``model``.

    Raises:
        WeightsError: the file is missing, unreadable, or holds another network's weights.
    """
    kind = type(model.module if hasattr(model, "module") else model).__name__
    try:
        blob = torch.load(path, map_location="cpu", weights_only=False)
        state = blob["state_dict"] if "state_dict" in blob else blob["model"]
        model.load_state_dict(
            {k: v.float() if v.is_floating_point() else v for k, v in state.items()}
        )
    except FileNotFoundError:
        raise WeightsError(f"{path}: missing ({kind} weights)") from None
    except Exception as error:  # torch.load and load_state_dict raise many kinds
        reason = str(error).strip().splitlines()[0][:200] if str(error).strip() else repr(error)
        raise WeightsError(f"{path}: not valid {kind} weights ({reason})") from None
    return blob


class _Distributed:
    """Rank, world size and device from torchrun's environment (1 process without it)."""

    def __init__(self) -> None:
        self.world = int(os.environ.get("WORLD_SIZE", "1"))
        self.rank = int(os.environ.get("RANK", "0"))
        local = int(os.environ.get("LOCAL_RANK", "0"))
        cuda = torch.cuda.is_available()
        self.device = torch.device(f"cuda:{local}" if cuda else "cpu")
        if self.world > 1:
            if cuda:
                torch.cuda.set_device(self.device)
            dist.init_process_group("nccl" if cuda else "gloo")

    @property
    def main(self) -> bool:
        return self.rank == 0

    def mean(self, value: float) -> float:
        if self.world == 1:
            return value
        tensor = torch.tensor([value], device=self.device)
        dist.all_reduce(tensor)
        return float(tensor) / self.world

    def close(self) -> None:
        if self.world > 1:
            dist.destroy_process_group()


def _move_optimizer_state(optimizer: torch.optim.Optimizer, device: torch.device) -> None:
    for slot in optimizer.state.values():
        for key, value in slot.items():
            if isinstance(value, Tensor) and key != "step":
                slot[key] = value.to(device)


def _has_search_crops(data_dirs: tuple[str, ...]) -> bool:
    manifest = json.loads((Path(data_dirs[0]) / "manifest.json").read_text())
    return manifest["recipe"]["recipe"].get("frame", "fixed") == "object"


def train(config: TrainConfig, *, progress: bool = True) -> dict:
    """Run (or resume) a training run; returns the last validation metrics."""
    from tqdm import tqdm

    if config.threads:
        torch.set_num_threads(config.threads)
    env = _Distributed()
    out_dir = Path(config.out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    torch.manual_seed(config.seed)
    # The sketch net also learns the search crops, where the object-fitted frame looks for the
    # object (when the data has them); the shape net needs voxels, which only the fitted crops have.
    search = config.stage == "sketch" and _has_search_crops(config.data_dirs)
    dataset = SketchVoxelDataset(config.data_dirs, search_crops=search)
    train_idx, val_idx = split_by_shape(dataset, config.val_fraction, config.seed)
    val_idx = val_idx[: config.max_val_samples]

    model = build_model(config.stage, config.preset)
    checkpoint = Path(config.checkpoint) if config.checkpoint else out_dir / "checkpoint.pt"
    optimizer = paper_optimizer(config.stage, model, config.learning_rate)
    epoch, batch_in_epoch, step, trained_s = 0, 0, 0, 0.0
    if checkpoint.exists():  # before DDP wraps the model; the initial weights are not needed
        progress_state = load_state(checkpoint, model, optimizer)
        epoch, batch_in_epoch = progress_state["epoch"], progress_state["batch_in_epoch"]
        step, trained_s = progress_state["step"], progress_state["trained_s"]
        log.info("resumed from %s at epoch %d batch %d", checkpoint, epoch, batch_in_epoch)
    elif config.init_weights:
        load_weights(model, config.init_weights)
    model.to(env.device)
    _move_optimizer_state(optimizer, env.device)
    if env.world > 1:
        if env.device.type == "cuda":
            model = nn.SyncBatchNorm.convert_sync_batchnorm(model)
        model = nn.parallel.DistributedDataParallel(model)
    augment = colour_light_jitter().to(env.device) if config.augment else None
    sketch_net = None
    if config.predicted_sketch_prob > 0 and not (config.stage == "shape" and config.sketch_weights):
        raise ValueError("predicted_sketch_prob needs the shape stage and sketch_weights")
    if config.stage == "shape" and config.sketch_weights:
        sketch_net = SketchNet(get_preset(config.preset))
        load_weights(sketch_net, config.sketch_weights)
        sketch_net.to(env.device).eval()

    metrics_file = out_dir / "metrics.jsonl"
    if env.main:
        write_json_atomically(out_dir / "config.json", asdict(config))

    def save_checkpoint(finished: bool = False) -> None:
        """Round the live run to the float16 numbers the file holds, then write it (main rank)."""
        core = model.module if env.world > 1 else model
        round_to_stored(core, optimizer)
        if not env.main:
            return
        progress_state = {
            "epoch": epoch,
            "batch_in_epoch": batch_in_epoch,
            "step": step,
            "trained_s": trained_s,
            "config": asdict(config),
        }
        save_state(checkpoint, encode_state(core, None if finished else optimizer, progress_state))

    def write(record: dict) -> None:
        if env.main:
            with metrics_file.open("a") as handle:
                handle.write(json.dumps(record) + "\n")

    budget_s = None if config.max_minutes is None else 60.0 * config.max_minutes
    validation: dict = {}
    stopped = False
    while epoch < config.epochs and not stopped:
        order = torch.randperm(
            len(train_idx), generator=torch.Generator().manual_seed(config.seed * 1000 + epoch)
        ).tolist()
        indices = [train_idx[i] for i in order][env.rank :: env.world]
        for group in optimizer.param_groups:
            group["lr"] = epoch_learning_rate(config, epoch)
        batches_per_epoch = len(indices) // config.batch_size
        model.train()
        bar = tqdm(
            total=batches_per_epoch,
            initial=batch_in_epoch,
            disable=not (progress and env.main),
            desc=f"{config.stage} epoch {epoch}",
        )
        running = 0.0
        start_index = batch_in_epoch * config.batch_size
        tick = time.monotonic()
        for batch in _batches(dataset, indices[start_index:], config.batch_size):
            batch = {k: v.to(env.device) for k, v in batch.items()}
            # The batch's randomness (jitter, sensor-depth draws) is a function of its step and
            # the rank: a run resumed from a checkpoint trains bit-exact as one never stopped.
            step_seed = (config.seed * 1_000_003 + step) * max(env.world, 1) + env.rank
            torch.manual_seed(step_seed)
            sample_noise = torch.Generator().manual_seed(step_seed)
            if config.stage == "sketch":
                rgb = batch["rgb"].float() / 255.0
                if augment is not None:
                    with torch.no_grad():
                        rgb = augment(rgb).clamp(0, 1)
                losses = sketch_loss(model(normalise_rgb(rgb)), batch)
                loss = losses["total"]
            else:
                inputs = ground_truth_shape_input(
                    batch, config.sensor_depth_prob, sample_noise, config.sensor_normals
                )
                if config.predicted_sketch_prob > 0:
                    assert sketch_net is not None
                    inputs = _mix_predicted_sketches(
                        inputs, batch, sketch_net, config.predicted_sketch_prob, sample_noise
                    )
                loss = shape_loss(model(inputs), batch["voxels"], config.positive_weight)
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            optimizer.step()
            step += 1
            batch_in_epoch += 1
            value = loss.item()
            running = 0.9 * running + 0.1 * value if running else value
            now = time.monotonic()
            trained_s, tick = trained_s + now - tick, now
            bar.update()
            bar.set_postfix(loss=f"{running:.4f}")
            if step % 25 == 0:
                write(
                    {
                        "step": step,
                        "epoch": epoch,
                        "train_loss": env.mean(value),
                        "trained_s": round(trained_s, 1),
                    }
                )
            if step % config.checkpoint_every_steps == 0:
                # Only here (and at epoch ends) may a run stop: every run, stopped or not, is
                # rounded to float16 at the same steps.
                save_checkpoint()
                if budget_s is not None and trained_s >= budget_s:
                    stopped = True
                    break
        bar.close()
        if not stopped:
            epoch, batch_in_epoch = epoch + 1, 0
            save_checkpoint(finished=epoch >= config.epochs)
        validation = evaluate(model, config, dataset, val_idx, env.device, sketch_net)
        validation = {k: env.mean(v) for k, v in validation.items()}
        write(
            {
                "step": step,
                "epoch": epoch,
                "trained_s": round(trained_s, 1),
                "train_loss_ema": running,
                **validation,
            }
        )
        log.info("epoch %d step %d: %s", epoch, step, validation)
        stopped = stopped or (budget_s is not None and trained_s >= budget_s)
    if env.main:
        save_weights(model, config.stage, config.preset, out_dir / f"{config.stage}.pt")
    env.close()
    return validation


@torch.no_grad()
def evaluate(
    model: nn.Module,
    config: TrainConfig,
    dataset: SketchVoxelDataset,
    indices: list[int],
    device: torch.device,
    sketch_net: SketchNet | None = None,
) -> dict[str, float]:
    """Validation losses (and voxel IoU at 0.5 for the shape stage) on held-out shapes."""
    was_training = model.training
    model.eval()
    totals: dict[str, float] = {}
    count = 0
    for batch in _batches(dataset, indices, min(config.batch_size, len(indices))):
        batch = {k: v.to(device) for k, v in batch.items()}
        size = batch["rgb"].shape[0]
        if config.stage == "sketch":
            prediction = model(normalise_rgb(batch["rgb"]))
            values = {f"val_{k}": float(v) for k, v in sketch_loss(prediction, batch).items()}
            silhouette = (prediction["silhouette_logits"] > 0).float()
            values["val_silhouette_iou"] = float(voxel_iou(silhouette, batch["silhouette"]))
        else:
            logits = model(ground_truth_shape_input(batch))
            values = {
                "val_loss": float(shape_loss(logits, batch["voxels"], config.positive_weight)),
                "val_iou_gt_sketch": float(voxel_iou(torch.sigmoid(logits), batch["voxels"])),
            }
            if sketch_net is not None:
                prediction = sketch_net(normalise_rgb(batch["rgb"]))
                probs = torch.sigmoid(model(predicted_shape_input(prediction)))
                values["val_iou_pred_sketch"] = float(voxel_iou(probs, batch["voxels"]))
                probs = torch.sigmoid(model(sensor_shape_input(batch, prediction)))
                values["val_iou_rgbd"] = float(voxel_iou(probs, batch["voxels"]))
        for key, value in values.items():
            totals[key] = totals.get(key, 0.0) + value * size
        count += size
    model.train(was_training)
    return {key: value / max(count, 1) for key, value in totals.items()}
