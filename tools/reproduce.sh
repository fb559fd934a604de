#!/usr/bin/env bash
# Regenerate every table, number and figure README.md and docs/ quote, into results/ under the names they cite.
#
#   tools/reproduce.sh [--quick] [--ship] [--jobs N] [--only STEP[,STEP...]] [--dry-run] [--help]
#
# Modes
#   (default) full: retrain stage 1 and stage 2 into runs/reproduce/ (never into models/), then evaluate.
#     results/single_view, results/search, results/search_large and results/flight always describe the
#     checkpoints in models/ (what `uavsearch fly` uses): without --ship those are the shipped ones, so a
#     full run re-checks the shipped numbers and adds what only new runs give; results/training_seeds/
#     is about the new runs (stage 2 retrained with training seeds 0, 1, 2 on the new stage 1) and
#     evaluates runs/reproduce/.
#   --ship: after training, copy runs/reproduce/perception.pt and runs/reproduce/seed0/search_s*_*.pt
#     into models/, then evaluate those (results/ then describes the new shipped models).
#   --quick: no training and no large-split render; evaluates the shipped models/ only: Table I + Fig. 4,
#     Table II + Fig. 6 on the paper split's test scenes. It prints what it skipped.
#   --jobs N: stage-2 trainings in parallel (default 1; 2 on a 2-core machine).
#   --only STEP,...: run only these steps (names as listed by --dry-run); --dry-run: print the commands.
#
# Steps, their seeds and their cost. "measured": on the 2-core machine shared with other jobs (load average
# 3-7.6 while measuring); "estimate": from the README's figures, not measured by this script.
#   quick (all from the shipped models): measured 26 min the first time (762 CPU-s, almost all of it
#   rendering; ~7 min on an idle 2-core machine by that count), 45 s after.
#     single_view     Table I + Fig. 4: start view of 80 density-set scenes per row (seed 0 for the extra
#                     Fig. 4 views). measured: 1353 s the first time (renders 1440 views into
#                     data/views/density_v3_s0/), 38 s after.
#     search          Table II + Fig. 6, paper split, 10 test scenes per setting, evaluation seeds 0-4 x 10
#                     episodes. measured: 229 s the first time (renders 750 views into cache/), 7 s after.
#   full only:
#     lattice_views   every lattice view of the large split (1950 scenes x 25 positions = 48,750 views; stage
#                     1 trains on the 37,500 of the training scenes, stage 2 reads all of them).
#                     measured: 2613 s for train + val on the shared machine (load 3-9), ~1 s per scene idle.
#     train_perception  stage 1, seed 1, 5000 steps of 32 crops on the large split's training lattice views.
#                     measured: see docs/results.md (about 4 steps/s on two cores).
#     view_caches     perception outputs of the 25 lattice views of every paper- and large-split scene for
#                     the new stage 1. estimate: ~10 min (about 12 ms of CPU per view).
#     train_policy    stage 2, 5 fusions x 3 settings x training seeds 0, 1, 2 = 45 runs, 1200 iterations,
#                     large split. estimate: 3 x (3 x 150 s + 12 x 60 s) = ~60 min serial, ~35 min --jobs 2.
#     train_reactive  the reactive policy (DAgger + REINFORCE), settings 1-3 x training seeds 0, 1, 2, on the
#                     frozen confidence net of the same seed's learned-fusion run. measured: ~8 min per run
#                     on the shared machine (two at once).
#     ship            (--ship only) copy into models/. seconds.
#     perception      stage-1 targets on every lattice view of the large split's test scenes
#                     (results/perception/). measured: 12 s (after view_caches).
#     search_large    Table II + Fig. 6 on the large split's 100 test scenes per setting (seeds 0-4).
#                     estimate: ~8 min rendering 7500 views the first time (shipped perception), 35 s after.
#     wide_renders    every viewpoint (73) of the wide families' scenes: wide 50 val + 300 train + 100 test,
#                     wide-uniform 50 test + 20 val + 20 train. measured: 7-11 s wall per scene (2 workers,
#                     shared machine at load 4-6), 3.6 MB per scene.
#     train_perception_wide  stage 1 across altitudes: the paper's net fine-tuned on the 7,300 views of 100
#                     wide training scenes (seed 1, 1500 steps), then on the 21,900 of 300 (2000 steps, lower
#                     learning rate). measured: see docs/results.md.
#     train_map_wide  the wide family's learned policy (uavsearch train map), T = 8 and 240 s, seed 0, on the
#                     first 300 training scenes, on the calibrated fusion. measured: see docs/learning.md.
#     train_stack_wide the learned stack: the neighbour fusion reading cell features (uavsearch train fusion
#                     --features, seeds 0 and 1, per budget), then the policy of train_map_wide fine-tuned on
#                     their ensemble (uavsearch train map --init, REINFORCE only, the best on validation kept,
#                     the start included) -> $RUN/search_wide_*_map.pt. measured: see docs/learning.md.
#     map_gains       the wide policy fitted to the label teacher's gains of every viewpoint (T = 8, 100 and 200
#                     training scenes, 5 DAgger iterations, seed 0) -> results/map_policy/gains_T8/ and
#                     gains_T8_200/ (curves, metrics). measured: 653 s (beside a benchmark) and 669 s
#                     (2 threads, building the 200 scenes' perception cache).
#     map_probes      why the rule is hard to beat: other ways of choosing its descents (other scores, the
#                     expected gain of a view, per-cell gains learned from the label teacher), shorter surveys,
#                     and bounds that read the labels, paired against the rule on the 50 wide validation scenes,
#                     T = 8 and 240 s, models/perception_wide.pt -> results/map_policy/probes_T8.md and
#                     probes_240s.md. measured: see docs/learning.md.
#     fusion_probe    would a fusion that learns how a cell's views go together (and its neighbours') make better
#                     final maps than the calibrated one: learned corrections fitted on rule rollouts of the first
#                     300 wide training scenes, scored on the rule's 50 validation episodes, T = 8 and 240 s ->
#                     results/map_policy/fusion_probe_T8.md and fusion_probe_240s.md; and without the
#                     square's symmetries on 100 scenes -> fusion_probe_T8_100_no_symmetries.md. measured: about
#                     8 min each on the 2-core machine, after the 300 scenes' perception cache (5 min).
#     perception_flips the rule with the wide perception seeing each view four ways (test-time flips) against the
#                     shipped net on the 50 wide validation scenes, T = 8 and 240 s ->
#                     results/wide_study/perception_flips.md. measured: 22 s after the caches it builds.
#     perception_500  the wide net fine-tuned once more, on all 500 training scenes (seed 1, 2000 steps, lr 2e-4),
#                     against the shipped one under the rule on the 50 wide validation scenes ->
#                     results/wide_study/perception_500.md. measured: 659 s of training (16 GB of memory), 54 s
#                     of comparison after the renders of the 500 training scenes.
#     fusion_seeds    the learned neighbour fusion (`uavsearch train fusion`) over seeds 0-2 and their ensemble,
#                     the rule and the shipped map policy on them against the rule on the calibrated fusion, 50
#                     wide validation scenes -> results/wide_study/fusion_seeds_T8.md and fusion_seeds_240s.md.
#                     measured: 2019 s (T = 8, beside a perception training) and 1197 s (240 s) after the 300
#                     scenes' caches.
#     fusion_seeds_500  the 240 s neighbour fusion fitted on all 500 training scenes (seeds 0 and 1), their
#                     ensemble under the shipped map policy and under the policy it was fine-tuned from (97f6d16's),
#                     paired against the shipped stack -> results/wide_study/fusion_seeds_240s_500.md. measured:
#                     787-1122 s per fit (one thread, the two side by side; this step fits them one after the other) after the 500 scenes' caches (about 16
#                     minutes of rendering and 21 of perception the first time), 320 s to evaluate.
#     fusion_features_seeds  the neighbour fusion reading cell features (`uavsearch train fusion --features`),
#                     seeds 0 and 1, their ensemble, the rule and the shipped map policy on them ->
#                     results/wide_study/fusion_features_seeds_T8.md and _240s.md. measured: 1182-1723 s per fit
#                     (one thread, beside the other budget's fits and other jobs), 25-69 s to evaluate. Its "shipped
#                     map policy" rows were measured with the policies trained on the calibrated fusion (models/
#                     before the learned stack shipped); a rerun now flies the learned stack's nets there.
#     fusion_features the neighbour fusion reading the views' cell features beside their scores (the fusion
#                     probe with --features, T = 8, 300 training scenes, seeds 0 and 1) ->
#                     results/wide_study/features_T8.md. measured: 568 s after the caches (their feature store on disk).
#     perception_wide the wide net's targets per altitude on the 100 wide test scenes
#                     (results/perception_wide/), against the paper's net on the same views.
#     wide            Table III: wide on 100 test scenes (results/search_wide/), wide-uniform on 50
#                     (results/search_wide_uniform/), fusion (Bayes, average, or the calibrated fusion fitted on
#                     the training scenes) and the rule's survey chosen on validation, fixed view sets searched
#                     on 20 training scenes. measured: see docs/results.md.
#     team            teams of 1, 2, 3 vehicles on the 100 wide test scenes: AF1 against mission time, planners
#                     and fusions (hand-made and the learned stack's aggregation) chosen on 50 validation scenes
#                     (results/team_wide/), the same with hand-made fusions only (results/team_wide/hand_made/),
#                     the two paired (results/team_wide/learned_vs_hand_made.md), and 3-vehicle flights of the
#                     team mission on 5 test scenes against teleport (results/team_wide/flights.md).
#                     measured: 1603 s, 70 s, 354 s and 61 s on the quiet 2-core machine.
#     map_flights     the learned wide-area policy's mission (missions/wide.yaml) flown on the first 10 wide test
#                     scenes against teleport (results/map_policy/flights.md), and its routes against the rule's on
#                     the 100 test scenes (results/map_policy/routes.md). measured: see docs/results.md.
#     flight          flight vs teleport, settings 1-3, the 10 paper test scenes each, missions/default.yaml
#                     (vehicle seed 0, policy acting greedily), lockstep at speed max. measured: 652 s
#                     (load 6-7; ~5 min idle at ~10 s per flown mission). Every Aacc, F1 and route is the
#                     same on every run; the wall-time columns are the machine's.
#     training_seeds  Table II on the large split for the runs of each training seed, then the spread of the
#                     paper's method over seeds 0-2. estimate: ~2 min (after view_caches).
#
# Python: $PY (default .venv/bin/python, else python3), run from the repository root.
set -euo pipefail
cd "$(dirname "$0")/.."

