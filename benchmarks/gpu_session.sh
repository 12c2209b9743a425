#!/usr/bin/env bash
# One planned GPU session (issue 39: CUDA graphs), in stages, each writing its output under $OUT. Run by the device
# tool from the repository root, with the packages its image lacks carried in .gpu/ (not committed; how to make it:
# docs/benchmarks.md, section "`--cuda-graph`: written and tested on the CPU"):
#   run(command="bash benchmarks/gpu_session.sh check graphs", carry=[".gpu"])      # estimated 4 min
#   run(command="bash benchmarks/gpu_session.sh precision profile", carry=[".gpu"]) # estimated 4 min
# Stages:
#   check      the CUDA equivalence test: graphed updates against eager ones (tests/test_cuda_graph.py)
#   graphs     --cuda-graph on/off, paired, every method, fp32: paper size (pixels, 50x50) and state mode (16x50)
#   precision  the same with --precision bf16, and fp32 with TF32 matrix products (cuBLAS override)
#   profile    one paper-size Dreamer update's operators, eager and graphed (kernel time against wall time)
#   e2e-eager, e2e-graphs   a real walker-walk run from pixels (20k env steps): env steps/s end to end (EGL)
#   share      1, 2 and 4 state-mode runs and 2 pixel runs side by side: env steps/s in all, GPU memory per run
#   pixels-start, pixels-poll, pixels-pack   issue 40's walker-stand seeds (sweeps/pixels_dreamer.toml) across calls
set -uo pipefail
OUT=${OUT:-/tmp/gpu_out}
mkdir -p "$OUT"
METHODS="dreamer uniform rrama rbrama vrama"
BENCH="python3 benchmarks/bench_update.py --device cuda --no-collection --methods $METHODS"

