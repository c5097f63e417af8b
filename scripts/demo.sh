#!/usr/bin/env bash
# Set up .venv if needed, then run the end-to-end demo on sample_data/ and print what it made.
# Usage: ./scripts/demo.sh [OUTPUT_DIR]   (default: out/demo)
set -euo pipefail
cd "$(dirname "$0")/.."
./scripts/setup.sh
export PATH="$PWD/.venv/bin:$PATH"
OUT=${1:-out/demo}
mkdir -p "$OUT"
made=()
has() { "$1" "$2" --help >/dev/null 2>&1; }

echo "== 1. a fresh synthetic capture with ground truth (dbb-capture synth)"
dbb-capture synth "$OUT/synth_static" --kind static --seconds 3 --fps 10 --resolution 320x240 --overwrite
made+=("$OUT/synth_static  synthetic capture: video.mp4, background.mp4, board.json, object.json, ground_truth/")

for kind in static dynamic; do
  cap=sample_data/$kind
  if has dbb-capture preprocess; then
    echo "== 2. preprocess sample_data/$kind (poses, background removal, crops)"
    dbb-capture preprocess "$cap" -o "$OUT/${kind}_dataset" --overwrite
    made+=("$OUT/${kind}_dataset  preprocessed dataset")
  fi
done

if has dbb-train plenoctree && [ -f "$OUT/static_dataset/crops.json" ]; then
  echo "== 3. train the static object (dbb-train plenoctree, short budget)"
  dbb-train plenoctree "$OUT/static_dataset" -o "$OUT/static_run" --minutes 3 --overwrite
  made+=("$OUT/static_run  PlenOctree training run")
fi
if has dbb-train rssm && [ -f "$OUT/dynamic_dataset/crops.json" ]; then
  echo "== 3b. train the dynamic object (dbb-train rssm, short budget)"
  dbb-train rssm "$OUT/dynamic_dataset" -o "$OUT/dynamic_run" --minutes 3 --overwrite
  made+=("$OUT/dynamic_run  RSSM training run")
fi
if has dbb-export bundle; then
  for kind in static dynamic; do
    if [ -d "$OUT/${kind}_run" ]; then
      echo "== 4. bundle the $kind billboard (dbb-export bundle)"
      dbb-export bundle "$OUT/${kind}_run" -o "$OUT/${kind}_bundle" --overwrite
      made+=("$OUT/${kind}_bundle  billboard bundle (manifest, model, proxy mesh, previews)")
    fi
  done
fi

echo
echo "Demo finished. It made:"
for m in "${made[@]}"; do echo "  $m"; done
