# Sourced by the tools/lent_gpu_*.sh scripts (repository root, START / TOTAL / OUT set): everything printed goes to
# $OUT/log.txt as well; elapsed / left / say time the call; wheels in .whl/ (packages the GPU image lacks) are
# installed to /tmp/site; the GPU, torch and the commit are printed.
mkdir -p "$OUT"
exec > >(tee -a "$OUT/log.txt") 2>&1
elapsed() { echo $(( $(date +%s) - START )); }
left() { echo $(( TOTAL - $(date +%s) + START )); }
say() { echo "== t=$(elapsed)s $*"; }

if compgen -G ".whl/*.whl" > /dev/null; then
    python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl
    export PYTHONPATH=/tmp/site:$PWD
else
    export PYTHONPATH=$PWD
fi
export PYTHONUNBUFFERED=1 OMP_WAIT_POLICY=PASSIVE
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader 2>/dev/null || echo "no nvidia-smi"
python3 -c "import torch, numpy; print('torch', torch.__version__, 'numpy', numpy.__version__, 'cuda', torch.cuda.is_available())"
git log --oneline -1 2>/dev/null || true