usage() { sed -n '2,/^set -euo/p' "$0" | sed '$d' | sed 's/^# \{0,1\}//'; }

QUICK=0 SHIP=0 JOBS=1 DRY=0 ONLY=""
while [ $# -gt 0 ]; do
  case "$1" in
    --quick) QUICK=1 ;;
    --ship) SHIP=1 ;;
    --jobs) JOBS=${2:?--jobs needs a number}; shift ;;
    --jobs=*) JOBS=${1#--jobs=} ;;
    --only) ONLY=${2:?--only needs step names}; shift ;;
    --only=*) ONLY=${1#--only=} ;;
    --dry-run) DRY=1 ;;
    -h|--help) usage; exit 0 ;;
    *) echo "reproduce.sh: unknown option '$1' (see --help)" >&2; exit 2 ;;
  esac
  shift
done
case "$JOBS" in ''|*[!0-9]*|0) echo "reproduce.sh: --jobs must be a positive integer, not '$JOBS'" >&2; exit 2 ;; esac
if [ "$QUICK" = 1 ] && [ "$SHIP" = 1 ]; then
  echo "reproduce.sh: --ship needs the full mode (--quick trains nothing)" >&2; exit 2
fi
if [ -z "${PY:-}" ]; then
  if [ -x .venv/bin/python ]; then PY=.venv/bin/python; else PY=python3; fi
