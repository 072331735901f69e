#!/usr/bin/env bash
# The capacity experiment on the object-frame shape net (docs/prior.md, "The ~0.64 plateau"):
# the `cpu_wide` preset (a voxel decoder twice as wide, 8.9 M parameters against 5.2 M) trained
# on the object-frame recipe's data plus the creature family. Its encoder starts from the
# committed object_frame shape net, its decoder from random weights (seed 0). One run, half its
# inputs predicted by the committed sketch net from the start (the recipe's steps 3 and 4 in one).
# The float16 checkpoint (weights + SGD momentum, 35 MB) lives in the committed
# training_state/object_frame_wide/, so each session resumes it: about 21 minutes an epoch on
# one thread of a 2-core machine, 8 epochs. Run from the repository root:
#   nohup scripts/train_wide_shape_prior.sh > logs/train_wide_shape_prior.log 2>&1 &
# Rehearsed with tiny sizes:
#   DATA=/tmp/wide/data RUN=/tmp/wide/run STATE=/tmp/wide/state SHAPES=1 EPOCHS=1 WORKERS=2 \
#       scripts/train_wide_shape_prior.sh
# Then compare with `touchshape eval prior` against the committed `object_frame` prior.
set -euo pipefail
PY=${PY:-.venv/bin/python}
TS="$PY -m controller.cli.prior"
DATA=${DATA:-logs/data/object_frame}
RUN=${RUN:-logs/train/object_frame_wide}
STATE=${STATE:-training_state/object_frame_wide}
MINUTES=${MINUTES:-600}
THREADS=${THREADS:-1}
W=models/prior/weights
mkdir -p "$RUN" "$STATE"

# 1. Data: the object-frame recipe's 20 groups and the creature family, 120 shapes x 6 views
#    each (rebuilt bit-exact from the seeds; finished shards are skipped).
$TS data build --out $DATA --frame object --shapes-per-category "${SHAPES:-120}" --views 6 --seed 0 \
    --workers "${WORKERS:-1}" --categories bag bottle bowl camera can cap keyboard earphone \
    helmet jar knife laptop mug remote box superquadric revolved box_any primitive_union blob \
    creature

# 2. The initial weights: the committed object-frame encoder, a fresh wide decoder.
$PY - "$W/object_frame_shape_cpu.pt" "$RUN/init.pt" <<'PYEOF'
import sys
import torch
from models.prior.networks import ShapeNet, get_preset
from models.prior.training import load_weights, save_weights
torch.manual_seed(0)
source, wide = ShapeNet(get_preset("cpu")), ShapeNet(get_preset("cpu_wide"))
load_weights(source, sys.argv[1])
wide.encoder.load_state_dict(source.encoder.state_dict())
save_weights(wide, "shape", "cpu_wide", sys.argv[2])
PYEOF

# 3. The shape net: SGD at the paper's rate, a tenth of it from epoch 4, a hundredth from 6.
$TS train shape --preset cpu_wide --data $DATA --out $RUN --checkpoint $STATE/shape.pt \
    --init "$RUN/init.pt" --sketch-weights $W/object_frame_sketch_cpu.pt \
    --predicted-sketch-prob 0.5 --epochs "${EPOCHS:-8}" --lr-decay-epochs 4 6 --batch-size 16 \
    --max-minutes "$MINUTES" --threads "$THREADS" --seed 0
echo "trained: $RUN/shape.pt"
