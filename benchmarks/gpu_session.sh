#!/usr/bin/env bash
# The GPU figures (docs/experiments.md, "On one GPU"), on a machine with one CUDA GPU, its own
# torch and no network:
#
#   bash benchmarks/gpu_session.sh STEP [STEP ...]
#
# Steps, each timed:
#   info     the GPU, torch, and whether torchvision's ImageNet ResNet50 file is in torch's cache
#   tests    pytest -m gpu (the CUDA code paths against the CPU ones)
#   prepare  table building at the paper's encoder size (ResNet50 at 256 px, ResNet18
#            recognizer) on a stand-in dataset: bare forward and `prepare`, images/s
#   train    one 300,000-episode IBE-MAP run at the paper's sizes on CUDA (stand-in table)
#   runs     the paper preset's 15 training runs (3 methods x 5 seeds, 300,000 episodes each, all
#            side by side) on a stand-in table (bench_ablation.py): the ablation's training part
#            without its world and tables; resumes when run again
#   ablate   the paper preset's ablation (3 methods x 5 seeds, one recognizer, no sweeps):
#            world, recognizer, tables and the 15 runs; resumes when run again in the same place
#
# Wheels in .whl/ (packages the machine lacks) are installed into /tmp/site first. Caches and
# results go to runs/gpu/ (ignored by git). ABLATE_SECONDS and RUNS_SECONDS bound the ablate and
# runs steps (default 540 each; RUNS_WORKERS, default 15, sets how many runs train side by side);
# a bounded step stops with SIGINT and resumes from its checkpoints when run again. A lent
# machine kills a command outright after its limit (600 s), which would lose the step's record
# of its time: CALL_SECONDS (default 570) bounds the whole invocation, so a bounded step gets
# at most what is left of it (less 30 s to stop and write), and is skipped, saying so, when
# under a minute is left.
set -uo pipefail
cd "$(dirname "$0")/.."
export PYTHONUNBUFFERED=1 PYTHONPATH="$PWD:/tmp/site${PYTHONPATH:+:$PYTHONPATH}"
export UEVAVD_CACHE="$PWD/runs/gpu/cache"
mkdir -p runs/gpu
if compgen -G ".whl/*.whl" >/dev/null && [ ! -f /tmp/site/.done ]; then
  python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl \
    && touch /tmp/site/.done || { echo "gpu_session: installing .whl/ failed"; exit 2; }
fi
uevavd() { python3 -c 'import sys; from uevavd.cli import main; sys.exit(main())' "$@"; }
stamp() { echo "=== $1: $(( $(date +%s) - T0 )) s"; }
START=$(date +%s)
# bound STEP SECONDS: the seconds a bounded step may run, SECONDS or what is left of this call
bound() {
  local left=$(( ${CALL_SECONDS:-570} - ($(date +%s) - START) - 30 ))
  local want=$2
  (( left < want )) && want=$left
  if (( want < 60 )); then
    echo "gpu_session: $1 skipped: ${left} s left of this call's ${CALL_SECONDS:-570} s; run it again in a new call" >&2
    return 1
  fi
  echo "$want"
}

for step in "$@"; do
  T0=$(date +%s)
  echo "=== $step (started $(date -u +%H:%M:%S))"
  case "$step" in
    info)
      nvidia-smi --query-gpu=name,memory.total,driver_version,clocks.sm,clocks.max.sm --format=csv
      python3 -c 'import torch, torchvision, os; print("torch", torch.__version__, "torchvision", torchvision.__version__,
"cuda", torch.version.cuda, torch.cuda.get_device_name(0), "cpus", os.cpu_count())'
      python3 -c 'from uevavd.perception.weights import imagenet_path
try: print("ImageNet ResNet50:", imagenet_path("resnet50"))
except Exception as e: print("ImageNet ResNet50: absent:", str(e)[:100])'
      ;;
    tests)
      python3 -m pytest -m gpu -p no:cacheprovider -n 4 -q tests/test_gpu.py tests/env/test_batched.py
      ;;
    prepare)
      python3 benchmarks/bench_prepare.py --device cuda --config resnet50:256 --scenes 8 --workers 16 \
        --threads 16 --batch 256 --repeats 3 --profile "${OUT:-runs/gpu}/prepare_profile.txt"
      ;;
    train)
      python3 benchmarks/bench_train.py --device cuda --methods ibe_map --episodes 300000 \
        --epoch-episodes 25000 --threads 1 --sb3-seconds 20 --progress
      ;;
    runs)
      secs=$(bound runs "${RUNS_SECONDS:-540}") || continue
      timeout -k 20 -s INT "$secs" python3 benchmarks/bench_ablation.py --device cuda \
        --workers "${RUNS_WORKERS:-15}" --out runs/gpu/bench_ablation
      echo "runs exit $?"
      ;;
    ablate)
      preset=paper
      if ! python3 -c 'from uevavd.perception.weights import imagenet_path; imagenet_path("resnet50")' 2>/dev/null; then
        # no ImageNet file on this machine: the same preset with a random-weight ResNet50, for
        # timing only (the work per image does not depend on the weights); never for results
        preset=runs/gpu/paper_random_encoder.toml
        python3 - "$preset" <<'EOF'
import sys, tomli_w
from uevavd.presets import load_preset
p = load_preset("paper")
p["overrides"]["perception.encoder.weights"] = "random"
p["ablation"].update(recognizers=1, sweeps={})
open(sys.argv[1], "wb").write(tomli_w.dumps(p).encode())
EOF
        echo "no ImageNet ResNet50 here: timing with $preset (random encoder weights)"
      fi
      secs=$(bound ablate "${ABLATE_SECONDS:-540}") || continue
      timeout -k 20 -s INT "$secs" \
        python3 -c 'import sys; from uevavd.cli import main; sys.exit(main())' ablate --preset "$preset" \
        --seeds 5 --recognizers 1 --device cuda --workers 16 --out runs/gpu/ablation
      echo "ablate exit $?"
      python3 - <<'EOF'
import json, pathlib
runs = sorted(pathlib.Path("runs/gpu/ablation").glob("runs/**/evals.jsonl"))
for f in runs:
    rows = [json.loads(l) for l in f.read_text().splitlines() if l.strip()]
    last = rows[-1] if rows else {}
    print(f.parent.relative_to("runs/gpu/ablation"), "epochs", last.get("epoch"), "episodes", last.get("episodes"),
          "training s", round(last.get("wall_s", 0)), "return", last.get("mean_return"))
EOF
      ;;
    *) echo "unknown step $step"; exit 2 ;;
  esac
  stamp "$step"
done