fi

RUN=runs/reproduce          # every trained checkpoint and every flight log of this script
SEEDS="0 1 2"               # training seeds of stage 2 (seed 0 is the one shipped)
SETTINGS="1 2 3"
FUSIONS="learned average bayes size oracle"
EVAL="--episodes 10 --seeds 5 --no-progress"   # evaluation: 10 episodes per test scene x seeds 0-4
UAV="$PY -m uavsearch"

# The perception stage 2 trains on and is evaluated with: the new one in full mode.
NEWPERC=$RUN/perception.pt
NEWPERC_WIDE=$RUN/perception_wide.pt   # the wide families' (trained across 70 m and 40 m)
# the learned wide-area policy's training (docs/learning.md), the same for both budgets
MAP_TRAIN="--train-scenes 300 --threads 1 --seed 0 --no-progress"

# ---------------------------------------------------------------------------------------------------
# Steps: name | mode (quick = also in --quick, full = full mode only, ship = --ship only) | what | command
STEPS=()
add() { STEPS+=("$1|$2|$3|$4"); }

add lattice_views full "render every lattice view of the large split into cache/lattice_views/ (resumable)" \
  "$PY -c \"from uavsearch.search.data.view_cache import CacheKey, render_lattice_views
[render_lattice_views(CacheKey(s, 'large', part), progress=False) for part in ('train', 'val', 'test') for s in (1, 2, 3)]\""
add train_perception full "stage 1 (seed 1, 5000 steps, the large split's training lattice views) -> $NEWPERC" \
  "$UAV train perception --seed 1 --runs-dir $RUN --out $NEWPERC --no-progress"
