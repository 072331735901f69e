#!/usr/bin/env bash
# Trains the object-fitted-frame priors (cpu preset): data of the 14 categories, the box family
# and the generated families (minus the held-out ones), then the sketch and shape nets side by
# side. Every step resumes: data builds skip finished shards, training resumes from its
# checkpoint, and --max-minutes counts the time of earlier runs. Run from the repository root:
#   nohup scripts/train_object_frame_priors.sh > logs/train_object_frame_priors.log 2>&1 &
set -euo pipefail
TS=".venv/bin/touchshape"
DATA=logs/data/object_frame
RUNS=logs/train/object_frame
MINUTES=${MINUTES:-240}
export OMP_NUM_THREADS=1  # one thread per process: the 2 cores are shared

# 1. Data: 20 groups x 120 shapes (shape seeds 0-119) x 6 views, object-fitted frame.
#    Held out (never trained on): the 'extruded' and 'fruit' families.
$TS data build --out $DATA --frame object --shapes-per-category 120 --views 6 --seed 0 \
    --workers 2 --categories bag bottle bowl camera can cap keyboard earphone helmet jar knife \
    laptop mug remote box superquadric revolved box_any primitive_union blob

# 2. The sketch net (fitted and search crops) and the shape net (ground-truth sketches) side by
#    side, each starting from the committed general (fixed-frame) weights: the features carry
#    over and a 2-core CPU cannot afford training from scratch. The shape net is validated on
#    ground-truth sketches (the sketch net is not ready). The learning rate is the paper's, then
#    a tenth of it from the decay epochs on (from scratch, the shape net's validation IoU
#    stalled at 0.61-0.62 at the constant rate; its first decayed epoch gave 0.667). Started from
#    the general weights, the shape net reached 0.53 after one epoch.
W=models/prior/weights
$TS train sketch --preset cpu --data $DATA --out $RUNS/sketch --init $W/general_sketch_cpu.pt \
    --epochs 4 --lr-decay-epochs 3 --batch-size 16 --max-minutes "$MINUTES" --threads 1 --seed 0 &
SKETCH=$!
$TS train shape --preset cpu --data $DATA --out $RUNS/shape --init $W/general_shape_cpu.pt \
    --epochs 6 --lr-decay-epochs 3 5 --batch-size 16 --max-minutes "$MINUTES" --threads 1 \
    --seed 0 &
SHAPE=$!
wait $SKETCH $SHAPE

# 3. The shape net fine-tuned with half its inputs predicted by the finished sketch net: trained
#    on true sketches only it scored IoU 0.38 on predicted ones against 0.67 on true ones.
$TS train shape --preset cpu --data $DATA --out $RUNS/shape_on_predicted \
    --init $RUNS/shape/shape.pt --sketch-weights $RUNS/sketch/sketch.pt \
    --predicted-sketch-prob 0.5 --lr 2e-3 --lr-decay-epochs 3 --epochs 5 --batch-size 16 \
    --max-minutes "$MINUTES" --threads 2 --seed 0
echo "trained: $RUNS/sketch/sketch.pt $RUNS/shape_on_predicted/shape.pt"
