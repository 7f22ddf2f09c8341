#!/usr/bin/env bash
# Train GS-Net through Q-Render on synthetic rooms, then evaluate on a held-out room.
# Multi-scene training scales out with torchrun (one OpenCL context per rank, gloo on CPU):
#   NPROC=2 examples/train_and_eval.sh
set -euo pipefail
OUT=${OUT:-qr-cl-example}
NPROC=${NPROC:-1}
mkdir -p "$OUT"
SCENES=$(python - "$OUT" <<'PY'
import sys
from qr_cl.synthetic import SyntheticConfig, synthetic_scene
print(" ".join(str(synthetic_scene(SyntheticConfig(seed=s))) for s in (0, 1, 2, 3, 1000)))
PY
)
set -- $SCENES
TRAIN="$1 $2 $3 $4"
HELD="$5"
if [ "$NPROC" -gt 1 ]; then
  torchrun --standalone --nnodes 1 --nproc_per_node "$NPROC" -m qr_cl.train $TRAIN \
    --out "$OUT/gsnet" --steps 200 --batch-scenes "$NPROC"
else
  qr-cl train $TRAIN --out "$OUT/gsnet" --steps 200
fi
qr-cl eval "$HELD" "$1" --checkpoint "$OUT/gsnet/checkpoint.pt" --out "$OUT/eval" --views 0 1