add view_caches full "perception outputs of every paper- and large-split lattice view for $NEWPERC" \
  "$PY -c \"from uavsearch.search.perception import load_perception; from uavsearch.search.data.view_cache import get_view_cache
net, _ = load_perception('$NEWPERC')
[get_view_cache(net, s, split, part, progress=False) for s in (1, 2, 3) for split in ('paper', 'large') for part in ('train', 'val', 'test')]\""
TRAIN_CMDS=""
for seed in $SEEDS; do for s in $SETTINGS; do for f in $FUSIONS; do
  TRAIN_CMDS+="$UAV train policy --setting $s --fusion $f --split large --seed $seed --perception $NEWPERC --runs-dir $RUN/policy_runs --progress false --out $RUN/seed$seed/search_s${s}_${f}.pt
"
done; done; done
add train_policy full "stage 2: 5 fusions x settings 1-3 x training seeds 0-2 -> $RUN/seed<S>/ ($JOBS in parallel)" \
  "printf '%s' \"\$TRAIN_CMDS\" | xargs -P $JOBS -I{} sh -c '{}'"
REACTIVE_CMDS=""
for seed in $SEEDS; do for s in $SETTINGS; do
  REACTIVE_CMDS+="$UAV train reactive --setting $s --seed $seed --perception $NEWPERC --confidence $RUN/seed$seed/search_s${s}_learned.pt --runs-dir $RUN/reactive_runs --progress false --out $RUN/seed$seed/search_s${s}_learned_reactive.pt
"
done; done
add train_reactive full "the reactive policy: settings 1-3 x training seeds 0-2 -> $RUN/seed<S>/ ($JOBS in parallel)" \
  "printf '%s' \"\$REACTIVE_CMDS\" | xargs -P $JOBS -I{} sh -c '{}'"
add wide_renders full "every viewpoint of the wide families' scenes (wide: 50 val, 300 train, 100 test; wide-uniform: 50 test, 20 val, 20 train; resumable)" \
  "$PY tools/render_wide.py --families wide --parts val --workers 2 && $PY tools/render_wide.py --families wide --parts train --scenes 300 --workers 2 && $PY tools/render_wide.py --families wide --parts test --workers 2 && $PY tools/render_wide.py --families wide-uniform --parts test --scenes 50 --workers 2 && $PY tools/render_wide.py --families wide-uniform --parts val,train --scenes 20 --workers 2"
