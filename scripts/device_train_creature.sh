#!/usr/bin/env bash
# The creature fine-tune of the object-frame shape net: the committed object_frame shape weights
# (models/prior/weights/RECIPE.md) came from this script, run in one call of a lent GPU machine
# (15 minutes of device time in all, so one prepared run). The data is built with every core,
# the fine-tune runs on the GPU (or the CPU: it runs anywhere), the calibration follows; what
# the run made is copied to $OUT_DIR even when a step fails. The committed weights started from
# the object-frame shape weights before it (commit e580695) and were made by
#   git show e580695:models/prior/weights/object_frame_shape_cpu.pt > logs/object_frame_shape_e580695.pt
#   INIT=logs/object_frame_shape_e580695.pt SHAPES=45 EPOCHS=8 MINUTES=3 \
#       scripts/device_train_creature.sh                              (16 cores + one H200)
#   cp $OUT_DIR/shape_calibrated.pt models/prior/weights/object_frame_shape_cpu.pt
# Rehearsed on the CPU with tiny sizes:
#   INIT=models/prior/weights/object_frame_shape_cpu.pt PY=.venv/bin/python WORKERS=2 CREATURES=2 SHAPES=1 EPOCHS=1 OUT_DIR=/tmp/rehearsal \
#       scripts/device_train_creature.sh
# Data: the creature family (shape seeds 0..CREATURES-1) and, to keep what the net knew, the
# object-frame recipe's 20 groups with shape seeds 0..SHAPES-1 (SHAPES is sized on the machine
# from how fast it built the creatures, so the build fits DATA_S seconds). Every replay shape
# is one the initial net was trained on or validated on: its validation IoU on that folder
# is not a held-out figure (`touchshape eval prior` gives those).
set -euo pipefail
PY=${PY:-python3}
INIT=${INIT:?the shape weights to start from (see above)}
TS="$PY -m controller.cli.prior"
OUT_DIR=${OUT_DIR:-logs/device_creature}
WORKERS=${WORKERS:-16}
CREATURES=${CREATURES:-200}
SHAPES=${SHAPES:-}
DATA_S=${DATA_S:-170}
EPOCHS=${EPOCHS:-4}
MINUTES=${MINUTES:-3.5}
W=models/prior/weights
RUN=logs/train/object_frame/creature_gpu
mkdir -p "$OUT_DIR"

collect() {
  for f in "$RUN/shape.pt" "$RUN/shape_calibrated.pt" "$RUN/metrics.jsonl" "$RUN/config.json"; do
    [ -e "$f" ] && cp "$f" "$OUT_DIR/" || true
  done
}
trap collect EXIT

$PY - <<'EOF'
import os, torch
print("torch", torch.__version__, "cuda", torch.cuda.is_available(),
      torch.cuda.get_device_name(0) if torch.cuda.is_available() else "-", "cpus", os.cpu_count())
EOF

start=$(date +%s)
$TS data build --out logs/data/creature --frame object --shapes-per-category "$CREATURES" \
    --views 6 --seed 0 --workers "$WORKERS" --categories creature
creature_s=$(( $(date +%s) - start ))
if [ -z "$SHAPES" ]; then
  # Seconds per shape (6 views) on this machine, from the creature build; 20 groups per seed.
  SHAPES=$($PY -c "print(max(10, min(120, int($DATA_S * $CREATURES / max($creature_s, 1) / 20))))")
fi
echo "creature build: ${creature_s} s for $CREATURES shapes; object-frame replay: $SHAPES shapes per group"
$TS data build --out "logs/data/object_frame_$SHAPES" --frame object \
    --shapes-per-category "$SHAPES" --views 6 --seed 0 --workers "$WORKERS" \
    --categories bag bottle bowl camera can cap keyboard earphone helmet jar knife laptop mug \
    remote box superquadric revolved box_any primitive_union blob
echo "data built in $(( $(date +%s) - start )) s"

$TS train shape --preset cpu --data "logs/data/object_frame_$SHAPES" logs/data/creature \
    --out "$RUN" --checkpoint "$RUN/checkpoint.pt" \
    --init "$INIT" --sketch-weights $W/object_frame_sketch_cpu.pt \
    --predicted-sketch-prob 0.5 --lr 2e-3 --lr-decay-epochs $(( EPOCHS - 1 )) \
    --epochs "$EPOCHS" --batch-size 16 --max-minutes "$MINUTES" --seed 0
echo "trained at $(( $(date +%s) - start )) s"

$TS train calibrate --data "logs/data/object_frame_$SHAPES" logs/data/creature \
    --sketch-weights $W/object_frame_sketch_cpu.pt --shape-weights "$RUN/shape.pt" \
    --out "$RUN/shape_calibrated.pt" --samples 256 --seed 0 | tee "$OUT_DIR/calibration.json"
echo "done at $(( $(date +%s) - start )) s"
