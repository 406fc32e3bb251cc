#!/usr/bin/env bash
# Rebuild the artefacts shipped in the repository, from a committed, clean tree: each records the
# commit it was made from (provenance), so each stage refuses to run on uncommitted changes.
# Run the stages in order and commit what each writes before the next:
#
#   bash scripts/make_artefacts.sh models    # rl/models/error_model_clear_tank_{480,640}.json
#   bash scripts/make_artefacts.sh models_ar1  # rl/models/error_model_clear_tank_480_ar1_refit.json (with memory,
#                                              # the current detector; the realistic recipe trains on it)
#   bash scripts/make_artefacts.sh policy    # rl/policies/error_model_ppo/ (DAgger + PPO, the option), docs/results/training_curve.png
#   bash scripts/make_artefacts.sh realistic # `rl train --recipe shipped --seed SEED` (default 0) from
#                                            # scratch into $WORK; with SHIP=1 (or --ship) it replaces
#                                            # rl/policies/realistic_ppo/ (the shipped policy) and
#                                            # docs/results/training_curve_realistic.png
#   bash scripts/make_artefacts.sh scratch   # trains PPO from scratch on the true pose into $WORK; with SHIP=1
#                                            # it replaces rl/policies/scratch_error_model_ppo/ (the policy
#                                            # shipped before realistic_ppo) and docs/results/training_curve_scratch.png
#   bash scripts/make_artefacts.sh figures   # docs/results/ (evaluation summaries and figures of the shipped policy)
#   bash scripts/make_artefacts.sh onnx      # rl/policies/realistic_ppo/policy.onnx + policy.json: the shipped
#                                            # policy exported (`rl export`), what `rl node` and `rl replay` load
#
# Seeds and data: datasets `datasets synth --n 2500 --water clear_tank --seed 0` at 480 and 640 px
# (their SHA-256 is recorded in each error model); the error model with memory from the PID's
# docking sequences `rl trajectories --episodes 30 --seed 0` rendered at 480 px, clear tank;
# training `configs/dagger.toml` (seed 0); training `configs/scratch/stage1.toml` then
# `configs/scratch/stage2.toml` from its best/ (seed SEED, default 1: the
# seed shipped, recorded in rl/policies/scratch_error_model_ppo/provenance.json);
# the shipped recipe `rl train --recipe shipped` (configs/recipes/shipped.toml: one stage,
# configs/realistic/policy.toml) from scratch, seed SEED (default 0: the seed shipped, recorded
# in rl/policies/realistic_ppo/ and in the docking page), numerics pinned (the same weights on
# any x86-64 CPU with AVX2 and FMA: uwdock.dockcore.numerics);
# evaluations on episode seeds 1000-1099.
# WORK (default /tmp/uwdock-artefacts) holds the datasets, the run folder and the evaluation
# folders; an interrupted stage resumes there.
set -euo pipefail
cd "$(dirname "$0")/.."
BIN=${VENV:-.venv}/bin
WORK=${WORK:-/tmp/uwdock-artefacts}
DAGGER=rl/policies/error_model_ppo      # the DAgger + PPO option
POLICY=rl/policies/realistic_ppo  # the shipped policy: PPO from scratch, realistic navigation
SCRATCH=rl/policies/scratch_error_model_ppo  # the policy shipped before it (true pose)
RESULTS=docs/results

say() { printf '[artefacts] %s\n' "$*"; }
die() { printf '[artefacts] error: %s\n' "$*" >&2; exit 1; }

[ -x "$BIN/rl" ] || die "no $BIN/rl: run scripts/setup.sh first"
[ -z "$(git status --porcelain --untracked-files=no)" ] \
  || die "the tree has uncommitted changes: commit them first (artefacts record their commit)"
mkdir -p "$WORK"

# Each stage makes everything in $WORK first and copies it into the tree last, so every step
# runs (and records its provenance) on the clean tree.