add train_perception_wide full "stage 1 across altitudes in two fine-tunings (seed 1): the paper's net on every viewpoint of 100 wide training scenes (1500 steps, lr 1e-3), then that net on 300 (2000 steps, lr 3e-4) -> $NEWPERC_WIDE" \
  "$UAV train perception --settings wide --train-scenes 100 --val-scenes 4 --altitude-feature --init models/perception.pt --lr 1e-3 --steps 1500 --eval-every 300 --pos-weight 4 --positive-share 0.5 --seed 1 --threads 2 --runs-dir $RUN --out $RUN/perception_wide_100.pt --no-progress && $UAV train perception --settings wide --train-scenes 300 --val-scenes 10 --altitude-feature --init $RUN/perception_wide_100.pt --lr 3e-4 --steps 2000 --eval-every 250 --pos-weight 4 --positive-share 0.5 --seed 1 --threads 1 --runs-dir $RUN --out $NEWPERC_WIDE --no-progress"
add train_map_wide full "the wide family's learned policy, one per budget (DAgger from the rule + REINFORCE, seed 0, 300 training scenes) on $NEWPERC_WIDE -> $RUN/search_wide_*_map.pt" \
  "$UAV train map --budget 8 --fusion calibrated:0.25 --pg-iterations 300 $MAP_TRAIN --perception $NEWPERC_WIDE --runs-dir $RUN --out $RUN/map_wide_T8_calibrated.pt && $UAV train map --budget 240 --fusion calibrated:0.75 --pg-iterations 100 $MAP_TRAIN --perception $NEWPERC_WIDE --runs-dir $RUN --out $RUN/map_wide_240s_calibrated.pt"
add train_stack_wide full "the learned stack per budget: the feature-reading neighbour fusion (seeds 0 and 1) and the policy of train_map_wide fine-tuned on their ensemble, on $NEWPERC_WIDE -> $RUN/search_wide_*_map.pt" \
  "for b in 8 240; do t=\$( [ \$b = 8 ] && echo T8 || echo 240s ); for s in 0 1; do $UAV train fusion --budget \$b --features --train-scenes 300 --threads 1 --seed \$s --perception $NEWPERC_WIDE --runs-dir $RUN --no-progress --out $RUN/fusion_features_\${t}_s\$s.pt || exit 1; done; done && $UAV train map --budget 8 --fusion neighbour:$RUN/fusion_features_T8_s0.pt,$RUN/fusion_features_T8_s1.pt --init $RUN/map_wide_T8_calibrated.pt --dagger-iterations 0 --pg-iterations 60 --eval-every 15 $MAP_TRAIN --perception $NEWPERC_WIDE --runs-dir $RUN --out $RUN/search_wide_T8_map.pt && $UAV train map --budget 240 --fusion neighbour:$RUN/fusion_features_240s_s0.pt,$RUN/fusion_features_240s_s1.pt --init $RUN/map_wide_240s_calibrated.pt --dagger-iterations 0 --pg-iterations 30 --eval-every 10 $MAP_TRAIN --perception $NEWPERC_WIDE --runs-dir $RUN --out $RUN/search_wide_240s_map.pt"
add map_gains full "the wide policy fitted to the label teacher's gains (T = 8, 100 and 200 training scenes, seed 0) on $NEWPERC_WIDE -> results/map_policy/gains_T8*/" \
  "for n in 100 200; do sfx=\$( [ \$n = 100 ] || echo _\$n ); thr=\$( [ \$n = 100 ] && echo 1 || echo 2 ); rm -rf $RUN/map_gains_\$n && $UAV train map --budget 8 --fusion calibrated:0.25 --train-scenes \$n --teacher labels --imitate gains --dagger-iterations 5 --pg-iterations 0 --threads \$thr --seed 0 --name gainsT8\$sfx --perception $NEWPERC_WIDE --runs-dir $RUN/map_gains_\$n --no-progress && mkdir -p results/map_policy/gains_T8\$sfx && cp $RUN/map_gains_\$n/*/metrics.csv $RUN/map_gains_\$n/*/learning_curve.png $RUN/map_gains_\$n/*/summary.json results/map_policy/gains_T8\$sfx/ || exit 1; done"
