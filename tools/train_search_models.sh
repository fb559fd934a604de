#!/usr/bin/env bash
# Retrain every shipped stage-2 model (models/search_s<K>_<fusion>.pt): the paper's method (learned
# fusion) and the four "+ policy" baselines, for settings 1-3, then evaluate Table II / Fig. 6.
# Needs models/perception.pt (stage 1). Usage: tools/train_search_models.sh [SEED] [JOBS] [SPLIT]
#   SEED: training seed (default 0); JOBS: runs in parallel (default 1; 2 on a 2-core machine);
#   SPLIT: the scenes stage 2 trains on (train part) and selects on (val part): large (default; 500 + 50
#   scenes per setting, the shipped models) or paper (20 + 10, which overfits). Evaluation is always on
#   the paper split's test scenes (and, with the large split, also on the large split's 100 test scenes).
set -euo pipefail
cd "$(dirname "$0")/.."
SEED=${1:-0}
JOBS=${2:-1}
SPLIT=${3:-large}
PY=${PY:-.venv/bin/python}
# Build the view caches once, serially (rendering is the only slow part and uses 2 processes itself).
for s in 1 2 3; do
  $PY -c "from uavsearch.search.perception import load_perception; from uavsearch.search.view_cache import get_view_cache
net, _ = load_perception('models/perception.pt')
for part in ('train', 'val', 'test'): get_view_cache(net, $s, 'paper', part)
if '$SPLIT' != 'paper':
    for part in ('train', 'val', 'test'): get_view_cache(net, $s, '$SPLIT', part)"
done
for s in 1 2 3; do for f in learned average bayes size oracle; do
  echo "$PY -m uavsearch.search.train_policy --setting $s --fusion $f --split $SPLIT --seed $SEED --progress false --out models/search_s${s}_${f}.pt"
done; done | xargs -P "$JOBS" -I{} sh -c '{}'
$PY -m uavsearch.search.eval_search --setting all --out results/search
if [ "$SPLIT" != paper ]; then
  $PY -m uavsearch.search.eval_search --setting all --split "$SPLIT" --out "results/search_$SPLIT"
fi
