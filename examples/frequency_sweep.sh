#!/usr/bin/env bash
# The paper's Fig. 4 set-up in one batched run: five fish at 3-7 Hz for 1.2 s, then a video of
# the 5 Hz fish's pressure field and a ParaView series. Further arguments are simulate overrides:
# add fluid=hydronet to use the surrogate instead of the numerical fluid (the default).
set -euo pipefail
out=${1:-outputs/frequency_sweep}
fishsim simulate batch.frequency=[3,4,5,6,7] frames=120 out_dir="$out" "${@:2}"
fishsim render "$out/trajectory.h5" sample=2 stride=2 vtk=true out_dir="$out/render"