add map_probes full "other ways of choosing the rule's descents, shorter surveys and label bounds against the rule (50 wide validation scenes, T = 8 and 240 s) -> results/map_policy/probes_*.md" \
  "$PY tools/wide_policy_probes.py --budget 8 --out results/map_policy/probes_T8.md && $PY tools/wide_policy_probes.py --budget 240 --out results/map_policy/probes_240s.md"
add fusion_probe full "learned fusions over each cell's views and its neighbours against the calibrated one (rule episodes, 50 wide validation scenes, T = 8 and 240 s) -> results/map_policy/fusion_probe_*.md" \
  "$PY tools/wide_fusion_probe.py --budget 8 --train-scenes 300 --out results/map_policy/fusion_probe_T8.md && $PY tools/wide_fusion_probe.py --budget 240 --train-scenes 300 --out results/map_policy/fusion_probe_240s.md && $PY tools/wide_fusion_probe.py --budget 8 --train-scenes 100 --epochs 60 --no-symmetries --out results/map_policy/fusion_probe_T8_100_no_symmetries.md"
add perception_flips full "test-time flips of the wide perception against the shipped net (the rule, 50 wide validation scenes, T = 8 and 240 s) -> results/wide_study/perception_flips.md" \
  "$PY tools/wide_perception_compare.py --out results/wide_study/perception_flips.md"
add perception_500 full "the wide net fine-tuned on all 500 training scenes against the shipped one (the rule, 50 wide validation scenes) -> results/wide_study/perception_500.md" \
  "$PY tools/render_wide.py --families wide --parts train --scenes 500 --workers 2 && $UAV train perception --settings wide --train-scenes 500 --val-scenes 10 --altitude-feature --init models/perception_wide.pt --lr 2e-4 --steps 2000 --eval-every 250 --pos-weight 4 --positive-share 0.5 --seed 1 --threads 1 --runs-dir $RUN --out $RUN/perception_wide_500.pt --no-progress && $PY tools/wide_perception_compare.py --candidate $RUN/perception_wide_500.pt --out results/wide_study/perception_500.md"
add fusion_features full "the neighbour fusion on per-view cell features beside the scores (final maps of the rule, 50 wide validation scenes, T = 8) -> results/wide_study/features_T8.md" \
  "$PY tools/wide_fusion_probe.py --budget 8 --train-scenes 300 --features --out results/wide_study/features_T8.md"
add fusion_features_seeds full "the neighbour fusion reading cell features over seeds 0 and 1 and their ensemble against the calibrated one (the rule and the shipped map policy, 50 wide validation scenes, T = 8 and 240 s) -> results/wide_study/fusion_features_seeds_*.md" \
  "$PY tools/wide_fusion_seeds.py --budget 8 --seeds 0 1 --features --threads 1 --out results/wide_study/fusion_features_seeds_T8.md && $PY tools/wide_fusion_seeds.py --budget 240 --seeds 0 1 --features --threads 1 --out results/wide_study/fusion_features_seeds_240s.md"
add fusion_seeds full "the learned neighbour fusion over seeds 0-2 against the calibrated one (the rule and the shipped map policy, 50 wide validation scenes, T = 8 and 240 s) -> results/wide_study/fusion_seeds_*.md" \
  "$PY tools/wide_fusion_seeds.py --budget 8 --seeds 0 1 2 --out results/wide_study/fusion_seeds_T8.md && $PY tools/wide_fusion_seeds.py --budget 240 --seeds 0 1 2 --out results/wide_study/fusion_seeds_240s.md"
