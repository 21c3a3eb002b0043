# Shared start of the cuda_check_*.sh scripts (sourced, not run): DEV (cuda by default, cpu for a dry run), OUT
# (made), unbuffered Python; on a machine without the project installed, the wheels in .whl/ go into the
# interpreter's own environment first (that machine is thrown away after; in /tmp/site on PYTHONPATH, as until
# 2026-12-01, a process started with a PYTHONPATH of its own did not see them), the repository on PYTHONPATH; then
# the GPU, the host CPU and torch are printed.
set -o pipefail
DEV=${DEV:-cuda}
OUT=${OUT:-/tmp/gpu_out}; mkdir -p "$OUT"
export PYTHONUNBUFFERED=1
if [ -d .whl ] && [ "$DEV" = cuda ]; then
  python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir .whl/*.whl >/dev/null 2>&1 || exit 1
  export PYTHONPATH=$PWD
fi
nvidia-smi -L 2>/dev/null; lscpu | grep "Model name"
python3 -c "import torch;print('torch', torch.__version__, 'cuda', torch.cuda.is_available())"
