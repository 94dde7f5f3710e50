#!/usr/bin/env bash
# GPU check of the trainer: fp32 vs bf16 autocast + channels_last throughput at 640x480, batch 6,
# then the paper recipe for a fixed wall-clock slice, with the loss and diagnostics first vs last.
#   here:        reloc synth /tmp/s --frames 60 --size 640x480 && mkdir -p VID && cp /tmp/s/videos/*.mp4 /tmp/s/intrinsics.yaml VID/
#   GPU machine: bash benchmarks/gpu_smoke.sh VID [SECONDS]
# (the mp4s are ~0.5 MB each: cheap to carry to a machine where rendering would cost minutes)
set -uo pipefail
VID=${1:?folder with seq-01.mp4, seq-02.mp4 and intrinsics.yaml}
SECONDS_PAPER=${2:-150}
R="python -m relocdepth.cli"
W=${OUT:-/tmp}/gpu_smoke; mkdir -p "$W"
python -c "import torch; print('torch', torch.__version__, torch.cuda.get_device_name())"
$R ingest "$VID/seq-01.mp4" "$VID/seq-02.mp4" --K "$VID/intrinsics.yaml" -o "$W/shards" --force 2>&1 | tail -1
summ() { python - "$1" "$2" <<'PY'
import json, sys
rows = [json.loads(x) for x in open(sys.argv[1]) if '"kind": "step"' in x]
late = rows[len(rows) // 2:]
d0, d1 = rows[0]["diagnostics"], rows[-1]["diagnostics"]
print(sys.argv[2], "steps", rows[-1]["step"], "loss", round(rows[0]["loss"], 4), "->", round(rows[-1]["loss"], 4),
      "triplets/s (2nd half)", round(sum(r["triplets_per_s"] or 0 for r in late) / len(late), 1))
print("  diag first", {k: round(v, 4) for k, v in d0.items()})
print("  diag last ", {k: round(v, 4) for k, v in d1.items()})
PY
}
for mode in fp32 amp; do
  extra=(); [ "$mode" = amp ] && extra=(--amp --channels-last)
  $R train "$W/shards" -o "$W/run-$mode" --size 640x480 --batch-size 6 --pretrained none --workers 8 \
    --max-steps 40 --log-every 5 --checkpoint-every 1000 --no-progress "${extra[@]}" 2>&1 | tail -1
  summ "$W/run-$mode/logs/train.jsonl" "$mode"
done
timeout -s INT "$SECONDS_PAPER" $R train "$W/shards" -o "$W/run-paper" --size 640x480 --batch-size 6 \
  --pretrained none --workers 8 --amp --channels-last --log-every 20 --checkpoint-every 100000 --no-progress 2>&1 | tail -1
summ "$W/run-paper/logs/train.jsonl" "paper-amp-${SECONDS_PAPER}s"
