#!/usr/bin/env bash
# The object-frame shape net fine-tuned with the vessel family (models/families.py: mugs, jugs,
# teapots, kettles: a revolved body with a handle, maybe a spout and a lid).
#
# Why: the committed object-frame shape net never saw a handle or a spout off a revolved body,
# the parts single-view completion of household vessels has to guess (the main job's mug; the
# sourced mug and teapot). Unlike the creature family, this one was not drawn to resemble the
# sourced test meshes' majority (animals and figures): it is judged on all of them, and on the
# held-out procedural sets, against the committed weights.
#
# Resumable across sessions: the run's float16 state is kept in the committed
# training_state/object_frame_vessel/ (training_state/README.md); run the script again from the
# repository root to go on (the data is rebuilt bit-exact from its seeds, and what is built is
# skipped):
#   nohup scripts/train_vessel_shape_prior.sh > logs/train_vessel_shape.log 2>&1 &
# 1. Data (seed 0, 6 views, object frame): the vessel family, 240 shapes; the creature family,
#    CREATURES shapes (seeds 0-199 are those of the committed creature fine-tune); replay of the
#    committed net's 21 groups (the recipe's 20 and creature), SHAPES shapes each (seeds 0-29,
#    all seen by the committed net, so its validation figure is not held out; the creatures
#    0-29 are in both folders).
# 2. From object_frame_shape_cpu.pt as calibrated (the BCE undoes the folded offset): SGD 2e-3,
#    2e-4 in the last epoch, batch 16, EPOCHS epochs, half the inputs predicted by the committed
#    object-frame sketch net, seed 0, one thread.
# 3. Calibration on the same folders, 256 views, seed 0.
# Run 1 (2026-12-07, CREATURES=0, EPOCHS=5, RUN=logs/train/object_frame_vessel)
# learnt the vessels and forgot animals: not adopted (docs/prior.md, "Results: the vessel
# fine-tune"). Run 2 (2026-12-07, these defaults) kept the creature fine-tune's 200 creatures
# and still lost the bunny: not adopted either (docs/prior.md, "... run 2").
set -euo pipefail
PY=${PY:-.venv/bin/python}
TS="$PY -m controller.cli.prior"
VESSELS=${VESSELS:-240}
CREATURES=${CREATURES:-200}
SHAPES=${SHAPES:-30}
EPOCHS=${EPOCHS:-4}
MINUTES=${MINUTES:-600}
THREADS=${THREADS:-1}
WORKERS=${WORKERS:-1}
W=models/prior/weights
RUN=${RUN:-logs/train/object_frame_vessel_2}
STATE=${STATE:-training_state/object_frame_vessel}
mkdir -p "$RUN" "$STATE"

$TS data build --out logs/data/vessel --frame object --shapes-per-category "$VESSELS" \
    --views 6 --seed 0 --workers "$WORKERS" --categories vessel
$TS data build --out logs/data/creature --frame object --shapes-per-category "$CREATURES" \
    --views 6 --seed 0 --workers "$WORKERS" --categories creature
$TS data build --out "logs/data/object_frame_$SHAPES" --frame object \
    --shapes-per-category "$SHAPES" --views 6 --seed 0 --workers "$WORKERS" \
    --categories bag bottle bowl camera can cap keyboard earphone helmet jar knife laptop mug \
    remote box superquadric revolved box_any primitive_union blob creature
DATA=("logs/data/object_frame_$SHAPES" logs/data/creature logs/data/vessel)

$TS train shape --preset cpu --data "${DATA[@]}" \
    --out "$RUN" --checkpoint "$STATE/shape.pt" \
    --init $W/object_frame_shape_cpu.pt --sketch-weights $W/object_frame_sketch_cpu.pt \
    --predicted-sketch-prob 0.5 --lr 2e-3 --lr-decay-epochs $(( EPOCHS - 1 )) \
    --epochs "$EPOCHS" --batch-size 16 --checkpoint-every 200 --max-minutes "$MINUTES" \
    --threads "$THREADS" --seed 0

$TS train calibrate --data "${DATA[@]}" \
    --sketch-weights $W/object_frame_sketch_cpu.pt --shape-weights "$RUN/shape.pt" \
    --out "$RUN/shape_calibrated.pt" --samples 256 --seed 0 --threads "$THREADS" \
    | tee "$RUN/calibration.json"
