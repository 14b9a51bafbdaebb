#!/usr/bin/env bash
# Bai 2022: the whole stack-train drl chain behind the shipped weights, one run after the other, with the
# wall time after each (README "Deep RL"). Usage: bash bench/drl_chain.sh [OUT]   (default runs/repro). Each run learns
# on a second thread while its world steps (stack-train drl --overlap, the default), so the chain uses both cores;
# every run is bounded by episodes, not time, so the chain is the same on any machine.
set -e
cd "$(dirname "$0")/.."
# stack-train from the active environment (make test / pip install -e .)
R=${1:-runs/repro}
A="--envs 32 --max-steps 250 --n-step 3 --target-every 100"
B="--walls 0 --time-penalty 0.01 --stall-steps 30 --eval-episodes 0"
t0=$(date +%s)
stack-train drl --stage 1 --episodes 3000 --eps-fraction 0.4 $A --eval-episodes 0 --no-progress --out $R/drl-s1; echo "s1 $(( $(date +%s) - t0 ))"
stack-train drl --stage 1 --init $R/drl-s1/drl.pt --episodes 2500 --stop-after 1561 --eps-start 0.1 --eps-end 0.02 --eps-fraction 0.5 --lr 5e-4 --seed 1 $A --eval-episodes 0 --no-progress --out $R/drl-s1b; echo "s1b $(( $(date +%s) - t0 ))"
stack-train drl --stage 1 --init $R/drl-s1b/drl.pt --episodes 4000 --eps-start 0.1 --eps-end 0.02 --eps-fraction 0.5 --lr 5e-4 --seed 5 $A $B --no-progress --out $R/drl-s1e; echo "s1e $(( $(date +%s) - t0 ))"
stack-train drl --stage 1 --init $R/drl-s1e/drl.pt --episodes 6000 --eps-start 0.05 --eps-end 0.01 --eps-fraction 0.3 --lr 2.5e-4 --seed 6 $A $B --no-progress --out $R/drl-s1f; echo "s1f $(( $(date +%s) - t0 ))"
stack-train drl --stage 2 --init $R/drl-s1f/best.pt --episodes 5000 --eps-start 0.3 --eps-end 0.02 --eps-fraction 0.4 --lr 2.5e-4 --seed 7 $A $B --no-progress --out $R/drl-s2b; echo "s2b $(( $(date +%s) - t0 ))"
C="--stage 3 --follow --eps-end 0.02 --eps-fraction 0.5 --lr 2.5e-4 --envs 32 --n-step 3 --target-every 100 --time-penalty 0.01 --stall-steps 30 --eval-episodes 100"
stack-train drl $C --init $R/drl-s2b/best.pt --eps-start 0.2 --seed 16 --max-steps 500 --episodes 6900 --collision-penalty 10 --no-progress --out $R/drl-s3j; echo "s3j $(( $(date +%s) - t0 ))"   # -> drl-chain.pt (README "Training time")
