#!/usr/bin/env bash
# The single lever runs of "Cost of learning" (benchmarks/README.md, issue 45), one at a time, one thread each,
# in a benchmark project folder (a copy of this repository's experiments.yaml; its data and runs land there):
#
#   mkdir -p /tmp/lc && cp experiments.yaml /tmp/lc/ && benchmarks/cost_levers.sh /tmp/lc [NAME ...]
#   python benchmarks/bench_learning_cost.py /tmp/lc      # -> benchmarks/results/learning-cost.json
#
# Each lever is its own experiment (cost-NAME), so running this again skips the levers that have a FINISHED run
# (train's own rule) and resumes a stopped one from its checkpoint. Every run stops at the first validation whose
# val.ratio.pos_l2 is <= 0.90 and validates every 500 pairs. About 7-10 min per run on one Zen 4 core.
# NAMEs (e.g. cost-conv3d-clip1): run only those levers. COST_SUFFIX (e.g. -xeon) is appended to every
# experiment's name: a session on another CPU kind keeps its runs (and its own reference) apart from the others'
# in the results file, which keys the prose's figures by experiment name. COST_SEED=N trains seed N instead of 0 (a
# replicate: the experiment's name gets -sN).
set -uo pipefail
project=${1:?usage: benchmarks/cost_levers.sh PROJECT_FOLDER [NAME ...]}
shift
only=" $* "
cd "$project"
export VTK_DEFAULT_OPENGL_WINDOW=${VTK_DEFAULT_OPENGL_WINDOW:-vtkEGLRenderWindow}
common=(--config "$PWD/experiments.yaml" -P personalized --set train.stop_at_ratio=0.90 --set train.val_every=25)
recipe=(--profile learning-cost --set train.lr=1e-3 --set train.warmup=0.05 --set train.batch_size=20
        --set model.dropout=0.2 --set train.schedule=cosine)
bronchopose=(bronchopose)  # the command run() trains with
run() {
    local name=$1; shift
    [[ "$only" == "  " || "$only" == *" $name "* ]] || return 0
    echo "=== $(date -u +%FT%TZ) $name: $*"
    local experiment=$name${COST_SEED:+-s$COST_SEED}${COST_SUFFIX:-} seed=(--seed "${COST_SEED:-0}")
    "${bronchopose[@]}" train "${common[@]}" --set "name=$experiment" "${seed[@]}" "$@" --resume 2>/dev/null \
        || "${bronchopose[@]}" train "${common[@]}" --set "name=$experiment" "${seed[@]}" "$@"
}
run cost-reference-today --profile bronchotrack-cpu -a convlstm -l ce            # the recipe before issue 45
run cost-base "${recipe[@]}" -a convlstm -l ce                                    # the chosen recipe (12,000-pair schedule)
run cost-span8k "${recipe[@]}" -a convlstm -l ce --set train.steps=400            # a schedule spanning 8,000 pairs
run cost-window5 "${recipe[@]}" -a convlstm -l ce --set data.window=5             # 4 windows of 5 pairs per batch
run cost-bf16 "${recipe[@]}" -a convlstm -l ce --set train.precision=bf16-mixed   # bf16 autocast
run cost-80 "${recipe[@]}" -a convlstm -l ce --set dataset.root=data/synthetic-cpu-lc-80 \
    --set dataset.generate.image_size=80                                          # 80² frames
run cost-conv3d "${recipe[@]}" -a conv3d -l ce --set train.steps=1000              # the 3-D-conv head, 20,000 pairs
run cost-conv3d-lr3e-4 "${recipe[@]}" -a conv3d -l ce --set train.steps=1000 --set train.lr=3e-4
# the 3-D-conv head's early instability (2026-11-29 on): a longer warm-up, gradient-norm clipping
run cost-conv3d-warm20 "${recipe[@]}" -a conv3d -l ce --set train.steps=1000 --set train.warmup=0.2
run cost-conv3d-clip1 "${recipe[@]}" -a conv3d -l ce --set train.steps=1000 --set train.grad_clip=1.0
# the 3-D-conv head's validation swings with its mode gap (eval-mode loss 3-4x the batch-statistics loss in the
# first thousands of pairs): 4 windows of 5 pairs per batch instead of 2 of 10 give its BatchNorm3d more windows
run cost-conv3d-window5 "${recipe[@]}" -a conv3d -l ce --set train.steps=1000 --set data.window=5
# the study's budget (10,000 pairs) with BatchNorm statistics fixed for the last half: the function evaluated is
# the function trained there (train.bn_freeze; docs/training.md, "Evaluation consistent with training")
run cost-conv3d-freeze50 "${recipe[@]}" -a conv3d -l ce --set train.steps=500 --set train.bn_freeze=0.5
# one cycle (train.schedule=onecycle, its rising phase OneCycleLR's default 30 %): at the recipe's peak rate, and at
# 3x it (one-cycle's premise: a short high peak that the annealing then settles)
# (the profile's tune space reaches warm-up 0, which a one-cycle refuses: a space of the rate alone for these runs)
onecycle=(--set train.schedule=onecycle --set train.warmup=0.3 --set 'tune.enqueue=[]'
          --set 'tune.space={train.lr: {type: float, low: 3.0e-4, high: 3.0e-3, log: true}}')
run cost-onecycle "${recipe[@]}" -a convlstm -l ce "${onecycle[@]}"
run cost-onecycle-lr3e-3 "${recipe[@]}" -a convlstm -l ce "${onecycle[@]}" --set train.lr=3e-3
# Diagnostic, not a platform option: the 3-D-conv head with its fusion unpadded (the paper's pads the 1x1 fusion
# convolution by one pixel, so at 96² 16 of the 5x5 positions its BatchNorms see are constant borders), patched in
# for this one run, at the study's budget
pad0() {
    python -c "import sys; import bronchocli.models.conv3d as m; f = m.fusion
m.fusion = lambda kernel, act, padding=None: f(kernel, act, padding=0)
from bronchocli.cli import main; sys.argv[0] = 'bronchopose'; main()" "$@"
}
bronchopose=(pad0)
run cost-conv3d-pad0 "${recipe[@]}" -a conv3d -l ce --set train.steps=500
bronchopose=(bronchopose)