# set-up: Python packages from .gpu/wheels into /tmp/site; EGL libraries from .gpu/debs for MuJoCo's rendering
python3 -m pip install -q --no-index --no-deps --target /tmp/site .gpu/wheels/*.whl 2>&1 | tail -2
export PYTHONPATH=/tmp/site MUJOCO_GL=egl
for f in .gpu/debs/*.deb; do dpkg -x "$f" / 2>/dev/null; done
ldconfig 2>/dev/null
{ date -u; nvidia-smi --query-gpu=name,driver_version,memory.total,clocks.sm --format=csv;
  python3 -c "import torch, tyro, gymnasium; print('torch', torch.__version__, torch.cuda.get_device_name())"
  git log -1 --format='commit %H %s' 2>/dev/null || true; } 2>&1 | tee "$OUT/setup.txt"

for stage in "$@"; do
  echo "=== $stage ($(date -u +%T))"
  case "$stage" in
    check)
      python3 -m pytest -q -p no:cacheprovider tests/test_cuda_graph.py 2>&1 | tee "$OUT/check.txt" | tail -15 ;;
    graphs)
      $BENCH --ab-flag cuda-graph --sizes paper --updates 20 --json "$OUT/graphs-paper-fp32.json" \
        2>&1 | tee "$OUT/graphs-paper-fp32.txt"
      $BENCH --ab-flag cuda-graph --sizes small --obs-type state --mlp-units 200 --updates 40 \
        --json "$OUT/graphs-state-fp32.json" 2>&1 | tee "$OUT/graphs-state-fp32.txt" ;;
    precision)
      $BENCH --ab-flag cuda-graph --sizes paper --updates 20 --precision bf16 --json "$OUT/graphs-paper-bf16.json" \
        2>&1 | tee "$OUT/graphs-paper-bf16.txt"
      TORCH_ALLOW_TF32_CUBLAS_OVERRIDE=1 $BENCH --ab-flag cuda-graph --sizes paper --updates 20 \
        --json "$OUT/graphs-paper-tf32.json" 2>&1 | tee "$OUT/graphs-paper-tf32.txt" ;;
    profile)
      python3 benchmarks/bench_update.py --device cuda --profile 2>&1 | tee "$OUT/profile-eager.txt" | tail -30
      python3 benchmarks/bench_update.py --device cuda --profile --cuda-graph 2>&1 | tee "$OUT/profile-graphs.txt" \
        | tail -30 ;;
    e2e-eager|e2e-graphs)  # one per call: the eager run takes about 8 of a call's 10 minutes
      flag=$([ "$stage" = e2e-graphs ] && echo --cuda-graph || echo --no-cuda-graph)
      timeout 560 python3 rama_dreamer.py --env-id dmc/walker-walk --total-steps 20000 --eval-every 20000 \
        --plain-log --run-dir /tmp/e2e --exp-name "$stage" $flag 2>&1 | tee "$OUT/$stage.txt" | tail -8
      cp /tmp/e2e/*"$stage"*/metrics.jsonl "$OUT/$stage-metrics.jsonl" ;;  # the episodes stay there (GBs)
    share)  # issue 39, item 5: N runs side by side on the one GPU: aggregate env steps/s and GPU memory per run
      for spec in "state 1" "state 2" "state 4" "pixels 2"; do
        set -- $spec; obs=$1; n=$2; start=$(date +%s.%N); pids=""
        for i in $(seq 1 "$n"); do
          python3 rama_dreamer.py --env-id dmc/walker-walk --obs-type "$obs" $([ "$obs" = state ] && echo \
            --batch-size 16 --mlp-units 200) --total-steps 10000 --eval-every 10000 --plain-log --seed "$i" \
            --run-dir /tmp/share --exp-name "share_${obs}_${n}" ${GRAPHS:---cuda-graph} \
            > "/tmp/share_${obs}_${n}_$i.log" 2>&1 &
          pids="$pids $!"
        done
        sleep 20; mem=$(nvidia-smi --query-compute-apps=used_memory --format=csv,noheader,nounits | paste -sd+)
        wait $pids; took=$(python3 -c "import time; print(f'{time.time() - $start:.1f}')")
        echo "$obs x$n: ${took} s wall, $(python3 -c "print(f'{$n * 10000 / $took:.0f}')") env steps/s in all," \
          "GPU MiB per process at 20 s: $mem" | tee -a "$OUT/share.txt"
      done ;;
    pixels-start)  # issue 40: the walker-stand seeds side by side, detached; they run while later calls hold the GPU
      setsid nohup python3 sweep.py sweeps/pixels_dreamer.toml --workers 3 --only "walker_stand__*" \
        > /tmp/pixels.log 2>&1 < /dev/null &
      sleep 240; tail -n 3 runs/pixels_dreamer/*/log.txt ;;
    pixels-poll)  # one call: about 9 minutes of the runs, then where they are
      sleep 530; tail -n 2 runs/pixels_dreamer/*/log.txt; cat /tmp/pixels.log ;;
    pixels-pack)  # every run's args.json, metrics.jsonl and its last open-loop prediction GIF, as results/ holds them
      for run in runs/pixels_dreamer/*/; do
        name=$(basename "$run"); mkdir -p "$OUT/pixels_dreamer/$name"
        cp "$run"/*/args.json "$run"/*/metrics.jsonl "$OUT/pixels_dreamer/$name/" 2>/dev/null
        last=$(ls -t "$run"/*/videos/*openloop*.gif 2>/dev/null | head -1)
        [ -n "$last" ] && cp "$last" "$OUT/pixels_dreamer/$name/"
      done
      tar czf "$OUT/pixels_dreamer.tgz" -C "$OUT" pixels_dreamer && ls -la "$OUT/pixels_dreamer"/* ;;
    *) echo "unknown stage $stage (check, graphs, precision, profile, e2e-eager, e2e-graphs, pixels-start," \
            "pixels-poll, pixels-pack, share)" ;;
  esac
done
echo "=== done ($(date -u +%T))"
