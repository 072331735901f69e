#!/usr/bin/env bash
# The RGB-D fine-tune of the object-frame shape net (docs/prior.md, "Depth's normals"): RGB-D
# inference gives the shape net the sensor's depth, its outline and the normals of its depth
# where they are known (ShapePrior.predict); the committed net was trained with the sensor's
# depth but the true normals. This run trains it on what it is given: the samples with
# simulated Kinect depth (half) also take that depth's normals (--sensor-normals), half of the
# RGB samples the committed sketch net's prediction, as before. From the committed
# object_frame shape net, SGD at 2e-3 for an epoch, then 2e-4 (the recipe's decayed rates).
# The float16 checkpoint (weights + SGD momentum, ~21 MB) lives in the committed
# training_state/object_frame_sensor/, so a later session resumes it. Run from the root:
#   nohup scripts/train_sensor_shape_prior.sh > logs/train_sensor_shape_prior.log 2>&1 &
# Rehearsed with tiny sizes:
#   DATA=/tmp/sensor/data RUN=/tmp/sensor/run STATE=/tmp/sensor/state SHAPES=1 EPOCHS=1 \
#       scripts/train_sensor_shape_prior.sh
# Then calibrate and compare with `touchshape eval prior` against the committed prior.
set -euo pipefail
PY=${PY:-.venv/bin/python}
TS="$PY -m controller.cli.prior"
DATA=${DATA:-logs/data/object_frame}
RUN=${RUN:-logs/train/object_frame_sensor}
STATE=${STATE:-training_state/object_frame_sensor}
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

# 2. The shape net from the committed one, its RGB-D samples with the sensor's normals.
$TS train shape --preset cpu --data $DATA --out $RUN --checkpoint $STATE/shape.pt \
    --init $W/object_frame_shape_cpu.pt --sketch-weights $W/object_frame_sketch_cpu.pt \
    --predicted-sketch-prob 0.5 --sensor-depth-prob 0.5 --sensor-normals --lr 2e-3 \
    --epochs "${EPOCHS:-3}" --lr-decay-epochs 1 --batch-size 16 --max-minutes "$MINUTES" \
    --threads "$THREADS" --seed 0
echo "trained: $RUN/shape.pt"
