#!/usr/bin/env bash
# GPU smoke run of the trainer (used on a lent GPU machine): a 640x480 synth scene, a few steps
# fp32 / bf16 autocast + channels_last, triplets/s from the JSONL log. Usage: bash benchmarks/gpu_smoke.sh OUT
set -euo pipefail
OUT=${1:-/tmp/gpu_smoke}
mkdir -p "$OUT"
python3 -m relocdepth.cli synth "$OUT/scene" --frames 60 --size 640x480 > /dev/null
python3 -m relocdepth.cli ingest "$OUT/scene" -o "$OUT/shards" --force > /dev/null
for mode in fp32 amp; do
  extra=(); [ "$mode" = amp ] && extra=(--amp --channels-last)
  python3 -m relocdepth.cli train "$OUT/shards" -o "$OUT/run-$mode" --size 640x480 --batch-size 6 \
    --pretrained none --workers 6 --max-steps 40 --log-every 5 --checkpoint-every 1000 --no-progress "${extra[@]}" 2>&1 | tail -2
  python3 - "$OUT/run-$mode/logs/train.jsonl" "$mode" <<'PY'
import json, sys
rows = [json.loads(x) for x in open(sys.argv[1]) if '"kind": "step"' in x]
late = rows[len(rows) // 2:]
print(sys.argv[2], "steps", rows[-1]["step"], "loss", round(rows[0]["loss"], 4), "->", round(rows[-1]["loss"], 4),
      "triplets/s (2nd half)", round(sum(r["triplets_per_s"] for r in late) / len(late), 1))
PY
done
