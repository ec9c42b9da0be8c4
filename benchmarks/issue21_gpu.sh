#!/bin/bash
# Issue 21's direct box experiment by MCX on the GPU machine, in the repository's root, with
# .gpu21 carried (made here by `benchmarks/issue21_mcx.py prepare --experiments direct` and the pip
# download that prepare prints).  Usage there: bash benchmarks/issue21_gpu.sh SECONDS SEED
# Writes $OUT/d_p<k>.npz (one per 2e9 photons), $OUT/mcx_box_n140_gpu.csv and $OUT/log.txt.
set -u
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site \
    .gpu21/whl/*.whl || exit 3
nvidia-smi --query-gpu=name,memory.total --format=csv,noheader; nproc  # (before OMP_NUM_THREADS, which nproc obeys)
export PYTHONPATH=/tmp/site:. PYTHONUNBUFFERED=1
# one thread per imaging worker, not 16 workers each with a 16-thread BLAS.  With this and the faster
# hand-over (mcx_reference.run_chunk_raw) a batch's imaging went from 16-17 s to 10-11 s on the H100
# machine; the two changes were measured together, not apart.
export OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 MKL_NUM_THREADS=1
python3 -c "import numpy, pmcx; print('numpy', numpy.__version__, 'pmcx', pmcx.__file__)" || exit 4
python3 benchmarks/issue21_mcx.py transport --photons 1.2e10 --split 2e9 --seconds "${1:-380}" \
    --seed "${2:-35000}" --out "$OUT/d.npz" > "$OUT/log.txt" 2>&1
grep "issue21_mcx\|direct:" "$OUT/log.txt" | tail -30; tail -5 "$OUT/log.txt"
ls -la "$OUT"
