#!/usr/bin/env bash
# Set up .venv if needed, then run the whole pipeline on sample_data/ and print what it made:
# preprocess (poses, background field, mattes, crops) -> train (short budgets) -> bundle
# (manifest, model, proxy mesh, previews) -> render and verify, for the static and the dynamic sample.
# Usage: ./scripts/demo.sh [OUTPUT_DIR]   (default: out/demo)
# Budgets (minutes) can be changed: DBB_BG_MINUTES, DBB_TRAIN_MINUTES. The defaults keep the whole
# demo, install included, within 15 minutes on 2 CPU cores: enough to see every stage work, not
# for quality (train for 10-15 minutes and at --res-max 256+ for that; see docs/results.md).
set -euo pipefail
cd "$(dirname "$0")/.."
./scripts/setup.sh
export PATH="$PWD/.venv/bin:$PATH"
OUT=${1:-out/demo}
BG=${DBB_BG_MINUTES:-0.75}
TRAIN=${DBB_TRAIN_MINUTES:-2}
mkdir -p "$OUT"
start=$SECONDS
made=()
step() { echo; echo "== [$(( (SECONDS - start) / 60 )) min] $*"; }

step "1. preprocess sample_data/static: poses, background field (clean plate), mattes, crops as fine as the footage"
dbb-capture preprocess sample_data/static -o "$OUT/static_dataset" --background-minutes "$BG" --overwrite
made+=("$OUT/static_dataset        dataset: crops.json, transforms.json (+ masks), contact_sheet.png, dataset.json")

step "2. preprocess sample_data/dynamic: same, 64 px crops (a dynamic object) and 11-frame sequences"
dbb-capture preprocess sample_data/dynamic -o "$OUT/dynamic_dataset" --background-minutes "$BG" --overwrite
made+=("$OUT/dynamic_dataset       dataset: crops.json with sequences, contact_sheet.png, dataset.json")

step "3. train the static object: radiance field baked into a PlenOctree ($TRAIN min)"
dbb-train plenoctree "$OUT/static_dataset" -o "$OUT/static_run" --minutes "$TRAIN" --res-max 64 --sh-degree 1 --overwrite
made+=("$OUT/static_run            PlenOctree run: tree.npz, report/ (held-out renders and PSNR)")

step "4. train the dynamic object: viewpoint-conditioned RSSM ($TRAIN min)"
dbb-train rssm "$OUT/dynamic_dataset" -o "$OUT/dynamic_run" --minutes "$TRAIN" --overwrite
made+=("$OUT/dynamic_run           RSSM run: model.pt, stepper.ts, report/ (evaluation, predicted strips)")

for kind in static dynamic; do
  step "5. bundle the $kind billboard, render it from the dataset's cameras, verify it"
  dbb-export bundle "$OUT/${kind}_run" -o "$OUT/${kind}_bundle" --overwrite
  dbb-export render "$OUT/${kind}_bundle" --cameras "$OUT/${kind}_dataset/crops.json" -o "$OUT/${kind}_renders" --overwrite
  dbb-export verify "$OUT/${kind}_bundle"
  made+=("$OUT/${kind}_bundle  bundle: manifest.json, model, proxy.glb, previews (turntable, sheet)")
  made+=("$OUT/${kind}_renders RGBA renders from the bundle, one per crop camera")
done

echo
echo "Demo finished in $(( (SECONDS - start) / 60 )) min $(( (SECONDS - start) % 60 )) s. It made:"
for m in "${made[@]}"; do echo "  $m"; done
echo
echo "See them live (viewer and stream; Ctrl-C stops):"
echo "  .venv/bin/dbb-serve $OUT/static_bundle $OUT/dynamic_bundle"