models() {
  local w
  for w in 480 640; do
    say "error model at $w px: 2,500 rendered frames, clear tank, seed 0"
    "$BIN/datasets" synth --n 2500 --width "$w" --water clear_tank --seed 0 --workers 2 \
      --out "$WORK/synth_clear_$w"
    "$BIN/rl" fit-error-model "$WORK/synth_clear_$w" --out "$WORK/error_model_clear_tank_$w.json"
  done
  cp "$WORK"/error_model_clear_tank_{480,640}.json rl/models/
}

# The error model with memory, fitted with the current detector, as ..._ar1_refit.json: the
# shipped policy's ..._ar1.json (fitted at 101f185 with the detector of then) stays as it was.
models_ar1() {
  local w=480 seq=$WORK/seq480_clear
  say "error model with memory at $w px: 30 PID docking sequences (seed 0), rendered, clear tank"
  if [ ! -f "$WORK/traj/poses.csv" ]; then
    rm -rf "$WORK/traj"
    "$BIN/rl" trajectories --out "$WORK/traj" --episodes 30 --seed 0 \
      --error-model rl/models/error_model_clear_tank_480.json
  fi
  "$BIN/datasets" render --poses "$WORK/traj/poses.csv" --water clear_tank --width "$w" \
    --workers 2 --out "$seq"
  "$BIN/rl" fit-error-model "$seq" --out "$WORK/error_model_clear_tank_${w}_ar1.json"
  cp "$WORK/error_model_clear_tank_${w}_ar1.json" "rl/models/error_model_clear_tank_${w}_ar1_refit.json"
}

# train CONFIG RUN [rl train flags]: train CONFIG into RUN, or resume it (a finished run is kept)
train() {
  local config=$1 run=$2
  shift 2
  say "training $config into $run"
  if [ -f "$run/config.toml" ]; then
    "$BIN/rl" train --out "$run" --resume
  else
    "$BIN/rl" train --config "$config" "$@" --out "$run"
  fi
}

# ship RUN DEST CURVE: copy RUN's best/ policy (model.json + weights.npz, data only) and its records
# into DEST, its curve to $RESULTS/CURVE; DEST/checksums.sha256 holds the SHA-256 of the policy
# files (`sha256sum -c checksums.sha256` in DEST checks the shipped weights)
ship() {
  local run=$1 dest=$2 curve=$3
  say "shipping best/ (the best evaluated checkpoint) into $dest"
  mkdir -p "$dest"
  rm -f "$dest/policy.zip" "$dest/vecnormalize.pkl"  # the pickled format is not shipped
  cp "$run/best/model.json" "$run/best/weights.npz" "$dest/"
  (cd "$run/best" && sha256sum model.json weights.npz) >"$dest/checksums.sha256"
  (cd "$dest" && sha256sum -c --quiet checksums.sha256) \
    || die "the files copied into $dest differ from $run/best/"
  cp "$run/config.toml" "$run/provenance.json" "$run/eval_history.jsonl" "$dest/"
  rm -f "$dest/imitation.json" "$dest/resume_log.jsonl"
  [ ! -f "$run/imitation.json" ] || cp "$run/imitation.json" "$dest/"  # the DAgger warm start
  [ ! -f "$run/resume_log.jsonl" ] || cp "$run/resume_log.jsonl" "$dest/"  # interruptions, commits
  cp "$run/eval_history.png" "$RESULTS/$curve"
}

policy() {
  train configs/dagger.toml "$WORK/run_error_model_ppo"
  ship "$WORK/run_error_model_ppo" "$DAGGER" training_curve.png
}

