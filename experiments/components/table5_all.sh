#!/usr/bin/env bash
# Table 5 read as the representation error: two and three levels trained on every shape of DATA, side by side on
# one machine (made for one GPU), each a `python -m experiments.components.sweep --split all` run with its learning
# curve of eq. (8) every 250 epochs, then `python -m experiments.components.curves` over the two.
#
#   bash experiments/components/table5_all.sh DATA OUT [EPOCHS=10000] [LIMIT_S=0] [HARDWARE]
#
# OUT gets two.jsonl / three.jsonl (the sweep result lines), two.log / three.log (the curve points as they come,
# which survive a LIMIT_S cut-off) and results.{json,md} + curves.png. LIMIT_S > 0 stops each run after that many
# seconds; a run cut off leaves its curve in its log only. It calls `python3`, which must import jaxdeform and its
# dependencies (on a bare GPU image: libigl for the geodesics and cholespy for the final reconstruction; without
# cholespy each run still trains and logs its curve, then stops before its result line).
set -u
data=${1:?usage: table5_all.sh DATA OUT [EPOCHS] [LIMIT_S] [HARDWARE]}
out=${2:?usage: table5_all.sh DATA OUT [EPOCHS] [LIMIT_S] [HARDWARE]}
epochs=${3:-10000}
limit=${4:-0}
hardware=${5:-}
mkdir -p "$out"
# two processes share the GPU: neither may take most of its memory up front
export XLA_PYTHON_CLIENT_MEM_FRACTION=${XLA_PYTHON_CLIENT_MEM_FRACTION:-0.45} PYTHONUNBUFFERED=1
sweep() {
    local label=$1; shift
    local cut=()
    if [ "$limit" -gt 0 ]; then cut=(timeout "$limit"); fi
    "${cut[@]}" python3 -m experiments.components.sweep --data "$data" "$@" --split all --epochs "$epochs" \
        --eval-every 250 --curve features --jsonl "$out/$label.jsonl" >"$out/$label.log" 2>&1
    echo "$label: exit $?"
}
sweep three --kz 10,5,2 --d 0.4,0.2,0.1 &
sweep two --kz 10,5 --d 0.4,0.2 &
wait
if [ -s "$out/two.jsonl" ] && [ -s "$out/three.jsonl" ]; then
    python3 -m experiments.components.curves "two=$out/two.jsonl" "three=$out/three.jsonl" --out "$out" \
        ${hardware:+--hardware "$hardware"}
fi
