#!/usr/bin/env bash
# Reproduces the committed cpu-preset weights in models/prior/weights/ (the exact commands, seeds and
# data recipe). Every step resumes: data builds skip finished shards, training resumes from its
# checkpoint. Run from the repository root:
#   nohup scripts/train_cpu_weights.sh > logs/train_cpu_weights.log 2>&1 &
# Time budgets (--max-minutes) were set for a 2-core CPU; on a faster machine raise --epochs.
# The committed weights: session 2 ran the sketch and shape nets for 40 and 35 minutes; session 3
# resumed both from their checkpoints up to 95 and 90 minutes (running side by side: the shape
# net uses the sketch net only to report validation IoU), then redid steps 4-6.
set -euo pipefail
TS=".venv/bin/touchshape"
DATA=logs/data
RUNS=logs/train
export OMP_NUM_THREADS=1  # one thread: the 2 cores are shared; 2 threads stall when oversubscribed

# 1. Data: 14 procedural categories x 150 shapes (shape seeds 0-149) x 6 views; box family x 400.
$TS data build --out $DATA/general --shapes-per-category 150 --views 6 --seed 0 --workers 2
$TS data build --out $DATA/box --categories box --shapes-per-category 400 --views 6 --seed 0 \
    --workers 2

# 2. 2.5D sketch net (Adam 5e-4, betas 0.5/0.9, L2), colour/light jitter.
$TS train sketch --preset cpu --data $DATA/general --out $RUNS/general_sketch \
    --epochs 40 --batch-size 16 --max-minutes 95 --threads 1 --seed 0

# 3. Shape net on ground-truth sketches (SGD 2e-2, momentum 0.9, BCE); validated on predicted.
$TS train shape --preset cpu --data $DATA/general --out $RUNS/general_shape \
    --epochs 40 --batch-size 16 --max-minutes 90 --threads 1 --seed 0 \
    --sketch-weights $RUNS/general_sketch/sketch.pt

# 4. Box prior: the general shape net fine-tuned on the box family (sketch net shared).
$TS train shape --preset cpu --data $DATA/box --out $RUNS/box_shape \
    --epochs 40 --batch-size 16 --max-minutes 10 --threads 1 --seed 0 \
    --init $RUNS/general_shape/shape.pt --sketch-weights $RUNS/general_sketch/sketch.pt

# 5. Platt-calibrate each shape net on predicted sketches (docs/prior.md: after this short
#    training the plain-BCE net keeps occupied voxels below 0.5); fit on 256 training views.
$TS train calibrate --data $DATA/general --sketch-weights $RUNS/general_sketch/sketch.pt \
    --shape-weights $RUNS/general_shape/shape.pt --out $RUNS/general_shape/shape_calibrated.pt \
    --threads 1
$TS train calibrate --data $DATA/box --sketch-weights $RUNS/general_sketch/sketch.pt \
    --shape-weights $RUNS/box_shape/shape.pt --out $RUNS/box_shape/shape_calibrated.pt \
    --threads 1

# 6. Install the float16 weights where the package loads them.
cp $RUNS/general_sketch/sketch.pt models/prior/weights/general_sketch_cpu.pt
cp $RUNS/general_shape/shape_calibrated.pt models/prior/weights/general_shape_cpu.pt
cp $RUNS/box_shape/shape_calibrated.pt models/prior/weights/box_shape_cpu.pt
echo "weights installed in models/prior/weights/"
