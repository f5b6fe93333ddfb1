#!/usr/bin/env bash
# Every GPU bench in one go, on a machine with a CUDA device and the solver importable:
#
#     BAREESA_SHARED=/path/to/shared bash bench/gpu.sh [OUTDIR] [SECONDS]
#
# Checks that KeOps compiles and runs on the GPU (else, or with BAREESA_NO_KEOPS=1 set, the benches
# run with dense torch, as "auto" does without pykeops), runs the CUDA tests, then
# bench.registration_speed (float32; with KeOps twice, the first paying its compiles; float64 last),
# bench.varifold_speed --device cuda and bench.user_speed --device cuda. Each step's log goes to
# OUTDIR (default bench/out/gpu); no step starts after SECONDS (default 480) from the start, and
# each has its own time limit. The benches' results files (bench/results/*--device-cuda*.json) are
# copied to OUTDIR too, to be brought back into bench/results where the GPU machine is not the checkout.
set -u
out=${1:-bench/out/gpu}
budget=${2:-480}
py=${PYTHON:-python3}
mkdir -p "$out"
export PYTHONUNBUFFERED=1
t0=$(date +%s)

step() {  # step NAME LIMIT_SECONDS COMMAND... : run it with its log in OUTDIR, print its end
    local name=$1 limit=$2 start rc
    shift 2
    start=$(date +%s)
    if (( start - t0 + 10 > budget )); then
        echo "== $name: not started (the ${budget} s budget is spent)"
        return 1
    fi
    (( limit > budget - (start - t0) )) && limit=$(( budget - (start - t0) ))
    echo "== $name (limit ${limit} s)"
    timeout "$limit" "$@" >"$out/$name.log" 2>&1
    rc=$?
    echo "== $name: exit $rc after $(( $(date +%s) - start )) s"
    tail -n "${TAIL:-45}" "$out/$name.log"
    return $rc
}

nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv,noheader
"$py" -c "import numpy, scipy, torch; print('torch', torch.__version__, 'CUDA', torch.version.cuda, \
'numpy', numpy.__version__, 'scipy', scipy.__version__, 'GPU', torch.cuda.get_device_name())" || exit 1

keops=no
if [[ ${BAREESA_NO_KEOPS:-} == 1 ]]; then
    echo "BAREESA_NO_KEOPS=1: dense torch, no KeOps"
elif step keops_check 240 "$py" -m bench.keops_check; then
    keops=yes
else
    echo "KeOps does not run on this GPU: the benches below use dense torch (BAREESA_NO_KEOPS=1)"
    export BAREESA_NO_KEOPS=1
fi
step cuda_tests 90 "$py" -m pytest -q -p no:cacheprovider tests/test_cuda.py tests/test_h2_metric.py -k cuda
step registration_speed_f32 150 "$py" -m bench.registration_speed --device cuda --dtype float32
[[ $keops == yes ]] && step registration_speed_f32_warm 90 "$py" -m bench.registration_speed --device cuda --dtype float32
step varifold_speed 100 "$py" bench/varifold_speed.py --device cuda
step user_speed 200 "$py" -m bench.user_speed --device cuda --skip matching random
step user_speed_matching 150 "$py" -m bench.user_speed --device cuda --skip registration interpolation \
    extrapolation random
step registration_speed_f64 120 "$py" -m bench.registration_speed --device cuda --dtype float64
cp bench/out/*cuda*.md "$out"/ 2>/dev/null
cp bench/results/*cuda*.json "$out"/ 2>/dev/null
echo "== all steps: $(( $(date +%s) - t0 )) s"
