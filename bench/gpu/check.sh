#!/usr/bin/env bash
# The prepared device check of issues #4/#5: does the `paper`-preset diffuser (102.9 M parameters)
# follow its condition on Meta-World button-press, where the `cpu` preset does not? One command,
# well inside the device tool's 10-minute limit:
#
#   here, once:  bash bench/gpu/build_site.sh        (-> .gpu_site/site.tar.xz, git-ignored)
#   device:      run(command="bash bench/gpu/check.sh", carry=[".gpu_site"], timeout_s=600)
#   a companion instead (same budget): BENCH_EXTRA="--pairs copy" or
#                BENCH_EXTRA="--override concat_condition=true" bash bench/gpu/check.sh
#   here, CPU smoke test of this very script (tiny sizes, minutes):
#                PY=<python without our packages> SMOKE=1 bash bench/gpu/check.sh
#
# Steps: unpack the packages the device image lacks -> the README's main run (button-press-v3,
# 30 scripted labels, `cpu` preset, seed 0) up to its blocks (stop_after=blocks; the dataset is
# generated there, 16 workers) -> bench/diffuser_conditioning.py with a fresh `paper`-preset
# diffuser on that run's block pairs (bf16, DDPM-25 samples, an evaluation every EVERY steps, a
# wall-clock cap; conditions from every block, the top one too, scored by the stop-rule return as the
# flow's statistics: do the top blocks' conditions get samples above them?). Every evaluation rewrites
# the bench's JSON, so a kill keeps what was measured.
# Results come back under $OUT (env.txt, the bench JSON, the run's metrics_partial.json, logs);
# copy the bench JSON into bench/results/diffuser_conditioning/ here and summarise it with
# `python bench/diffuser_conditioning.py --summarize <json>`.
set -uo pipefail
cd "$(dirname "$0")/../.."
OUT=${OUT:-outputs/gpu_check}
PY=${PY:-python3}
ARCHIVE=${ARCHIVE:-.gpu_site/site.tar.xz}
mkdir -p "$OUT"
if [ -f "$ARCHIVE" ]; then
    rm -rf /tmp/ftb_site && mkdir -p /tmp/ftb_site && tar -C /tmp/ftb_site -xJf "$ARCHIVE" || exit 3
    export PYTHONPATH="/tmp/ftb_site${PYTHONPATH:+:$PYTHONPATH}"
fi
export PYTHONPATH="$PWD${PYTHONPATH:+:$PYTHONPATH}" PYTHONUNBUFFERED=1 MPLBACKEND=Agg

if [ -n "${SMOKE:-}" ]; then  # CPU: the same steps at toy sizes
    DEVICE=cpu; PRESET=tiny; BF16=(); STEPS=4; EVERY=2; WORKERS=2; BUDGET=${BUDGET:-900}
    RUN_EXTRA=(dataset.episodes_per_group=3 score_model.steps=20 dataset.cache_dir=/tmp/ftb_smoke_data)
    TAG=smoke; RUN=outputs/gpu_check_smoke
else
    DEVICE=cuda; PRESET=paper; BF16=(--autocast-bf16); STEPS=${STEPS:-20000}; EVERY=${EVERY:-2000}; WORKERS=16
    BUDGET=${BUDGET:-540}  # seconds for the whole script: the tool's 600 s limit, with room to copy results
    RUN_EXTRA=(dataset.cache_dir=/tmp/ftb_data)
    TAG=paper-gpu; RUN=outputs/gpu_check_run
fi

{
    date -u
    "$PY" - <<'PYEOF'
import platform, torch
print("python", platform.python_version(), "torch", torch.__version__, "cuda", torch.cuda.is_available(),
      torch.cuda.get_device_name(0) if torch.cuda.is_available() else "")
import diffusers, gymnasium, hydra, metaworld, mujoco, tensordict, torchrl
print({m.__name__: getattr(m, "__version__", "?") for m in (torchrl, tensordict, gymnasium, mujoco, hydra, diffusers)})
PYEOF
} 2>&1 | tee "$OUT/env.txt"
[ "${PIPESTATUS[0]}" -eq 0 ] || { echo "imports failed (see $OUT/env.txt)"; exit 4; }

echo "== run up to the blocks" | tee -a "$OUT/env.txt"
"$PY" recipes/ftb_offline.py run_dir="$RUN" device="$DEVICE" dataset.num_workers="$WORKERS" stop_after=blocks \
    progress=false resume=true "${RUN_EXTRA[@]}" 2>&1 | tail -n 40 > "$OUT/run.log"
cp "$RUN/metrics_partial.json" "$OUT/" 2>/dev/null || { echo "the run failed:"; tail -n 20 "$OUT/run.log"; exit 5; }

[ -n "${BENCH_EXTRA:-}" ] && TAG="$TAG-$(echo "$BENCH_EXTRA" | sed -E 's/--//g; s/[^A-Za-z0-9_.]+/-/g; s/^-|-$//g')"
# what is left of the budget: training stops (and evaluates once more) a minute and a half
# before the hard stop, which only catches an evaluation that overruns
BENCH_SECONDS=$((BUDGET - SECONDS)); MINUTES=$(awk "BEGIN {print ($BENCH_SECONDS - 90) / 60}")
echo "== conditioning bench, $PRESET preset on $DEVICE: ${BENCH_SECONDS} s left, cap $MINUTES min" | tee -a "$OUT/env.txt"
[ "$BENCH_SECONDS" -gt 150 ] || { echo "too little time left for the bench"; exit 6; }
timeout "$BENCH_SECONDS" "$PY" bench/diffuser_conditioning.py --run-dir "$RUN" --preset "$PRESET" --steps "$STEPS" \
    --eval-every "$EVERY" --sampler ddpm --sample-steps 25 --device "$DEVICE" "${BF16[@]}" --max-minutes "$MINUTES" \
    --top-block --horizon 500 --streak 25 --tag "$TAG" ${BENCH_EXTRA:-} 2>&1 | tail -n 40 > "$OUT/bench.log"
echo "bench exit ${PIPESTATUS[0]} (124: stopped by the wall-clock cap; evaluations so far are kept)" | tee -a "$OUT/env.txt"
mv bench/results/diffuser_conditioning/*-"$(basename "$RUN")"*"-$TAG.json" "$OUT/" 2>/dev/null || echo "no bench JSON"
command -v nvidia-smi >/dev/null && nvidia-smi --query-gpu=name,memory.used,memory.total --format=csv >> "$OUT/env.txt"
tail -n 12 "$OUT/bench.log"
ls -l "$OUT"
