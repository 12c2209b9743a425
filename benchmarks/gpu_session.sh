#!/usr/bin/env bash
# One planned GPU session (issue 39: CUDA graphs), in stages, each writing its output under $OUT. Run by the device
# tool from the repository root, with the packages its image lacks carried in .gpu/ (not committed; how to make it:
# docs/benchmarks.md, section "Set-up on a GPU machine"):
#   run(command="BUDGET=555 bash benchmarks/gpu_session.sh check graphs precision profile", carry=[".gpu"])
#       # 256 s on an H100 on 2026-11-24 (its tables: results/benchmarks/2026-11-24-h100.json)
# 2026-11-26 (H200, one 15-minute session): `check` passed on the current code (issue 39's last step), and the walker
# grid's first part ran (4 runs side by side under MPS, 7.7 min; one more alone; docs/benchmarks.md): issue 41's next
# sessions make the two calls in sweeps/walker_tables.toml, the second at once when the first returns. Issue 40's last
# walker-stand seed does not fit such a session: one 100k-step pixel run alone needs ~14 min (10k graphed updates x
# 53 ms, 100k env steps collected at ~430/s, 5 evaluations of 5 episodes), and runs do not outlive their session. In a
# session of 30 device-minutes, it and cartpole-balance's first seed, side by side under MPS (two took 23.5 min without it):
#   run(command="BUDGET=585 MPS=1 PIXEL_WORKERS=2 PIXEL_ONLY='walker_stand__dreamer__s3 cartpole_balance__dreamer__s1' \
#       bash benchmarks/gpu_session.sh check pixels-start pixels-poll", carry=[".gpu"])
#   run(command="BUDGET=585 bash benchmarks/gpu_session.sh pixels-poll", carry=[".gpu"])
#   run(command="BUDGET=585 bash benchmarks/gpu_session.sh pixels-poll pixels-pack", carry=[".gpu"])
#   run(command="BUDGET=430 COMPILE_MODES=loops KERNEL_METHODS='dreamer rbrama' KERNELS_PAPER=0 \
#       bash benchmarks/gpu_session.sh share-bench compile kernels", carry=[".gpu"])
#       # 334 s on an H100 on 2026-11-25, then `MPS=1 SHARE='state 1;state 16' ... share` (141 s) and
#       # `COMPILE_MODES=steps STEPS_METHODS=dreamer ... compile` (31 s): results/benchmarks/2026-11-25-h100.json
# Stages:
#   check      the CUDA tests: graphed updates against eager ones (tests/test_cuda_graph.py), and no host sync in an
#              update under torch.cuda.set_sync_debug_mode("error") (tests/test_update.py::test_update_has_no_host_sync)
#   graphs     --cuda-graph on/off, paired, every method, fp32: paper size (pixels, 50x50) and state mode (16x50)
#   precision  the same with --precision bf16, and fp32 with TF32 matrix products (cuBLAS override)
#   profile    one paper-size Dreamer update's operators, eager and graphed (kernel time against wall time)
#   kernels    the script against commit d1ecdaf's (before 2026-11-25's operator cuts), both graphed, paired
#   compile    benchmarks/compiled_rssm.py (torch.compile on the RSSM's steps, or its whole loops) against the script,
#              both graphed, paired: state mode for dreamer, rrama and vrama, and paper size for dreamer
#   collection the policy's step against the env's, per step of collection (pixels, and the state mode): ~30 s
#   e2e-eager, e2e-graphs   a real walker-walk run from pixels (20k env steps): env steps/s end to end (EGL)
#   share      real runs side by side on the one GPU (SHARE, default 1, 2 and 4 state-mode runs and 2 pixel runs;
#              MPS=1 through MPS): env steps/s in all, GPU memory per run
#   share-bench  bench_update.py --share: 1/4 state-mode processes' graphed updates side by side without MPS, 1/4/16
#              with it, and 1/2 paper-size ones with it: updates/s in all
#   pixels-start, pixels-poll, pixels-pack   issue 40's walker-stand seeds (sweeps/pixels_dreamer.toml) across calls
#   sweep-start, sweep-poll, sweep-pack      any spec the same way (issue 41: SPEC=sweeps/walker_tables.toml), with
#              ONLY (sweep.py --only patterns), MAX_RUNS (sweep.py --max-runs: at most that many of the runs still
#              to do, lowest seed first), WORKERS (runs side by side) and FLAGS (added to the spec's); the poll
#              returns as soon as the sweep has ended, and the pack brings back results/<experiment>/ as sweep.py
#              left it (args.json, metrics.jsonl and the priors' kept episodes) and every run's log tail. Checked on
#              a CPU with a tiny grid (tests/test_sweep.py::test_gpu_session_sweep_stages_run_a_spec); pixels-start and -poll are
#              the same code on sweeps/pixels_dreamer.toml
# Issue 41 (walker tables): in parts of MAX_RUNS runs side by side under MPS, one part per session (the two calls are in
# sweeps/walker_tables.toml); the first part ran on 2026-11-26. The device copies the working tree afresh on every
# call, deleting the untracked results/ an earlier call wrote (runs/, ignored, stays): sweep-pack copies them again.
set -uo pipefail
OUT=${OUT:-/tmp/gpu_out}
mkdir -p "$OUT"
METHODS="dreamer uniform rrama rbrama vrama"
BENCH="python3 benchmarks/bench_update.py --device cuda --no-collection --methods $METHODS"
BENCH_SHARE="python3 benchmarks/bench_update.py --device cuda --cuda-graph True --methods dreamer --share-seconds 8"

