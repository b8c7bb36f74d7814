#!/bin/bash
# GPU check of SkillPlug-JAX's MJX-Warp path on a lent device (one NVIDIA H200), one call.
# Run from the repository root on the device, after the earlier call(s) copied .whl/p1/part.00 to /tmp/w,
# with .whl/p2, .whl/run and .gl carried:  bash .whl/run/device_check.sh
# DEADLINE (s): wall-clock budget of the whole script; each step's timeout is cut to what is left.
set -u
T0=$(date +%s)
DEADLINE=${DEADLINE:-480}
OUT=${OUT:-/tmp/out}
mkdir -p "$OUT"
LOG=$OUT/device_check.log
exec > >(tee -a "$LOG") 2>&1
REPO=$PWD
PY=${PY:-python3}   # the device's python3 (/opt/torch/.venv); a local dry run passes another
el() { echo $(( $(date +%s) - T0 )); }
# tmo WANT: WANT seconds, or what is left before the deadline less 15 s; 0 when under 25 s are left
tmo() { local w=$1 l=$(( DEADLINE - $(date +%s) + T0 - 15 )); [ "$l" -lt "$w" ] && w=$l; [ "$w" -lt 25 ] && w=0; echo "$w"; }
step() {  # step NAME WANT_S CMD...: run CMD under a timeout; record rc and seconds
  local name=$1 want=$2; shift 2
  local t; t=$(tmo "$want")
  if [ "$t" -eq 0 ]; then echo "=== [$(el) s] SKIP $name: no time left"; echo "$name skipped (no time)" >>/tmp/steps.txt; return 0; fi
  echo "=== [$(el) s] START $name (timeout ${t}s): $*"
  local s; s=$(date +%s)
  timeout -k 5 "$t" "$@"
  local rc=$?
  echo "=== [$(el) s] END $name rc=$rc after $(( $(date +%s) - s )) s"
  echo "$name rc=$rc wall_s=$(( $(date +%s) - s )) timeout_s=$t" >>/tmp/steps.txt
}

echo "=== [$(el) s] setup"
mkdir -p /tmp/w && cp .whl/p2/part.01 /tmp/w/ 2>/dev/null
ls -la /tmp/w
cd /tmp/w && cat part.00 part.01 > payload.tar && sha256sum -c "$REPO/.whl/run/payload.sha256" || {
  echo "FATAL: payload incomplete (was the machine replaced between calls?)"; exit 3; }
rm -f part.00 part.01
tar -xf payload.tar && rm payload.tar
cd "$REPO"
"$PY" - <<'EOF' || { echo "FATAL: unpacking failed"; exit 4; }
import lzma, shutil, tarfile, time
t = time.time()
with tarfile.open("/tmp/w/stage.tar.xz", "r:xz") as tf:
    tf.extractall("/tmp/site")
with lzma.open("/tmp/w/warp.so.xz") as src, open("/tmp/site/site/warp/bin/warp.so", "wb") as dst:
    shutil.copyfileobj(src, dst, 16 << 20)
print(f"unpacked in {time.time() - t:.1f} s")
EOF
rm -f /tmp/w/warp.so.xz /tmp/w/stage.tar.xz

