# shellcheck shell=bash
# The one place that sets up the ROS 2 environment of this project. Source it:
#     source scripts/env.sh
# It never depends on the caller's shell for anything that decides where DDS traffic goes:
#   - AMENT_PREFIX_PATH: the venv prefix (ROS 2 wheels) plus the workspace install space;
#   - the workspace's install/setup.bash (PYTHONPATH, LD_LIBRARY_PATH of the generated messages);
#   - ROS_LOG_DIR inside the repo's ignored .cache/ folder;
#   - ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST: discovery and traffic stay on loopback;
#   - ROS_DOMAIN_ID: TRAIN_ROS_DOMAIN_ID if given, else a random id in [1, 100] per sourcing.
#     (A developer's own ROS_DOMAIN_ID is deliberately ignored; override with TRAIN_ROS_DOMAIN_ID.)
#   - one BLAS/OpenMP thread per process (small matrices; see the end of this file);

TRAIN_REPO="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
export TRAIN_REPO
TRAIN_VENV="${TRAIN_REPO}/.venv"
export TRAIN_VENV

if [ ! -x "${TRAIN_VENV}/bin/python" ]; then
    echo "scripts/env.sh: ${TRAIN_VENV} is missing; run './run setup' first" >&2
    return 1 2>/dev/null || exit 1
fi

# shellcheck disable=SC1091
source "${TRAIN_VENV}/bin/activate"

# ament_index lookups need the venv prefix (where the ROS 2 wheels put share/ament_index).
export AMENT_PREFIX_PATH="${TRAIN_VENV}"
export CMAKE_PREFIX_PATH="${TRAIN_VENV}"
if [ -f "${TRAIN_REPO}/ros_ws/install/setup.bash" ]; then
    # colcon's setup.bash references unset variables; keep the caller's `set -u` happy.
    _train_nounset=$(set -o | awk '$1=="nounset"{print $2}')
    set +u
    # shellcheck disable=SC1091
    source "${TRAIN_REPO}/ros_ws/install/setup.bash"
    [ "${_train_nounset}" = "on" ] && set -u
    unset _train_nounset
fi

# `ros2 run PKG EXE` runs <prefix>/lib/PKG/EXE; there is no ros2 command on the pip set-up, so
# put those folders on PATH: `simulator --ros-args ...` then works as `ros2 run` would.
for _d in "${TRAIN_REPO}"/ros_ws/install/*/lib/train_*; do
    [ -d "${_d}" ] && PATH="${_d}:${PATH}"
done
unset _d
export PATH
export ROS_LOG_DIR="${TRAIN_REPO}/.cache/ros_log"
mkdir -p "${ROS_LOG_DIR}"
export ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST
unset ROS_STATIC_PEERS
export RMW_IMPLEMENTATION=rmw_fastrtps_cpp
if [ -n "${TRAIN_ROS_DOMAIN_ID:-}" ]; then
    export ROS_DOMAIN_ID="${TRAIN_ROS_DOMAIN_ID}"
else
    ROS_DOMAIN_ID=$(( (RANDOM % 100) + 1 ))
    export ROS_DOMAIN_ID
fi
export PYTHONDONTWRITEBYTECODE=1

# One BLAS thread per process. The filters multiply 2x2 to 4x4 matrices: a second BLAS thread
# only spins, and beside other processes on a 2-core machine (nodes, test workers, dask
# workers) the spinning threads starve each other (one expm-heavy test: 26 s against 1 s).
# A caller's explicit setting wins.
export OMP_NUM_THREADS="${OMP_NUM_THREADS:-1}"
export OPENBLAS_NUM_THREADS="${OPENBLAS_NUM_THREADS:-1}"
export MKL_NUM_THREADS="${MKL_NUM_THREADS:-1}"
