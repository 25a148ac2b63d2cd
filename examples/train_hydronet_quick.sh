#!/usr/bin/env bash
# A short HydroNet training run on small crops (minutes on a laptop CPU), then its evaluation
# against the numerical solver. For a real model use the defaults and let it run for hours;
# `resume=true` continues a stopped run, `torchrun --nproc_per_node N -m fishsim train-hydronet`
# trains on N GPUs/processes. Further arguments are train-hydronet overrides
# (e.g. `examples/train_hydronet_quick.sh runs/q device=cuda lr=3e-4`).
set -euo pipefail
out=${1:-runs/hydronet-quick}
fishsim train-hydronet out_dir="$out" iterations=2000 pool.H=48 pool.W=96 pool.size=64 val_every=250 "${@:2}"
fishsim validate hydronet.model_file="$out/best.pt" out_dir="$out/validate"
