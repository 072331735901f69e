#!/usr/bin/env bash
# The object-frame shape net fine-tuned with the `creature` family added (animals and figurines:
# a body on two or four legs, a head, maybe a tail), the data the priors lacked for the
# sourced real meshes, most of which are figurines. Starts from the committed object-frame shape
# weights (calibrated: the fine-tune's BCE undoes the folded offset, and calibration follows)
# and keeps every earlier dataset's validation split as it was (each folder splits on its own).
# The run's float16 checkpoint lives in the committed training_state/ (<= 40 MB), so it resumes
# in a later session. About 80 minutes on 2 cores. Run from the repository root:
#   nohup scripts/train_object_frame_creature.sh > logs/train_object_frame_creature.log 2>&1 &
set -euo pipefail
TS=".venv/bin/touchshape"
RUNS=logs/train/object_frame
W=models/prior/weights
THREADS=${THREADS:-2}

# 1. Data: the object-frame recipe's 20 groups (scripts/train_object_frame_priors.sh) and the
#    creature family, 120 shapes x 6 views each, object-fitted frame.
$TS data build --out logs/data/object_frame --frame object --shapes-per-category 120 --views 6 \
    --seed 0 --workers 2 --categories bag bottle bowl camera can cap keyboard earphone helmet jar \
    knife laptop mug remote box superquadric revolved box_any primitive_union blob
$TS data build --out logs/data/creature --frame object --shapes-per-category 120 --views 6 \
    --seed 0 --workers 2 --categories creature

# 2. The shape net on both, half its inputs predicted by the committed sketch net (as step 4 of
#    the recipe): one epoch at 2e-3, one at 2e-4.
$TS train shape --preset cpu --data logs/data/object_frame logs/data/creature \
    --out $RUNS/creature --checkpoint training_state/object_frame_creature.pt \
    --init $W/object_frame_shape_cpu.pt --sketch-weights $W/object_frame_sketch_cpu.pt \
    --predicted-sketch-prob 0.5 --lr 2e-3 --lr-decay-epochs 1 --epochs 2 --batch-size 16 \
    --threads "$THREADS" --seed 0

# 3. Calibration on both datasets' training views.
$TS train calibrate --data logs/data/object_frame logs/data/creature \
    --sketch-weights $W/object_frame_sketch_cpu.pt --shape-weights $RUNS/creature/shape.pt \
    --out $RUNS/creature/shape_calibrated.pt --samples 256 --seed 0 --threads "$THREADS"
echo "trained: $RUNS/creature/shape_calibrated.pt"
