#!/usr/bin/env bash
# Evaluates every committed prior, and the automatic choice among them, on the held-out sets of
# docs/prior.md, from INPUT (rgb, or rgbd: the estimate a session starts from, depth fused in):
# held-out procedural shapes (the 14 categories and the trained families), the held-out
# families, small objects (3-6 cm) and the real-object meshes of scripts/source_test_meshes.py
# (if logs/meshes/ holds them). One JSON per prior and set under $OUT, then the table of
# scripts/summarise_prior_eval.py. Run from the repository root:
#   nohup scripts/eval_priors.sh > logs/eval_priors.log 2>&1 &
#   INPUT=rgbd nohup scripts/eval_priors.sh > logs/eval_priors_rgbd.log 2>&1 &
# INPUT, PRIORS, VIEWS, SHAPES, WEIGHTS_DIR, PRESET and OUT may be set in the environment.
set -euo pipefail
TS=".venv/bin/touchshape"
INPUT=${INPUT:-rgb}
OUT=${OUT:-logs/eval/priors/$INPUT}
VIEWS=${VIEWS:-2}
SHAPES=${SHAPES:-3}
PRIORS=${PRIORS:-"general box object_frame auto"}
WEIGHTS=()
if [[ -n "${WEIGHTS_DIR:-}" ]]; then WEIGHTS=(--weights-dir "$WEIGHTS_DIR"); fi
if [[ -n "${PRESET:-}" ]]; then WEIGHTS+=(--preset "$PRESET"); fi
export OMP_NUM_THREADS=1
mkdir -p "$OUT"

for prior in $PRIORS; do
    common=(--prior "$prior" --input "$INPUT" --views "$VIEWS" --seed 0 "${WEIGHTS[@]}")
    $TS eval prior "${common[@]}" --shapes-per-category "$SHAPES" \
        --categories bag bottle bowl camera can cap keyboard earphone helmet jar knife laptop \
        mug remote box superquadric revolved box_any primitive_union blob \
        --json "$OUT/$prior.procedural.json" > /dev/null
    $TS eval prior "${common[@]}" --shapes-per-category "$((SHAPES * 4))" \
        --categories extruded fruit --json "$OUT/$prior.families.json" > /dev/null
    $TS eval prior "${common[@]}" --shapes-per-category "$SHAPES" --size-range 0.03 0.06 \
        --categories bottle can jar mug remote box superquadric revolved box_any blob extruded \
        fruit --json "$OUT/$prior.small.json" > /dev/null
    if compgen -G "logs/meshes/*.obj" > /dev/null; then
        $TS eval prior "${common[@]}" --objects logs/meshes/*.obj --up-axis z \
            --json "$OUT/$prior.real.json" > /dev/null
    fi
    echo "evaluated $prior"
done
.venv/bin/python scripts/summarise_prior_eval.py "$OUT" | tee "$OUT/summary.md"
