#!/usr/bin/env bash
# "What pretraining buys" (benchmarks/README.md; issue 56): BronchoTrack (ConvLSTM + MSE+CE) on the main job's
# dataset and recipe (96², 500 steps x 20 pairs = 10,000 pairs, lr 1e-3, 5 % warm-up, cosine; validation every
# 1,000 pairs, the whole budget trained so that the costs to 0.90 and 0.85 and the final test ratios are all
# read from one run), one thread, one run at a time, in a benchmark project folder:
#
#   mkdir -p /tmp/pt && cp experiments.yaml /tmp/pt/ && benchmarks/pretraining.sh /tmp/pt [NAME ...]
#   python benchmarks/bench_pretraining.py /tmp/pt     # -> benchmarks/results/pretraining.json
#
# Each run is its own experiment (pt-NAME-sSEED), so running this again skips what has a FINISHED run (train's own
# rule) and resumes a stopped one from its checkpoint: a session that ends mid-run loses at most a checkpoint
# interval. NAMEs: run only those arms/levers (the arms: every seed in PT_SEEDS, default "0 1 2"; the levers:
# LEVER_SEEDS, default "0"). Each lever is compared with the Lite0-ImageNet arm of the same seed.
set -uo pipefail
project=${1:?usage: benchmarks/pretraining.sh PROJECT_FOLDER [NAME ...]}
shift
only=" $* "
cd "$project"
export VTK_DEFAULT_OPENGL_WINDOW=${VTK_DEFAULT_OPENGL_WINDOW:-vtkEGLRenderWindow}
# the recipe, spelled out so that the default plan's own settings (ImageNet Lite0, frozen) do not leak in: the
# paper's B0 from random initialisation, 500 steps x 20 pairs, lr 1e-3, 5 % warm-up, cosine, dropout 0.2
common=(--config "$PWD/experiments.yaml" -P personalized -a convlstm -l ce --set train.val_every=50
        --set train.threads=1 --set model.backbone=efficientnet_b0 --set model.pretrained=null
        --set model.frozen_stages=0 --set model.dropout=0.2 --set train.steps=500 --set train.batch_size=20
        --set train.lr=1e-3 --set train.warmup=0.05 --set train.schedule=cosine --set train.precision=auto)
run() {  # run NAME SETTINGS...: every seed of $seeds (default PT_SEEDS, "0 1 2")
    local name=$1; shift
    [[ "$only" == "  " || "$only" == *" $name "* ]] || return 0
    local seed
    for seed in ${seeds:-${PT_SEEDS:-0 1 2}}; do
        local experiment=pt-$name-s$seed
        echo "=== $(date -u +%FT%TZ) $experiment: $*"
        bronchopose train "${common[@]}" --set "name=$experiment" --seed "$seed" "$@" --resume 2>/dev/null \
            || bronchopose train "${common[@]}" --set "name=$experiment" --seed "$seed" "$@"
    done
}
lite=(--set model.backbone=efficientnet_lite0)
imagenet=(--set model.pretrained=imagenet)
# the three arms: today's backbone from random initialisation, the lighter Lite0 from random and from ImageNet
run b0-random
run lite0-random "${lite[@]}"
run lite0-imagenet "${lite[@]}" "${imagenet[@]}"
# the levers pretrained features open, each against lite0-imagenet of its seed
levers=${LEVER_SEEDS:-0}
# frozen stages are computed once per dataset and read by every run after (training/frozen_features.py): a run's
# train.core_s is then the trainable part's alone, train.frozen_features_core_s the one-off computation
seeds=$levers run lite0-imagenet-frozen9 "${lite[@]}" "${imagenet[@]}" --set model.frozen_stages=9   # fixed features
seeds=$levers run lite0-imagenet-frozen9-lr3e-3 "${lite[@]}" "${imagenet[@]}" --set model.frozen_stages=9 \
    --set train.lr=3e-3                                                                                # the head alone: a higher rate
seeds=$levers run lite0-imagenet-frozen7 "${lite[@]}" "${imagenet[@]}" --set model.frozen_stages=7   # all but stage 7 + head
seeds=$levers run lite0-imagenet-frozen6 "${lite[@]}" "${imagenet[@]}" --set model.frozen_stages=6   # stem + 5 stages
seeds=$levers run lite0-imagenet-frozen4 "${lite[@]}" "${imagenet[@]}" --set model.frozen_stages=4   # stem + 3 stages
seeds=$levers run lite0-imagenet-blr0.1 "${lite[@]}" "${imagenet[@]}" --set train.backbone_lr=0.1   # backbone at lr/10
seeds=$levers run lite0-imagenet-64 "${lite[@]}" "${imagenet[@]}" --set dataset.root=data/synthetic-cpu-64 \
    --set dataset.generate.image_size=64                                                               # 64² frames
seeds=$levers run lite0-imagenet-128 "${lite[@]}" "${imagenet[@]}" --set dataset.root=data/synthetic-cpu-128 \
    --set dataset.generate.image_size=128                                                              # 128² frames
