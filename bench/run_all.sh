#!/usr/bin/env bash
# Run every benchmark and print its figures (issue 6). Benchmarks are never timed test
# assertions: run them on a quiet machine and compare the ratios each script measures side
# by side in one run. docs/performance.md records the figures and the machine.
#
# Usage: bash bench/run_all.sh [--quick]      (--quick: smaller sizes, for a smoke run)
# Output also goes to out/bench/run_all.log.
set -uo pipefail
cd "$(dirname "$0")/.."
mkdir -p out/bench
LOG=out/bench/run_all.log
QUICK=0
[[ "${1:-}" == "--quick" ]] && QUICK=1

status=0
run() {
    local script=$1; shift
    echo "== python $script $*"
    if [[ ! -f "$script" ]]; then
        echo "!! $script is missing"; status=1; echo; return
    fi
    local t0=$SECONDS
    if ! nice -n 10 python "$script" "$@"; then
        echo "!! $script failed"; status=1
    fi
    echo "   ($((SECONDS - t0)) s)"; echo
}

{
echo "== machine"
echo "date (UTC): $(date -u +%Y-%m-%dT%H:%M:%SZ)"
echo "nproc: $(nproc)   CPU: $(grep -m1 'model name' /proc/cpuinfo | cut -d: -f2- | sed 's/^ *//')"
echo "load average: $(cut -d' ' -f1-3 /proc/loadavg)   memory: $(free -g | awk '/Mem:/{print $2}') GiB"
python -c "import sys, numpy, scipy, mujoco, allantools, dask; print('python', sys.version.split()[0], '| numpy', numpy.__version__, '| scipy', scipy.__version__, '| mujoco', mujoco.__version__, '| allantools', allantools.__version__, '| dask', dask.__version__)"
echo

if [[ $QUICK == 1 ]]; then
    run bench/bench_sim.py --hover-s 5 --repeat 1
    run bench/bench_family_terms.py --hover-s 3 --repeat 1
    run bench/bench_allan.py --n 1000000 --repeat 1
    run bench/bench_attitude.py --n 1000000 --loop-n 100000
    run bench/bench_efficiency.py --instances 40
    run bench/bench_montecarlo.py --scenarios static --sensors icm42688p --instances 2 --duration-s 20 --quick
    run bench/bench_memory.py --duration-s 300 --compare-duration-s 100
else
    run bench/bench_sim.py
    run bench/bench_family_terms.py
    run bench/bench_allan.py
    run bench/bench_attitude.py
    run bench/bench_efficiency.py --instances 200
    run bench/bench_montecarlo.py --scenarios static,turntable --sensors icm42688p --instances 4 --duration-s 60 --quick --dask
    run bench/bench_memory.py
fi
exit $status
} 2>&1 | tee "$LOG"
exit "${PIPESTATUS[0]}"
