#!/usr/bin/env bash
# Fresh machine to a trained SeaThru-NeRF in one command (8-14 minutes of training on a 2-core CPU,
# about 30 minutes with set-up, evaluation and four videos):
# set up, write the embedded demo scene, train seathru-nerf-lite, evaluate, render videos.
# Results: outputs/quickstart/ (see the summary printed at the end).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup.sh
BIN=.venv/bin
# nerfstudio and torch print hundreds of known deprecation warnings over the progress display;
# ignore exactly those (seathru_nerfstudio/quiet.py), keep every other warning
PYTHONWARNINGS="$("$BIN/python" -m seathru_nerfstudio.quiet)"
export PYTHONWARNINGS
OUT=outputs/quickstart
SCENE=$OUT/demo-water
mkdir -p "$OUT"
[ -f "$SCENE/transforms.json" ] || "$BIN/seathru-synth" --output-dir "$SCENE" --preset water --seed 0
"$BIN/ns-train" seathru-nerf-lite --data "$SCENE" --output-dir "$OUT" --experiment-name demo-water \
  --timestamp quickstart --vis tensorboard "$@"
RUN=$OUT/demo-water/seathru-nerf-lite/quickstart
"$BIN/ns-eval" --load-config "$RUN/config.yml" --output-path "$RUN/eval.json"
# The *_display outputs are tone mapped for the screen (rgb, clean, backscatter are linear radiance).
for pair in rgb_display:rgb clean_display:clean backscatter_display:backscatter depth:depth; do
  "$BIN/ns-render" interpolate --load-config "$RUN/config.yml" --rendered-output-names "${pair%%:*}" \
    --interpolation-steps 10 --frame-rate 10 --output-path "$RUN/renders/${pair##*:}.mp4"
done
"$BIN/python" - "$RUN/eval.json" <<'PY'
import json, sys
results = json.load(open(sys.argv[1]))["results"]
keys = ["psnr", "ssim", "clean_psnr", "clean_ssim", "depth_abs_rel", "depth_abs_rel_far"]
print("quickstart held-out metrics: " + ", ".join(f"{k}={results[k]:.3f}" for k in keys if k in results))
PY
echo "quickstart: model, checkpoints and TensorBoard logs in $RUN"
echo "quickstart: metrics in $RUN/eval.json, videos in $RUN/renders/"
echo "quickstart: browse it with: $BIN/seathru-viewer --load-config $RUN/config.yml   (then open http://127.0.0.1:7007)"
