#!/usr/bin/env bash
# Rebuilds the demo model from nothing, on 2 CPU cores (89 minutes on the AVX-512 EPYC that
# made it: 6.9 generation, 9.3 pretraining, 72.8 training; a demo of 16,000 steps took 71 there,
# 81 on Xeons and about 2.7 hours on an AVX2-only EPYC, so this one fits the 90 minutes only on
# a CPU as fast as that EPYC; parq-train --minutes 90 holds a slower one to the 90 with fewer
# steps and a weaker model: docs/demo-experiments.md, "held to 90 minutes"), into
# work/parq-demo; compare it with models/parq-demo with benchmarks/tradeoff.py --model.
# Needs: pip install -e ".[export,test]".  Seeds: training scenes 1000, validation 2000 and
# 2001, held-out (reported numbers) 3000, 5000 and 6000, sample scene 4000; training seed 0.
set -euo pipefail
cd "$(dirname "$0")/../.."
parq-synth data/val --scenes 40 --seed 2000 --frames 60 --width 160 --height 120 --jobs 2 --quiet
parq-synth data/val2 --scenes 120 --seed 2001 --frames 60 --width 160 --height 120 --jobs 2 --quiet
# generates its 1600 training scenes of 30 frames into data/train1600, then trains (the demo
# configuration names point sampling as its resize filter, so the card it exports to does too)
# (--dropout 0.1 and --steps 19000, also the defaults, written out: the authors' training
# dropout on the decoder layer's residual branches and FFN, and the steps that fill the 90
# minutes; docs/demo-experiments.md, "The authors' training dropout" and "A longer schedule
# inside the 90 minutes")
parq-train work/demo.pt --seed 0 --data data/train1600 --scenes 1600 --frames 30 --jobs 2 \
    --dropout 0.1 --steps 19000
# ranks the learned queries (and chooses a post-processing for 2 x 32) on the 40 scenes of
# seed 2000, as the shipped card's query ranking was made
python -m parq_train.tune work/demo.pt --data data/val -o work/demo-ranked.pt
parq-export work/demo-ranked.pt -o work/parq-demo-ranked --force
# chooses the post-processing for 2 iterations x 64 queries with mirror runs, the card's run
# setting, on all 160 validation scenes, as the highest F1@0.25 among the settings whose F1@0.5
# is at least 0.35 (a floor set before the run: docs/demo-experiments.md, "Chosen for the
# goal"): for the shipped weights no region, ray fusion, ratio 30, then scene NMS 0.05, then
# the floor prior for chairs, tables, cabinets, trash bins, sofas and bathtubs at weight 10,
# then labels by vote, then the matching IoU 0.01, then threshold 0.75 and support 4 runs
# chosen again together (13 minutes on a 2-core AVX-512 EPYC, 22 on the AMX Xeon); the tuning
# of a model folder keeps its query ranking and writes a new folder
rm -rf work/parq-demo
python -m parq_train.tune work/parq-demo-ranked --data data/val data/val2 --queries 64 --mirror \
    --min-f1-50 0.35 -o work/parq-demo
