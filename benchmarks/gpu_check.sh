#!/usr/bin/env bash
# The measurements on a GPU, in one go: the update step of `make bench` on the device (every row of
# bench_losses.py, the JAX peer too when JAX has a CUDA backend), then the default run (make run's job) with
# device=cuda and its stage breakdown. What it writes into OUTDIR (a few small text files; the run's
# checkpoints and rollouts stay in the run directory):
#   env.txt        the GPU, torch, CUDA and the software stack
#   bench.txt      bench_losses.py --device DEVICE
#   run.txt        the default run's output; results.json and config.yaml: the run's
#   breakdown.txt  run_breakdown.py on that run
#
#   benchmarks/gpu_check.sh OUTDIR [DEVICE]          # DEVICE: cuda (default) or cuda:<index>
#
# Environment: PYTHON (default python3) must have a CUDA build of torch; the project's other dependencies come
# from its environment, or, on a machine without network, from WHEELS, a folder of wheels that is installed
# (no index, no dependencies resolved) into SITE (default /tmp/spoil_torchrl_site) first. BENCH_ARGS replaces
# the bench's arguments (default: one thread, 300 steps, 3 repeats, 5 seeds); RUN_DIR is where the run goes
# (default: a new temporary folder); RUN_ARGS are added to the run's settings; PARTS picks the parts (default
# "bench run"). A part that fails is reported and the next one still runs; the exit status is then 1.
set -euo pipefail
out=${1:?usage: benchmarks/gpu_check.sh OUTDIR [DEVICE]}
device=${2:-cuda}
python=${PYTHON:-python3}
root=$(cd "$(dirname "$0")/.." && pwd)
mkdir -p "$out"
out=$(cd "$out" && pwd)
if [ -n "${WHEELS:-}" ]; then
  site=${SITE:-/tmp/spoil_torchrl_site}
  "$python" -m pip install --quiet --no-index --no-deps --no-compile --no-cache-dir --upgrade --target "$site" \
    "$WHEELS"/*.whl
  export PYTHONPATH="$site${PYTHONPATH:+:$PYTHONPATH}"
fi
export PYTHONPATH="$root${PYTHONPATH:+:$PYTHONPATH}" PYTHONUNBUFFERED=1
export XLA_PYTHON_CLIENT_PREALLOCATE=false  # the JAX peer takes GPU memory as it needs it, beside torch's
cd "$root"
parts=" ${PARTS:-bench run} "
status=0

{
  nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv 2>&1 || true
  "$python" -c 'import json, torch; from spoil_torchrl.stack import current_stack, current_machine
print("torch", torch.__version__, "CUDA", torch.version.cuda, "devices", torch.cuda.device_count())
print(json.dumps({"stack": current_stack(), "machine": current_machine()}))'
} 2>&1 | tee "$out/env.txt"

if [[ $parts == *" bench "* ]]; then
  read -r -a bench_args <<< "${BENCH_ARGS:---threads 1 --steps 300 --repeats 3 --seeds 5}"
  "$python" benchmarks/bench_losses.py --device "$device" "${bench_args[@]}" 2>&1 | tee "$out/bench.txt" \
    || { echo "gpu_check: the bench failed" | tee -a "$out/bench.txt"; status=1; }
fi

if [[ $parts == *" run "* ]]; then
  run_dir=${RUN_DIR:-$(mktemp -d)/run}
  read -r -a run_args <<< "${RUN_ARGS:-}"
  if "$python" recipes/spoildice_dsrl.py device="$device" hydra.run.dir="$run_dir" progress=false \
    "${run_args[@]}" 2>&1 | tee "$out/run.txt"; then
    cp "$run_dir/results.json" "$run_dir/config.yaml" "$out/"
    "$python" benchmarks/run_breakdown.py "$run_dir/results.json" 2>&1 | tee "$out/breakdown.txt"
  else
    echo "gpu_check: the run failed (its directory: $run_dir)" | tee -a "$out/run.txt"
    status=1
  fi
fi
exit $status
