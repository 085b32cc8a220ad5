#!/usr/bin/env bash
# The GPU suite (issue #21, item 5): localize, odometry, batched GICP, fusion and SLAM
# benchmarks (and bench_commands.py's localize and slam) on cuda within 8 minutes, merged into
# bench/results/device_suite.json with the GPU's name; `python bench/run_all.py` renders it
# as the page's cuda section. Sets up nothing from the network.
#
#   bash bench/device_suite.sh                          # cuda, the full suite (< 8 min)
#   bash bench/device_suite.sh --backend cpu --quick    # smoke test without a GPU
#
# Python: $PYTHON, else .venv/bin/python, else python3, with mcl3d's dependencies (taichi,
# open3d, ...) and the bench extra; on a bare machine without a network, what
# bench/device_pack.sh installed in /tmp/site (see there for the two calls).
set -euo pipefail
cd "$(dirname "$0")/.."

backend=cuda
for ((i = 1; i <= $#; i++)); do
  if [[ "${!i}" == "--backend" ]]; then j=$((i + 1)); backend="${!j:-}"; fi
  if [[ "${!i}" == --backend=* ]]; then backend="${!i#--backend=}"; fi
done

if [[ -d /tmp/site ]]; then  # a bare machine set up by bench/device_pack.sh --install
  export PYTHONPATH="/tmp/site:$PWD${PYTHONPATH:+:$PYTHONPATH}"
  export LD_LIBRARY_PATH="/tmp/gllibs${LD_LIBRARY_PATH:+:$LD_LIBRARY_PATH}"
fi
if [[ -z "${PYTHON:-}" ]]; then
  if [[ -x .venv/bin/python ]]; then PYTHON=.venv/bin/python; else PYTHON=python3; fi
fi
if ! "$PYTHON" -c "import taichi, mcl3d" > /dev/null 2>&1; then
  echo "device_suite: $PYTHON cannot import taichi and mcl3d; run 'bash setup.sh bench'" \
    "on this machine (bench/device_pack.sh on one without a network), or set PYTHON to an environment that has them" >&2
  exit 1
fi
if ! "$PYTHON" -c "import mcl3d.maps, mcl3d.kernels" > /dev/null 2>&1; then
  # not installed (a bare machine): maps/ and kernels/ install as mcl3d.maps and
  # mcl3d.kernels (pyproject.toml), so link them there for this run
  ln -s ../maps mcl3d/maps && ln -s ../kernels mcl3d/kernels
  trap 'rm -f mcl3d/maps mcl3d/kernels' EXIT
fi

if [[ "$backend" == "cuda" ]]; then
  if ! gpu=$(nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader \
      2> /dev/null) || [[ -z "$gpu" ]]; then
    echo "device_suite: no NVIDIA GPU (nvidia-smi found none); run it on a cuda machine," \
      "or pass --backend cpu for a smoke test" >&2
    exit 1
  fi
  if ! "$PYTHON" -c "from mcl3d.core import runtime; runtime.init('cuda')" > /dev/null; then
    echo "device_suite: nvidia-smi sees '$gpu' but Taichi cannot start cuda" >&2
    exit 1
  fi
  export MCL3D_DEVICE_NAME="$gpu"
fi

"$PYTHON" bench/device_suite.py "$@"