add fusion_seeds_500 full "the 240 s neighbour fusion on all 500 training scenes (seeds 0 and 1) and its ensemble under the shipped map policy and its start, paired against the shipped stack (50 wide validation scenes) -> results/wide_study/fusion_seeds_240s_500.md" \
  "git show 97f6d16:models/search_wide_240s_map.pt > $RUN/map_wide_240s_calibrated_shipped.pt && $PY tools/wide_fusion_seeds.py --budget 240 --seeds 0 1 --train-scenes 500 --threads 1 --runs-dir $RUN/fusion500 --start $RUN/map_wide_240s_calibrated_shipped.pt --out results/wide_study/fusion_seeds_240s_500.md"
add ship ship "copy $NEWPERC, $NEWPERC_WIDE, $RUN/seed0/search_s*_*.pt and $RUN/search_wide_*_map.pt into models/" \
  "cp $NEWPERC models/perception.pt && cp $NEWPERC_WIDE models/perception_wide.pt && cp $RUN/seed0/search_s*_*.pt $RUN/search_wide_*_map.pt models/"
add single_view quick "Table I + Fig. 4 from models/perception.pt -> results/single_view/" \
  "$UAV eval single-view --checkpoint models/perception.pt --scenes-per-pair 80 --views-per-scene 3 --seed 0 --out results/single_view --no-progress"
add perception full "stage-1 targets on the large split's test views, models/perception.pt -> results/perception/" \
  "$UAV eval perception --split large --part test --perception models/perception.pt --out results/perception --no-progress"
add search quick "Table II + Fig. 6, paper split, models/ -> results/search/" \
  "$UAV eval search --setting all --split paper --perception models/perception.pt --models-dir models $EVAL --out results/search"
add search_large full "Table II + Fig. 6, large split (100 test scenes), models/ -> results/search_large/" \
  "$UAV eval search --setting all --split large --perception models/perception.pt --models-dir models $EVAL --out results/search_large && $PY tools/route_diversity.py --out results/search_large/routes.md"
add perception_wide full "the wide net against its targets per altitude (test views), models/perception_wide.pt -> results/perception_wide/" \
  "$UAV eval perception --setting wide --part test --out results/perception_wide --no-progress"
add wide full "Table III: wide (100 test scenes) and wide-uniform (50), models/perception_wide.pt -> results/search_wide/, results/search_wide_uniform/" \
  "$UAV eval search --setting wide --wide-train-scenes 20 --episodes 10 --seeds 2 --no-progress --out results/search_wide && $UAV eval search --setting wide-uniform --wide-test-scenes 50 --wide-val-scenes 20 --wide-train-scenes 20 --episodes 10 --seeds 2 --no-progress --out results/search_wide_uniform"
add team full "teams of 1-3 vehicles on the wide test scenes, with and without the learned aggregation, paired; flown 3-vehicle missions vs teleport -> results/team_wide/" \
  "$UAV eval team --setting wide --wide-val-scenes 50 --no-progress --out results/team_wide && $UAV eval team --setting wide --wide-val-scenes 50 --learned none --no-progress --out results/team_wide/hand_made && $PY tools/team_learned_vs_hand_made.py --out results/team_wide/learned_vs_hand_made.md && $PY tools/wide_flights.py --mission missions/wide_team.yaml --scenes 5 --out results/team_wide/flights.md"
add map_flights full "the learned wide-area policy flown (missions/wide.yaml) on 10 wide test scenes against teleport, and its routes against the rule's -> results/map_policy/" \
  "$PY tools/wide_flights.py --scenes 10 --out results/map_policy/flights.md && $PY tools/wide_routes.py --out results/map_policy/routes.md"
FLIGHT_CMD=""
for s in $SETTINGS; do
  FLIGHT_CMD+="rm -rf $RUN/flight_s$s && $UAV eval search --vehicle mavlink --setting $s --split paper --speed max --no-progress --out $RUN/flight_s$s && mkdir -p results/flight && cp $RUN/flight_s$s/flight_vs_teleport.md results/flight/flight_vs_teleport_s$s.md && "