# OpenGL/EGL loaders for MuJoCo's C renderer (README of the device tool), and NVIDIA's EGL vendor file
if [ -z "${DRY:-}" ]; then for f in .gl/*.deb; do dpkg -x "$f" /; done; ldconfig; fi
EGLV=/usr/local/nvidia/share/glvnd/egl_vendor.d/10_nvidia.json
[ -f "$EGLV" ] && export __EGL_VENDOR_LIBRARY_FILENAMES=$EGLV
ls /usr/local/nvidia/share/glvnd/egl_vendor.d/ 2>&1; ldconfig -p | grep -E "libEGL(_nvidia)?\.so" | head -4

export MUJOCO_GL=egl PYTHONUNBUFFERED=1 GLIBC_TUNABLES=glibc.malloc.hugetlb=1 TF_CPP_MIN_LOG_LEVEL=2

echo "=== [$(el) s] versions"
nvidia-smi
nvidia-smi --query-gpu=name,memory.total,driver_version,clocks.sm,clocks.mem --format=csv
nproc; grep -m1 "model name" /proc/cpuinfo; free -g | head -2
"$PY" -m pip list 2>/dev/null | grep -iE "^(jax|jaxlib|jax-cuda13-plugin|jax-cuda13-pjrt|flax|optax|orbax-checkpoint|chex|etils|tensorstore|numpy|scipy|protobuf|ml_dtypes|absl-py|msgpack|treescope|pillow) "

# Our pinned flax/optax/orbax/chex (carried, /tmp/site/pin) unless they fail on this jax; else the device's own.
PROBE='import envs, jax, mujoco, warp, flax, optax, orbax.checkpoint, chex, brax, tensorflow_datasets, tensorboardX
import benchmarks.bench_envs, benchmarks.bench_train, benchmarks.bench_eval, skillplug_jax.cli
from mujoco import mjx
import importlib.metadata as md
print("python", __import__("sys").version.split()[0], "| jax", jax.__version__, "| jaxlib", md.version("jaxlib"),
      "| flax", flax.__version__, "| optax", optax.__version__, "| orbax-checkpoint", md.version("orbax-checkpoint"),
      "| chex", chex.__version__, "| mujoco", mujoco.__version__, "| mujoco-mjx", md.version("mujoco-mjx"),
      "| warp", warp.__version__, "| brax", md.version("brax"), "| numpy", __import__("numpy").__version__)
print("jax devices:", jax.devices(), "| backend:", jax.default_backend())
print(float(jax.jit(lambda x: (x @ x).sum())(jax.numpy.ones((256, 256)))))
warp.init(); print("warp cuda devices:", warp.get_cuda_devices(), "| cpu (warp-clang) available:", warp.is_cpu_available())'
export PYTHONPATH=/tmp/site/pin:/tmp/site/site:$REPO
if timeout 180 "$PY" -c "$PROBE"; then PINNED=yes; else
  echo "!!! pinned flax/optax/orbax/chex failed on this jax: falling back to the device's own"
  PINNED=no; export PYTHONPATH=/tmp/site/site:$REPO
  timeout 180 "$PY" -c "$PROBE" || echo "!!! probe failed with the device's packages too"
fi
echo "pinned_flax_optax_orbax_chex=$PINNED" | tee -a /tmp/steps.txt
[ -n "${STOP_AFTER_PROBE:-}" ] && exit 0

# 1. Environment throughput on both backends; MJX-Warp on the GPU (the first row includes Warp's first-ever compile).
step envs_state 170 "$PY" -m benchmarks.bench_envs --tasks jujube_pick,cuplid_cover --batches 64,1024,4096 \
  --render state --steps 10 --warp-steps 10 --eval-tasks none --out "$OUT/bench_envs_state_gpu.json"
# 2. Scripted experts on MJX-Warp on the GPU (compare docs/results/experts/experts_mjx_warp_cpu.json):
#    skillplug experts' own cmd_experts, a task at a time, the JSON rewritten after each task
step experts 150 "$PY" .whl/run/experts_by_task.py --taskset discoverse7 --episodes 100 --batch 100 \
  --backend mjx-warp --json "$OUT/experts_mjx_warp_gpu.json"
# 3. Train step (paper shapes, images; the cpu preset at the end if time is left), no Warp involved. JAX's persistent cache lets
#    the paired-rounds process reuse the separate runs' compiled steps.
export JAX_COMPILATION_CACHE_DIR=/tmp/jaxcache JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS=1
step train 170 "$PY" -m benchmarks.bench_train --presets paper --policies act,skillplug --steps 50 \
  --pair-rounds 20 --infer-batches 1,64 --infer-calls 20 --out "$OUT/bench_train_gpu.json"
unset JAX_COMPILATION_CACHE_DIR JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS
# 1b. Cameras: Warp's ray-cast renderer on the GPU; MuJoCo's C renderer through NVIDIA's EGL
step envs_cameras 80 "$PY" -m benchmarks.bench_envs --tasks jujube_pick --batches 64,1024 --render cameras \
  --steps 10 --warp-steps 10 --warp-render-batches all --eval-tasks none --out "$OUT/bench_envs_cameras_gpu.json"
# 4. Closed-loop evaluation with a random-weights policy on MJX-Warp, if time is left
step eval 150 "$PY" -m benchmarks.bench_eval --backend mjx-warp --presets quick --policies act,skillplug \
  --batches 64,1024 --steps 40 --repeats 2 --out "$OUT/bench_eval_mjx_warp_gpu.json"

# 3b. The cpu preset's train step, if time is left
export JAX_COMPILATION_CACHE_DIR=/tmp/jaxcache JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS=1
step train_cpu_preset 100 "$PY" -m benchmarks.bench_train --presets cpu --policies act,skillplug --steps 100 \
  --pair-rounds 30 --infer-batches 1,64 --infer-calls 20 --out "$OUT/bench_train_cpu_preset_gpu.json"
unset JAX_COMPILATION_CACHE_DIR JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS

echo "=== [$(el) s] done"; cat /tmp/steps.txt
nvidia-smi --query-gpu=name,memory.used,clocks.sm,temperature.gpu --format=csv
ls -la "$OUT"