# two_stages SEED STAGE1 STAGE2 RUN SUFFIX DEST CURVE: train STAGE1 into RUN, then STAGE2 from its
# best/ into RUN_SUFFIX; with SHIP=1 copy stage 2's best/ into DEST and stage 1's policy and
# records into DEST/stage1/ (further arguments go to both `rl train` calls). With STAGE1_RUN
# naming a kept stage-1 policy folder (model.json, weights.npz, checksums.sha256,
# provenance.json, eval_history.jsonl: e.g. rl/policies/realistic_ppo/stage1), stage 1 is not
# trained: stage 2 starts from it, checked against its checksums first.
two_stages() {
  local seed=$1 stage1=$2 stage2=$3 w=$4 suffix=$5 dest=$6 curve=$7 s1 s1_policy
  shift 7
  if [ -n "${STAGE1_RUN:-}" ]; then
    s1=$STAGE1_RUN s1_policy=$STAGE1_RUN
    [ -f "$s1/checksums.sha256" ] && [ -f "$s1/provenance.json" ] \
      || die "STAGE1_RUN=$s1: not a kept stage 1 (checksums.sha256, provenance.json)"
    (cd "$s1" && sha256sum -c --quiet checksums.sha256) \
      || die "STAGE1_RUN=$s1: its policy differs from its checksums.sha256"
    say "stage 1: the kept policy $s1 (not trained again)"
  else
    s1=$w s1_policy=$w/best
    train "$stage1" "$w" --seed "$seed" "$@"
  fi
  train "$stage2" "${w}_$suffix" --seed "$seed" --init-policy "$s1_policy" "$@"
  if [ "$SHIP" != 1 ]; then
    say "trained ${w}_$suffix; $dest is left as it is (SHIP=1 or --ship replaces it)"
    (cd "${w}_$suffix/best" && sha256sum model.json weights.npz)
    return
  fi
  ship "${w}_$suffix" "$dest" "$curve"
  if [ "$(cd "$s1_policy" && pwd -P)" != "$(mkdir -p "$dest/stage1" && cd "$dest/stage1" && pwd -P)" ]; then
    cp "$s1_policy/model.json" "$s1_policy/weights.npz" "$s1/config.toml" "$s1/provenance.json" \
      "$s1/eval_history.jsonl" "$dest/stage1/"  # stage 1 beside stage 2, as shipped
    (cd "$dest/stage1" && sha256sum model.json weights.npz) >"$dest/stage1/checksums.sha256"
  fi
}

scratch() {  # the true-pose recipe: PPO from scratch, then its best/ at collision penalty 30
  local seed=${SEED:-1}
  two_stages "$seed" configs/scratch/stage1.toml \
    configs/scratch/stage2.toml \
    "$WORK/run_scratch_error_model_precision_ppo_s$seed" soft "$SCRATCH" training_curve_scratch.png
}

# The shipped recipe (configs/recipes/shipped.toml): DAgger from the PID, the critic alone for
# 60k steps, then PPO to 600k steps, in one stage (configs/realistic/policy.toml says what it
# trains on), from scratch with the one command a user runs. Its folder is the policy:
# model.json, weights.npz and checksums.sha256 at its top, the run in runs/policy/.
realistic() {
  local seed=${SEED:-0} run
  run=$WORK/realistic_s$seed
  say "training the shipped recipe from scratch, seed $seed, into $run"
  "$BIN/rl" train --recipe shipped --seed "$seed" --out "$run"
  (cd "$run" && sha256sum -c --quiet checksums.sha256) || die "$run: its policy differs from its checksums"
  if [ "$SHIP" != 1 ]; then
    say "trained $run; $POLICY is left as it is (SHIP=1 or --ship replaces it)"
    cat "$run/checksums.sha256"
    return
  fi
  say "shipping $run into $POLICY"
  rm -rf "${POLICY:?}/stage1"  # a two-stage policy's stage 1: the recipe has one stage
  rm -f "$POLICY"/{model.json,weights.npz,checksums.sha256,config.toml,provenance.json} \
    "$POLICY"/{eval_history.jsonl,recipe.json,imitation.json,resume_log.jsonl} \
    "$POLICY"/{policy.onnx,policy.json,onnx_checksums.sha256}  # the export of the one before
  mkdir -p "$POLICY"
  cp "$run"/{model.json,weights.npz,checksums.sha256,config.toml,provenance.json} \
    "$run"/{eval_history.jsonl,recipe.json} "$POLICY/"
  [ ! -f "$run/runs/policy/imitation.json" ] || cp "$run/runs/policy/imitation.json" "$POLICY/"
  (cd "$POLICY" && sha256sum -c --quiet checksums.sha256) || die "the files copied into $POLICY differ"
  cp "$run/runs/policy/eval_history.png" "$RESULTS/training_curve_realistic.png"
  say "now: bash scripts/make_artefacts.sh onnx (the vehicle node loads the export)"
}