# Every stage ends by a deadline: BUDGET seconds after the start (default 560, inside the device tool's 600 s per
# call), so a slow stage leaves the later ones their time and $OUT always comes back with what was measured.
T0=$(date +%s); BUDGET=${BUDGET:-560}
ST=${SWEEP_TMP:-/tmp/gpu_sweep}  # the sweep stages' spec, pid and logs (kept between calls on a warm machine)
left() { echo $((T0 + BUDGET - $(date +%s))); }
cap() { local l; l=$(left); [ "$l" -lt "$1" ] && echo "$l" || echo "$1"; }  # a stage's own limit, or less if late

# a sweep spec (its flags extended) started detached, so that its runs outlive the call: spec, --only patterns
# (space-separated, not globbed here), workers, flags to add
start_sweep() {
  mkdir -p "$ST"; sed "s|^flags = \"\"\"|flags = \"\"\"$4 |" "$1" > "$ST/spec.toml"
  grep -A1 '^flags = """' "$ST/spec.toml" | tee "$OUT/$(basename "$1" .toml)-spec.txt"
  set -f; setsid nohup python3 sweep.py "$ST/spec.toml" --workers "$3" ${2:+--only $2} ${MAX_RUNS:+--max-runs $MAX_RUNS} \
    > "$ST/sweep.log" 2>&1 < /dev/null &
  set +f; echo $! > "$ST/pid"; sleep 5; cat "$ST/sweep.log"
}

# NVIDIA's multi-process service, so that processes sharing the GPU may run their small kernels at the same time
# rather than take turns (if the image has nvidia-cuda-mps-control; otherwise one line says so and they share as usual)
mps_start() {
  export CUDA_MPS_PIPE_DIRECTORY=/tmp/mps CUDA_MPS_LOG_DIRECTORY=/tmp/mps-log; mkdir -p /tmp/mps /tmp/mps-log
  if nvidia-cuda-mps-control -d >> "$OUT/mps.txt" 2>&1; then echo "MPS: started" | tee -a "$OUT/mps.txt"
  else echo "MPS: could not start" | tee -a "$OUT/mps.txt"; unset CUDA_MPS_PIPE_DIRECTORY CUDA_MPS_LOG_DIRECTORY; fi
}
mps_stop() {
  [ -n "${CUDA_MPS_PIPE_DIRECTORY:-}" ] && { echo quit | nvidia-cuda-mps-control; sleep 2; }
  unset CUDA_MPS_PIPE_DIRECTORY CUDA_MPS_LOG_DIRECTORY
}

