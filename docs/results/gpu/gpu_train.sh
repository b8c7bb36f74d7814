#!/bin/bash
# Training-step check on the lent GPU (no Warp needed): ACT+SkillPlug paper shapes, then the cpu preset.
set -u
T0=$(date +%s); OUT=${OUT:-/tmp/out}; mkdir -p "$OUT"; exec > >(tee -a "$OUT/gpu_train.log") 2>&1
REPO=$PWD; el() { echo $(( $(date +%s) - T0 )); }
for f in .gl/*.deb; do dpkg -x $f /; done; ldconfig
EGLV=/usr/local/nvidia/share/glvnd/egl_vendor.d/10_nvidia.json; [ -f "$EGLV" ] && export __EGL_VENDOR_LIBRARY_FILENAMES=$EGLV
mkdir -p /tmp/site && tar -xJf .whl/tr/stage.tar.xz -C /tmp/site && echo "[$(el) s] unpacked"
export PYTHONPATH=/tmp/site/pin:/tmp/site/site:$REPO MUJOCO_GL=egl PYTHONUNBUFFERED=1 GLIBC_TUNABLES=glibc.malloc.hugetlb=1 TF_CPP_MIN_LOG_LEVEL=2
export JAX_COMPILATION_CACHE_DIR=/tmp/jaxcache JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS=1
nvidia-smi --query-gpu=name,memory.total,driver_version,clocks.sm --format=csv; grep -m1 "model name" /proc/cpuinfo; nproc
python3 -c "import jax, flax, optax; from skillplug_jax.train import loop; print('jax', jax.__version__, 'flax', flax.__version__, jax.devices())" || exit 4
echo "[$(el) s] START paper skillplug,act"
timeout -k 5 ${T1:-400} python3 -m benchmarks.bench_train --presets paper --policies skillplug,act --steps 30 \
  --pair-rounds 10 --infer-batches 1,64 --infer-calls 10 --out "$OUT/bench_train_paper_gpu.json"; echo "[$(el) s] END rc=$?"
echo "[$(el) s] START cpu preset"
timeout -k 5 ${T2:-90} python3 -m benchmarks.bench_train --presets cpu --policies act,skillplug --steps 100 \
  --pair-rounds 20 --infer-batches 1,64 --infer-calls 20 --out "$OUT/bench_train_cpu_gpu.json"; echo "[$(el) s] END rc=$?"
nvidia-smi --query-gpu=name,memory.used,clocks.sm,temperature.gpu --format=csv; ls -la "$OUT"