EM=rl/models/error_model_clear_tank_480_ar1_refit.json  # the error model the shipped policy trained on

evaluate() {  # evaluate NAME ARGS...: rl eval into $WORK/NAME, unless a finished one is there
  local name=$1
  shift
  if [ -f "$WORK/$name/summary.json" ]; then
    say "$name: already evaluated (remove $WORK/$name to run it again)"
    return
  fi
  rm -rf "${WORK:?}/$name"
  "$BIN/rl" eval --seed 1000 --workers 2 --out "$WORK/$name" "$@"
}

figures() {
  say "100 camera episodes (seeds 1000-1099), the graded stress tables, and the other sources"
  evaluate eval_camera --policy "$POLICY" --obs camera --episodes 100 --videos 0 \
    --stress --stress-episodes 20
  evaluate eval_error_model --policy "$POLICY" --obs error-model --error-model "$EM" \
    --episodes 100 --videos ""
  evaluate eval_proxy --policy "$POLICY" --obs proxy --episodes 100 --videos ""
  evaluate eval_pid_error_model --policy pid --env-from "$POLICY" --obs error-model \
    --error-model "$EM" --episodes 100 --videos ""
  local e=$WORK/eval_camera k
  k=$("$BIN/python" -c 'import csv, sys
rows = list(csv.DictReader(open(sys.argv[1])))
bad = [r["episode"] for r in rows if r["success_strict"] not in ("True", "1", "true")]
print(bad[0] if bad else "")' "$e/episodes.csv")
  if [ -n "$k" ]; then
    say "filming the first failed camera episode ($k, seed $((1000 + k)))"
    rm -rf "${WORK:?}/failure_ep$k"
    "$BIN/rl" eval --policy "$POLICY" --obs camera --episodes 1 --seed $((1000 + k)) --videos 0 \
      --out "$WORK/failure_ep$k"
  fi
  cp "$e/summary.json" "$RESULTS/camera_eval_summary.json"
  cp "$e/trajectories_top.png" "$e/traces_ep0.png" "$e/camera_ep0_frames.jpg" "$RESULTS/"
  "$BIN/python" - "$e/summary.json" "$RESULTS/stress_camera.json" <<'PY'
import json, sys
s = json.load(open(sys.argv[1]))
keys = ("policy", "obs_source", "stress", "config", "provenance")
out = {"seed": 1000, "episodes_per_row": 20, **{k: s[k] for k in keys}}
json.dump(out, open(sys.argv[2], "w"), indent=2)
PY
  rm -f "$RESULTS"/failure_ep*
  if [ -n "$k" ]; then
    cp "$WORK/failure_ep$k/camera_ep0_frames.jpg" "$RESULTS/failure_ep${k}_frames.jpg"
    cp "$WORK/failure_ep$k/traces_ep0.png" "$RESULTS/failure_ep${k}_traces.png"
  fi
}

# The shipped policy as ONNX (observation normalisation inside) with its .json (the env it was
# trained in): the vehicle node and the replay load only these, never a pickle.
onnx() {
  say "exporting $POLICY to ONNX"
  "$BIN/rl" export --policy "$POLICY" --out "$WORK/policy.onnx"
  cp "$WORK/policy.onnx" "$WORK/policy.json" "$POLICY/"
  (cd "$POLICY" && sha256sum policy.onnx policy.json) >"$POLICY/onnx_checksums.sha256"
}

SHIP=${SHIP:-0}
[ "${2:-}" != --ship ] || SHIP=1
case "${1:-}" in
  models) models ;;
  models_ar1) models_ar1 ;;
  policy) policy ;;
  realistic) realistic ;;
  scratch) scratch ;;
  figures) figures ;;
  onnx) onnx ;;
  *) die "usage: bash scripts/make_artefacts.sh models|models_ar1|policy|realistic [--ship]|scratch [--ship]|figures|onnx" ;;
esac
say "done: review and commit what changed (git status)"