# set-up (once per machine): Python packages from .gpu/wheels into /tmp/site; EGL libraries from .gpu/debs for MuJoCo
export PYTHONPATH=/tmp/site MUJOCO_GL=egl PYTHONUNBUFFERED=1
if [ ! -d /tmp/site/tyro ] && [ -d .gpu ]; then  # (no .gpu: a machine with the packages already, e.g. a CPU check)
  python3 -m pip install -q --no-index --no-deps --target /tmp/site .gpu/wheels/*.whl 2>&1 | tail -2
  for f in .gpu/debs/*.deb; do dpkg -x "$f" / 2>/dev/null; done
  ldconfig 2>/dev/null
fi
{ date -u; nvidia-smi --query-gpu=name,driver_version,memory.total,clocks.sm --format=csv;
  python3 -c "import torch, tyro, gymnasium; print('torch', torch.__version__, torch.cuda.get_device_name())"
  git log -1 --format='commit %H %s' 2>/dev/null || true; } 2>&1 | tee -a "$OUT/setup.txt"

for stage in "$@"; do
  echo "=== $stage ($(date -u +%T))"
  case "$stage" in
    check)
      timeout "$(cap 180)" python3 -m pytest -q -rA --tb=short -p no:cacheprovider tests/test_cuda_graph.py \
        "tests/test_update.py::test_update_has_no_host_sync" 2>&1 \
        | tee "$OUT/check.txt" | tail -15 ;;
    graphs)
      timeout "$(cap 170)" $BENCH --ab-flag cuda-graph --sizes paper --updates 20 \
        --json "$OUT/graphs-paper-fp32.json" 2>&1 | tee "$OUT/graphs-paper-fp32.txt"
      timeout "$(cap 90)" $BENCH --ab-flag cuda-graph --sizes small --obs-type state --mlp-units 200 --updates 40 \
        --json "$OUT/graphs-state-fp32.json" 2>&1 | tee "$OUT/graphs-state-fp32.txt" ;;
    precision)
      timeout "$(cap 120)" $BENCH --ab-flag cuda-graph --sizes paper --updates 10 --precision bf16 \
        --json "$OUT/graphs-paper-bf16.json" 2>&1 | tee "$OUT/graphs-paper-bf16.txt"
      TORCH_ALLOW_TF32_CUBLAS_OVERRIDE=1 timeout "$(cap 120)" $BENCH --ab-flag cuda-graph --sizes paper --updates 10 \
        --json "$OUT/graphs-paper-tf32.json" 2>&1 | tee "$OUT/graphs-paper-tf32.txt" ;;
    profile)
      timeout "$(cap 60)" python3 benchmarks/bench_update.py --device cuda --profile --cuda-graph True 2>&1 \
        | tee "$OUT/profile-graphs.txt" | tail -30
      timeout "$(cap 60)" python3 benchmarks/bench_update.py --device cuda --profile 2>&1 \
        | tee "$OUT/profile-eager.txt" | tail -30 ;;
    kernels)  # 2026-11-25's operator cuts (the prior head after the filter's loop, RbRAMa's one pass, unbind), graphed,
      # paired against the script before them (commit d1ecdaf): what 17.6% fewer operators on a CPU buy on the GPU
      # (a copy without .git: make the file before the call, `git show d1ecdaf:rama_dreamer.py > /tmp/before_cuts.py`
      # here, then copy it to benchmarks/before_cuts.py, untracked, so that it travels with the working tree)
      before=benchmarks/before_cuts.py
      [ -f "$before" ] || git show d1ecdaf:rama_dreamer.py > "$before" || { echo "kernels: no $before"; continue; }
      timeout "$(cap 200)" python3 benchmarks/bench_update.py --device cuda --no-collection --methods \
        ${KERNEL_METHODS:-$METHODS} --cuda-graph True --compare-to "$before" --sizes small --obs-type state \
        --mlp-units 200 --updates 20 --json "$OUT/kernels-state.json" 2>&1 | tee "$OUT/kernels-state.txt"
      [ "${KERNELS_PAPER:-1}" = 1 ] && timeout "$(cap 150)" python3 benchmarks/bench_update.py --device cuda \
        --no-collection --methods dreamer rbrama --cuda-graph True --compare-to "$before" --sizes paper --updates 10 \
        --json "$OUT/kernels-paper.json" 2>&1 | tee "$OUT/kernels-paper.txt" ;;
    compile)  # issue 39's next lever: torch.compile's fused kernels inside the graphs (benchmarks/compiled_rssm.py),
      # paired against the script, state mode (COMPILE_MODES: loops and/or steps; loops compiles for minutes, so it
      # times LOOPS_METHODS, dreamer by default; STEPS_METHODS likewise); COMPILE_PAPER=loops or steps adds that mode
      # at paper size for dreamer
      for mode in ${COMPILE_MODES:-loops steps}; do
        methods=$([ "$mode" = loops ] && echo ${LOOPS_METHODS:-dreamer} || echo ${STEPS_METHODS:-dreamer rrama vrama})
        COMPILE=$mode timeout "$(cap 240)" python3 benchmarks/bench_update.py --device cuda --no-collection \
          --cuda-graph True --compare-to benchmarks/compiled_rssm.py --methods $methods --sizes small \
          --obs-type state --mlp-units 200 --updates 20 --json "$OUT/compile-$mode-state.json" 2>&1 \
          | grep -v -i warn | tee "$OUT/compile-$mode-state.txt"
      done
      mode=${COMPILE_PAPER:-}
      [ -n "$mode" ] && COMPILE=$mode timeout "$(cap 240)" python3 benchmarks/bench_update.py --device cuda \
        --no-collection --cuda-graph True --compare-to benchmarks/compiled_rssm.py --methods dreamer --sizes paper \
        --updates 10 --json "$OUT/compile-$mode-paper.json" 2>&1 | grep -v -i warn | tee "$OUT/compile-$mode-paper.txt" ;;
    share-bench)  # issue 39 item 5 and issue 41's budget: N processes' graphed updates side by side on the one GPU,
      # without and with MPS (bench_update.py --share): do updates add up when runs share the GPU? State mode 1/4/16
      # processes, paper size 1/2 (MPS only). Updates alone, no collection: the update is what a run mostly waits on
      for mps in 0 1; do
        [ "$mps" = 1 ] && mps_start
        counts=$([ "$mps" = 1 ] && echo 1 4 16 || echo 1 4)
        OMP_NUM_THREADS=1 timeout "$(cap 90)" $BENCH_SHARE --share $counts --sizes small --obs-type state \
          --mlp-units 200 --json "$OUT/share-state-mps$mps.json" 2>&1 | tee "$OUT/share-state-mps$mps.txt"
        [ "$mps" = 1 ] && OMP_NUM_THREADS=1 timeout "$(cap 60)" $BENCH_SHARE --share 1 2 --sizes paper \
          --json "$OUT/share-paper-mps$mps.json" 2>&1 | tee "$OUT/share-paper-mps$mps.txt"
        [ "$mps" = 1 ] && mps_stop
      done ;;
    collection)  # where a step of collection goes (bench_update.py's collection line): the policy's eager step on the
      # GPU against the rest (physics, EGL rendering, bookkeeping), from pixels at paper size and in the walker tables'
      # state mode: the most that graphing the policy's step could save (CPU figures: docs/benchmarks.md)
      for obs in "--obs-type pixels" "--obs-type state --mlp-units 200"; do
        timeout "$(cap 60)" python3 benchmarks/bench_update.py --device cuda --sizes small --methods dreamer \
          --updates 1 $obs 2>&1 | grep collection | tee -a "$OUT/collection.txt"
      done ;;
    e2e-eager|e2e-graphs)  # one per call: the eager run takes about 8 of a call's 10 minutes
      flag=$([ "$stage" = e2e-graphs ] && echo True || echo False)
      timeout "$(( $(left) - 10 ))" python3 rama_dreamer.py --env-id dmc/walker-walk --total-steps 20000 --eval-every 20000 \
        --plain-log --run-dir /tmp/e2e --exp-name "$stage" --cuda-graph $flag 2>&1 | tee "$OUT/$stage.txt" | tail -8
      cp /tmp/e2e/*"$stage"*/metrics.jsonl "$OUT/$stage-metrics.jsonl" ;;  # the episodes stay there (GBs)
    share)  # issue 39, item 5: N runs side by side on the one GPU: aggregate env steps/s and GPU memory per run
      # MPS=1: through NVIDIA's multi-process service, so that the runs' small kernels may overlap rather than take
      # turns (if the image has nvidia-cuda-mps-control; otherwise one line says so and the runs share as usual)
      [ "${MPS:-0}" = 1 ] && mps_start
      IFS=';' read -ra specs <<< "${SHARE:-state 1;state 2;state 4;pixels 2}"  # SHARE="state 8;state 16" for others
      for spec in "${specs[@]}"; do
        [ "$(left)" -lt 60 ] && { echo "share: $spec skipped (the call's deadline)" | tee -a "$OUT/share.txt"; continue; }
        set -- $spec; obs=$1; n=$2; start=$(date +%s.%N); pids=""; limit=$(( $(left) - 15 ))
        for i in $(seq 1 "$n"); do
          timeout "$limit" python3 rama_dreamer.py --env-id dmc/walker-walk --obs-type "$obs" $([ "$obs" = state ] && echo \
            --batch-size 16 --mlp-units 200) --total-steps 10000 --eval-every 10000 --plain-log --seed "$i" \
            --run-dir /tmp/share --exp-name "share_${obs}_${n}" --cuda-graph ${GRAPHS:-True} \
            > "/tmp/share_${obs}_${n}_$i.log" 2>&1 &
          pids="$pids $!"
        done
        sleep 20; mem=$(nvidia-smi --query-compute-apps=used_memory --format=csv,noheader,nounits | paste -sd+)
        wait $pids; took=$(python3 -c "import time; print(f'{time.time() - $start:.1f}')")
        echo "$obs x$n: ${took} s wall, $(python3 -c "print(f'{$n * 10000 / $took:.0f}')") env steps/s in all," \
          "GPU MiB per process at 20 s: $mem, MPS ${MPS:-0}" | tee -a "$OUT/share.txt"
      done
      [ "${MPS:-0}" = 1 ] && mps_stop ;;
    pixels-start)  # issue 40, detached: the runs go on while later calls hold the machine (within 30 s of each other)
      [ "${MPS:-0}" = 1 ] && mps_start  # (2 paper-size processes: 1.26x one's updates/s under MPS, 2026-11-25)
      # PIXEL_ONLY picks the runs, PIXEL_FLAGS adds flags to the spec's (e.g. --precision bf16; graphs are the CUDA default)
      start_sweep sweeps/pixels_dreamer.toml "${PIXEL_ONLY:-walker_stand__*}" "${PIXEL_WORKERS:-3}" "${PIXEL_FLAGS:-}" ;;
    pixels-pack)  # every run's args.json, metrics.jsonl, log tail and last open-loop GIF, as results/ holds them
      for run in runs/pixels_dreamer/*/; do
        name=$(basename "$run"); mkdir -p "$OUT/pixels_dreamer/$name"
        cp "$run"/*/args.json "$run"/*/metrics.jsonl "$OUT/pixels_dreamer/$name/" 2>/dev/null
        tail -n 40 "$run/log.txt" > "$OUT/pixels_dreamer/$name/log_tail.txt" 2>/dev/null
        last=$(ls -t "$run"/*/videos/*openloop*.gif 2>/dev/null | head -1)
        [ -n "$last" ] && cp "$last" "$OUT/pixels_dreamer/$name/"
      done
      nvidia-smi > "$OUT/pixels_dreamer/nvidia-smi.txt" 2>&1
      tar czf "$OUT/pixels_dreamer.tgz" -C "$OUT" pixels_dreamer && rm -rf "$OUT/pixels_dreamer" \
        && tar tzvf "$OUT/pixels_dreamer.tgz" ;;
    sweep-start)  # detached, like pixels-start: the runs go on between calls (their bookkeeping in $ST); MPS=1 runs
      # them through MPS (16 state-mode runs side by side: 9x one run's env steps/s on the H100, 2026-11-25)
      [ "${MPS:-0}" = 1 ] && mps_start
      start_sweep "${SPEC:?sweep-start needs SPEC=sweeps/<name>.toml}" "${ONLY:-}" "${WORKERS:-4}" "${FLAGS:-}" ;;
    pixels-poll|sweep-poll)  # until the sweep has ended (checked every 10 s) or 45 s of the call are left: each
      # unfinished run's last line, every minute
      exp=$(sed -n 's/^experiment = "\(.*\)"/\1/p' "$ST/spec.toml"); ticks=0
      while [ "$(left)" -gt 45 ] && kill -0 "$(cat "$ST/pid")" 2>/dev/null; do
        sleep "$(cap 10)"; ticks=$((ticks + 1)); [ $((ticks % 6)) = 0 ] || continue; echo "--- $(date -u +%T)"
        for f in runs/"$exp"/*/log.txt; do [ -e "${f%log.txt}DONE" ] || echo "$f: $(tail -n 1 "$f")"; done
      done; cat "$ST/sweep.log" ;;
    sweep-pack)  # results/<experiment>/ with every done run's results, the sweep's log and each run's log tail.
      # The device copies the working tree afresh on every call, which deletes the untracked results/ an earlier call
      # wrote (runs/, ignored, stays): sweep.py --collect copies them again from runs/ (2026-11-26 lost four runs so)
      exp=$(sed -n 's/^experiment = "\(.*\)"/\1/p' "$ST/spec.toml"); mkdir -p "$ST/logs/$exp" "results/$exp"
      python3 sweep.py "$ST/spec.toml" --collect 2>&1 | tail -n 20
      cp "$ST/sweep.log" "$ST/logs/$exp/sweep.txt"
      for run in runs/"$exp"/*/; do tail -n 40 "$run/log.txt" > "$ST/logs/$exp/$(basename "$run").txt"; done
      tar czf "$OUT/$exp.tgz" "results/$exp" -C "$ST" logs && tar tzf "$OUT/$exp.tgz" | tail -n 12 ;;
    *) echo "unknown stage $stage (check, graphs, precision, profile, e2e-eager, e2e-graphs, pixels-start," \
            "pixels-poll, pixels-pack, sweep-start, sweep-poll, sweep-pack, share, share-bench, kernels, compile," \
            "collection)" ;;
  esac
done
# the device tool brings back at most 8 files: past 7, everything goes back as one archive
if [ "$(find "$OUT" -type f | wc -l)" -gt 7 ]; then
  tar czf /tmp/session.tgz -C "$OUT" . && rm -rf "${OUT:?}"/* && mv /tmp/session.tgz "$OUT/session.tgz"
fi
echo "=== done ($(date -u +%T))"
