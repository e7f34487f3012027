#!/usr/bin/env bash
# Re-create models/cavenav-pilot-small from nothing: the geometric pilot teaches, a fresh
# small VLM learns from its flights, flies one DAgger round with the teacher in its shadow,
# and a second fresh model learns from both (the teacher's states and the student's).
#
#   pip install -e '.[transformers,train]'
#   examples/train_small_pilot.sh WORK_DIR [OUT]       # OUT: WORK_DIR/pilot-small
#
# Every step writes its own folder under WORK_DIR and is skipped when that folder is
# complete, so an interrupted run picks up where it stopped (a sweep resumes, a fine-tune
# resumes from its last checkpoint). On 2 CPU cores: about 20 minutes of teacher flights,
# 10 of export, 15 + 50 of training and 10 of the DAgger round.
set -euo pipefail

work=${1:?usage: examples/train_small_pilot.sh WORK_DIR [OUT]}
out=${2:-$work/pilot-small}
prompt=$(dirname "$0")/../src/cavenav/pilots/prompts/small.md
# The requests the small model is shown: its own short prompt, 96x72 images, two earlier
# observations, and a reply that is the action with a short justification.
request=(--prompt-file "$prompt" --image-size 96x72 --history 2 --reply brief)
mkdir -p "$work"

# 1. The teacher flies the training caves (seeds below 1000) of S1-S5.
cavenav eval --scenarios S1,S2,S3,S4,S5 --seeds 0-19 --pilot geometric \
  --frames none --no-report --out "$work/teacher"

# 2. Its decisions become a dataset; a first student learns them.
[ -f "$work/data0/README.md" ] ||
  cavenav dataset "$work/teacher" --out "$work/data0" "${request[@]}"
[ -f "$work/student0/README.md" ] ||
  cavenav finetune "$work/data0" --out "$work/student0" --new small \
    --prompt-file "$prompt" --epochs 2

# 3. DAgger: the student flies caves of its own, the teacher decides alongside.
cavenav eval --scenarios S1,S2,S3,S4,S5 --seeds 20-29 --pilot vlm --backend transformers \
  --model "$work/student0" --temperature 0 --teacher geometric \
  --frames none --no-report --out "$work/round1"

# 4. Both sets of states, labelled by the teacher, train the model that ships.
[ -f "$work/data1/README.md" ] ||
  cavenav dataset "$work/teacher" "$work/round1" --labels teacher \
    --out "$work/data1" "${request[@]}"
[ -f "$out/README.md" ] ||
  cavenav finetune "$work/data1" --out "$out" --new small --prompt-file "$prompt" --epochs 4

echo "model: $out"
echo "fly it: cavenav run S1 --pilot vlm --backend transformers --model $out"