done
add flight full "flight vs teleport, settings 1-3, models/ (flight logs in $RUN/flight_s<K>/) -> results/flight/" "${FLIGHT_CMD}true"
SEED_CMD=""
for seed in $SEEDS; do
  SEED_CMD+="$UAV eval search --setting all --split large --perception $NEWPERC --models-dir $RUN/seed$seed $EVAL --out results/training_seeds/seed$seed && "
done
add training_seeds full "Table II (large split) of the runs of training seeds 0-2 and their spread -> results/training_seeds/" \
  "${SEED_CMD}$PY tools/seed_spread.py results/training_seeds/seed0 results/training_seeds/seed1 results/training_seeds/seed2 --out results/training_seeds/spread.md"

# ---------------------------------------------------------------------------------------------------
selected=() skipped=()
for st in "${STEPS[@]}"; do
  IFS='|' read -r name mode _ _ <<<"$st"
  if [ -n "$ONLY" ]; then
    case ",$ONLY," in *",$name,"*) selected+=("$st") ;; *) skipped+=("$name (not in --only)") ;; esac
    continue
  fi
  case "$mode" in
    quick) selected+=("$st") ;;
    full) if [ "$QUICK" = 1 ]; then skipped+=("$name (full mode only)"); else selected+=("$st"); fi ;;
    ship) if [ "$SHIP" = 1 ]; then selected+=("$st"); else skipped+=("$name (without --ship models/ is left alone)"); fi ;;
  esac
done
if [ -n "$ONLY" ]; then
  for n in ${ONLY//,/ }; do
    printf '%s\n' "${STEPS[@]}" | grep -q "^$n|" || { echo "reproduce.sh: unknown step '$n'" >&2; exit 2; }
  done
fi

n=${#selected[@]}
mode_name=$([ -n "$ONLY" ] && echo "only $ONLY" || { [ "$QUICK" = 1 ] && echo quick || echo full; })$([ "$SHIP" = 1 ] && echo " + ship" || true)
echo "reproduce.sh: $mode_name mode, $n step(s), python $PY"
if [ "$DRY" = 1 ]; then
  i=0
  for st in "${selected[@]}"; do
    i=$((i + 1)); IFS='|' read -r name _ what cmd <<<"$st"
    echo "[$i/$n] $name: $what"
    case "$name" in
      train_policy) printf '%s' "$TRAIN_CMDS" | sed 's/^/  /' ;;
      train_reactive) printf '%s' "$REACTIVE_CMDS" | sed 's/^/  /' ;;
      *) echo "  $cmd" ;;
    esac
  done
  for s in "${skipped[@]}"; do echo "skip: $s"; done
  exit 0
fi

START=$(date +%s)
stamp=$(mktemp); trap 'rm -f "$stamp"' EXIT
mkdir -p results "$RUN"
elapsed() { local t=$(( $(date +%s) - START )); printf '%02d:%02d' $((t / 60)) $((t % 60)); }
i=0
for st in "${selected[@]}"; do
  i=$((i + 1)); IFS='|' read -r name _ what cmd <<<"$st"
  echo "[$i/$n] $name: $what (elapsed $(elapsed))"
  t0=$(date +%s)
  TRAIN_CMDS="$TRAIN_CMDS" REACTIVE_CMDS="$REACTIVE_CMDS" bash -c "set -euo pipefail; $cmd" || { echo "reproduce.sh: step $name failed (elapsed $(elapsed))" >&2; exit 1; }
  echo "[$i/$n] $name done in $(( $(date +%s) - t0 )) s (elapsed $(elapsed))"
done

echo
echo "Done in $(elapsed) ($mode_name mode). Files written under results/:"
printf '%-48s %10s\n' file bytes
find results -type f -newer "$stamp" | sort | while read -r f; do printf '%-48s %10s\n' "$f" "$(wc -c <"$f")"; done
for s in "${skipped[@]}"; do echo "skipped: $s"; done
